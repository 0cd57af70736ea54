"""Resampling a suspect onto the original, and estimating the watermark displacement.

Two ways from a registered suspect to the coefficient differences r-hat - r:

``snap_to_original`` is the paper's resampling: each original point p_j takes
the coordinates of its nearest suspect point if that is closer than
d_r = 1/2 of p_j's nearest-neighbour distance in the original, else keeps its
own.  The differences are then E^T (P'' - P).

``fit_spectral_displacement`` goes beyond it: the unknown differences X
(n_coefficients x 3) of all clusters are fitted by weighted least squares so
that the original, deformed by E X, passes through the suspect points.  Each
suspect point pulls on its nearest deformed original point; the pull is split
into the normal part and the tangential part, weighted by the inverse of
their measured variances (point-to-plane when the suspect was resampled,
point-to-point when its points are the original's).  Matches whose normal
misfit exceeds ``trim`` robust standard deviations, and more than the mark
itself can move a point, are left out (a skipped estimator: junk points near
the surface would otherwise pull the fit).  A small
ridge keeps clusters with few suspect points well posed.  The fit is repeated
with the correspondences of the deformed original.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sl
from scipy.spatial import cKDTree

__all__ = [
    "nearest_spacing", "estimate_normals", "snap_to_original", "fit_spectral_displacement",
    "normal_noise", "normal_gram",
]


def nearest_spacing(points):
    """Distance from each point to its nearest other point at a different place.

    Repeated points (the same coordinates stored twice) do not count as
    neighbours: the spacing of a file whose every point is present twice is
    the spacing of its distinct points, never 0.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    (n,) float
        0 only when all points are identical.
    """
    points = np.asarray(points, dtype=np.float64)
    unique, inverse = np.unique(points, axis=0, return_inverse=True)
    if len(unique) < 2:
        return np.zeros(len(points))
    dist, _ = cKDTree(unique).query(unique, k=2)
    return dist[np.asarray(inverse).reshape(-1), 1]


def estimate_normals(points, k=16, at=None, *, tree=None, chunk=65536):
    """Unoriented normals by local principal component analysis.

    Computed ``chunk`` points at a time, so peak memory stays near
    ``chunk * k * 3`` floats however large the cloud (each point's normal
    is the same as when computed all at once).

    Parameters
    ----------
    points : (n, 3) float
    k : int
        Neighbourhood size.
    at : (l,) int, optional
        Only the normals of these points (their neighbours are still taken
        from all of ``points``).
    tree : cKDTree over ``points``, optional
        Built here when not given.
    chunk : int

    Returns
    -------
    (n, 3) or (l, 3) float, unit rows
    """
    k = min(k, len(points))
    tree = cKDTree(points) if tree is None else tree
    queries = points if at is None else points[at]
    out = np.empty((len(queries), 3))
    for start in range(0, len(queries), chunk):
        _, idx = tree.query(queries[start:start + chunk], k=k)
        nbrs = points[idx]                                  # (c, k, 3)
        centred = nbrs - nbrs.mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", centred, centred)   # (c, 3, 3)
        out[start:start + chunk] = np.linalg.eigh(cov)[1][:, :, 0]   # smallest-variance direction
    return out


def snap_to_original(original, suspect):
    """The paper's resampling of the suspect onto the original.

    Parameters
    ----------
    original : (n, 3) float
    suspect : (m, 3) float, registered

    Returns
    -------
    resampled : (n, 3) float
        P'': each original point replaced by its nearest suspect point within d_r.
    matched : (n,) bool
    """
    threshold = 0.5 * nearest_spacing(original)
    dist, idx = cKDTree(suspect).query(original)
    matched = dist < threshold
    resampled = original.copy()
    resampled[matched] = suspect[idx[matched]]
    return resampled, matched


def normal_gram(basis, normals):
    """G^T G of one cluster's normal-only model, G = [n_x E | n_y E | n_z E].

    When every original point is matched by exactly one suspect point, the
    normal equations of the normal-only fit are G^T G / var; otherwise they
    differ from it only at the points matched other than once, so this is
    computed once per original (the basis store keeps it).

    Parameters
    ----------
    basis : (n_c, K) float
    normals : (n_c, 3) float, the original's unit normals at the cluster's points

    Returns
    -------
    (3K, 3K) float
    """
    g = np.concatenate([normals[:, a:a + 1] * basis for a in range(3)], axis=1)
    return g.T @ g


def fit_spectral_displacement(original, normals, suspect, clusters, bases, *,
                              iterations, ridge, tangential_gate, ratio_gate, gate_switch, cut=None,
                              normal_only=False, grams=None, spacing=None, trim=None, reach=None):
    """Least-squares coefficient differences of every cluster.

    Parameters
    ----------
    original : (n, 3) float
    normals : (n, 3) float, unit
    suspect : (m, 3) float, registered onto ``original``
    clusters : list of (n_c,) int
        Point indices of each cluster.
    bases : list of (n_c, K) float
        Spectral basis E of each cluster.
    iterations : int
    ridge : float
        Ridge weight relative to the mean diagonal of the normal equations.
    cut : float, optional
        Suspect points farther than this from the deformed original are
        ignored (default: 4 times the original's median spacing).
    tangential_gate, ratio_gate, gate_switch : float
        Which matches also constrain tangential motion.  While the suspect's
        noise across the surface is below ``gate_switch`` times the median
        spacing, a match whose nearest distance is under ``ratio_gate`` times
        its second-nearest (unambiguous); above it, only matches closer than
        ``tangential_gate`` times the local spacing.  ``gate_switch=0`` always
        uses the fixed gate, ``inf`` always the ratio.
    normal_only : bool
        The watermark moved points along their normals only (``along_normals``):
        the model is then original + n n^T E X, fitted from the normal misfit
        alone; the gates are not used.
    grams : list of (3K, 3K) float, optional
        :func:`normal_gram` of each cluster with ``normals``; with
        ``normal_only`` the normal equations are updated from it at the points
        matched other than once instead of being summed over every point.
    spacing : (n,) float, optional
        :func:`nearest_spacing` of ``original`` (computed when not given).
    trim : float, optional
        Leave out, per cluster and iteration, the matches whose misfit along
        the normal is over ``trim`` times its root median square (at least 1,
        so that half the matches always stay) and over the ``reach`` of
        the point matched.  None keeps every match.
    reach : (n,) float, optional
        Misfit along the normal that the watermark itself can cause at each
        original point: a match within it is always kept, however many
        matches have no misfit at all (an unmarked original beside the copy).

    Returns
    -------
    deltas : list of (K, 3) float
        Estimated r-hat - r per cluster.
    support : list of int
        Suspect points used per cluster (last iteration).
    """
    if trim is not None and not trim >= 1.0:
        raise ValueError(f"trim must be at least 1 (got {trim})")
    reach = np.zeros(len(original)) if reach is None else np.asarray(reach, dtype=np.float64)
    spacing = nearest_spacing(original) if spacing is None else spacing
    if cut is None:
        cut = 4.0 * float(np.median(spacing))
    deltas = [np.zeros((e.shape[1], 3)) for e in bases]
    support = [0] * len(clusters)
    owner = np.full(len(original), -1, dtype=np.int64)   # cluster of each original point
    for c, members in enumerate(clusters):
        owner[members] = c
    use_ratio = None                                      # decided on the first matches
    for _ in range(iterations):
        deformed = original.copy()
        for members, basis, delta in zip(clusters, bases, deltas):
            moved = basis @ delta
            if normal_only:
                moved = np.einsum("ki,ki->k", moved, normals[members])[:, None] * normals[members]
            deformed[members] += moved
        dist2, nearest2 = cKDTree(deformed).query(suspect, k=2)
        dist, nearest = dist2[:, 0], nearest2[:, 0]
        near = dist < cut
        if use_ratio is None and not normal_only:
            noise = normal_noise(suspect[near], original[nearest[near]], normals[nearest[near]])
            use_ratio = noise < gate_switch * float(np.median(spacing))
        for c, (members, basis) in enumerate(zip(clusters, bases)):
            pick = near & (owner[nearest] == c)
            support[c] = int(pick.sum())
            if support[c] == 0:
                deltas[c] = np.zeros_like(deltas[c])
                continue
            if normal_only:
                reliable = np.zeros(int(pick.sum()), dtype=bool)
            elif use_ratio:
                reliable = dist[pick] < ratio_gate * dist2[pick, 1]
            else:
                reliable = dist[pick] < tangential_gate * spacing[nearest[pick]]
            deltas[c] = _solve_cluster(
                original, normals, deformed, suspect[pick], nearest[pick], reliable, members,
                basis, ridge, gram=grams[c] if (grams is not None and normal_only) else None,
                trim=None if trim is None else (trim, reach[nearest[pick]]),
            )
    return deltas, support


def normal_noise(points, targets, normals):
    """Robust standard deviation of the offsets along the normals.

    Parameters
    ----------
    points, targets : (k, 3) float
        Matched suspect and original points.
    normals : (k, 3) float, unit normals at ``targets``.

    Returns
    -------
    float
        Median absolute deviation of the normal offsets, scaled to a standard
        deviation (0 when there are no matches).
    """
    if len(points) == 0:
        return 0.0
    offset = np.einsum("ki,ki->k", points - targets, normals)
    return 1.4826 * float(np.median(np.abs(offset - np.median(offset))))


def _solve_cluster(original, normals, deformed, points, targets, reliable, members, basis, ridge, gram=None,
                   trim=None):
    """One weighted least-squares solve for a cluster's coefficient differences.

    ``trim`` is None or (factor, reach at each target): see :func:`fit_spectral_displacement`.
    """
    local = np.full(len(original), -1, dtype=np.int64)
    local[members] = np.arange(len(members))
    j = local[targets]
    n = normals[targets]
    residual = points - original[targets]               # what the displacement must explain
    current = points - deformed[targets]                # misfit of the current estimate
    normal_part = np.einsum("ki,ki->k", current, n)
    tangential = current - normal_part[:, None] * n
    var_n = max(float(np.median(normal_part**2)), 1e-30)
    kept = None
    if trim is not None:
        kept = (normal_part**2 <= np.maximum(trim[0] ** 2 * var_n, trim[1] ** 2)).astype(float)
    outer = n[:, :, None] * n[:, None, :]               # (k, 3, 3)
    weight = outer / var_n
    if reliable.any():
        # tangential misfit only where the match is unambiguous: a nearest
        # neighbour chosen among several candidates biases it towards zero
        var_t = max(float(np.median((tangential[reliable] ** 2).sum(axis=1)) / 2.0), var_n)
        weight = weight + reliable[:, None, None] * (np.eye(3) - outer) / var_t
    if kept is not None:
        weight = weight * kept[:, None, None]
    size = len(members)
    # the cluster points matched: the others add nothing to either side of the equations
    rows, at = np.unique(j, return_inverse=True)
    matched = basis[rows]
    rhs_points = np.zeros((len(rows), 3))
    np.add.at(rhs_points, at, np.einsum("kab,kb->ka", weight, residual))
    k = basis.shape[1]
    if gram is not None and not reliable.any():
        counts = np.bincount(j, weights=kept, minlength=size)
        normal_matrix = _normal_matrix_from_gram(gram, counts, normals[members], basis) / var_n
    else:
        m = np.zeros((len(rows), 3, 3))
        np.add.at(m, at, weight)
        normal_matrix = np.empty((3 * k, 3 * k))
        for a in range(3):
            for b in range(a, 3):
                block = matched.T @ (m[:, a, b][:, None] * matched)
                normal_matrix[a * k:(a + 1) * k, b * k:(b + 1) * k] = block
                normal_matrix[b * k:(b + 1) * k, a * k:(a + 1) * k] = block
    rhs = (matched.T @ rhs_points).T.reshape(-1)        # [axis x | axis y | axis z]
    lam = ridge * float(np.trace(normal_matrix)) / (3 * k)
    normal_matrix[np.diag_indices_from(normal_matrix)] += lam
    solution = sl.solve(normal_matrix, rhs, assume_a="pos")
    return solution.reshape(3, k).T


def _normal_matrix_from_gram(gram, counts, normals, basis):
    """sum_j counts_j g_j g_j^T, from whichever takes fewer rows of g_j = [n_j,x e_j | n_j,y e_j | n_j,z e_j].

    G^T G + G_d^T diag(counts - 1) G_d over the points with counts != 1 (a
    whole copy: nearly every point matched once), or the sum itself over the
    points matched at all (a part of the original, or a shape that is not
    it, lying on a few of the cluster's points).  ``counts`` (n_c,): matches
    (kept) per cluster point.
    """
    other = np.flatnonzero(counts != 1)
    if len(other) == 0:
        return gram.copy()
    matched = np.flatnonzero(counts)
    if len(matched) < len(other):
        g = np.concatenate([normals[matched, a:a + 1] * basis[matched] for a in range(3)], axis=1)
        return g.T @ (counts[matched][:, None] * g)
    g = np.concatenate([normals[other, a:a + 1] * basis[other] for a in range(3)], axis=1)
    return gram + g.T @ ((counts[other] - 1.0)[:, None] * g)
