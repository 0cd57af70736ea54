"""Registration of a suspect point set onto the original (paper, "Point Set Registration").

``register_covariance`` is the paper's method: centroids, principal axes
(covariance matrix, as in Gottschalk's OBB) and a scale from the spread along
them.  Axis signs are ambiguous; the four proper sign choices are scored by
the median distance to the original.

``register_robust`` goes further: identity and all 24 axis-aligned rotations
of the principal frame are each refined by trimmed ICP with scale
(Umeyama's closed form on nearest neighbours, pairs beyond a robust cut
dropped, so partial overlap does not pull), and the best fit wins.

``rotation_search`` needs no features: at a known scale it tries a fixed
set of rotations and finds each one's best translation by an FFT
correlation of voxel grids (as protein docking does).  It registers parts of
smooth shapes, where local descriptors are all alike.

``connected_parts`` splits a scene into the objects it holds (points closer
than a few spacings are linked), so an asset placed among other objects can
be registered whole-to-whole by ``register_robust``, the way a whole copy is.

A transform maps suspect coordinates x to ``scale * x @ rotation.T + translation``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

__all__ = [
    "Similarity", "apply", "umeyama", "principal_frame", "register_covariance", "symmetry_axes", "fine_turns",
    "icp_similarity", "register_robust", "umeyama_batch", "ransac_similarity", "overlap",
    "refine_part", "refine_plane", "rotation_search", "connected_parts", "separate_objects", "shape_signature",
    "poses_alike", "lies_on", "closeness", "roughness", "distinct_poses",
]

MAX_STEP = 0.5   # refine_plane: largest scale change and rotation (rad) of one linearised step


@dataclass(frozen=True)
class Similarity:
    """x -> scale * R x + t, with fit quality against the original."""

    rotation: np.ndarray
    scale: float
    translation: np.ndarray
    fitness: float = float("nan")    # share of suspect points within the inlier cut
    residual: float = float("nan")   # RMS inlier distance, in original units


def apply(transform, points):
    """Apply a :class:`Similarity` to (n, 3) points."""
    return transform.scale * points @ transform.rotation.T + transform.translation


def umeyama(source, target, *, with_scale=True):
    """Least-squares similarity mapping ``source`` onto ``target`` (Umeyama 1991).

    Parameters
    ----------
    source, target : (n, 3) float, corresponding rows

    Returns
    -------
    Similarity
    """
    mu_s = source.mean(axis=0)
    mu_t = target.mean(axis=0)
    xs = source - mu_s
    xt = target - mu_t
    cov = xt.T @ xs / len(source)
    u, d, vt = np.linalg.svd(cov)
    flip = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        flip[2, 2] = -1.0
    rotation = u @ flip @ vt
    var_s = (xs**2).sum() / len(source)
    scale = float((d * np.diag(flip)).sum() / var_s) if with_scale and var_s > 0 else 1.0
    translation = mu_t - scale * rotation @ mu_s
    return Similarity(rotation, scale, translation)


def principal_frame(points):
    """Centroid, principal axes (columns, descending variance) and RMS spread.

    Returns
    -------
    centroid : (3,) float
    axes : (3, 3) float, right-handed
    spread : float
    """
    centroid = points.mean(axis=0)
    centred = points - centroid
    values, vectors = np.linalg.eigh(centred.T @ centred / len(points))
    axes = vectors[:, ::-1]
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1.0
    return centroid, axes, float(np.sqrt(values.sum()))


def _frame_hypotheses(suspect, original, rotations):
    cs, axes_s, spread_s = principal_frame(suspect)
    co, axes_o, spread_o = principal_frame(original)
    scale = spread_o / spread_s if spread_s > 0 else 1.0
    for flip in rotations:
        rotation = axes_o @ flip @ axes_s.T
        yield Similarity(rotation, scale, co - scale * rotation @ cs)


def _score(tree, moved, cut):
    dist, _ = tree.query(moved)
    inside = dist < cut
    fitness = float(inside.mean())
    residual = float(np.sqrt((dist[inside] ** 2).mean())) if inside.any() else float("inf")
    return fitness, residual, float(np.median(dist))


def _sign_flips():
    """The 4 proper diagonal sign matrices."""
    return [np.diag(s) for s in itertools.product((1.0, -1.0), repeat=3) if np.prod(s) > 0]


def _axis_rotations():
    """The 24 proper rotations that permute and flip coordinate axes."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    return out


def register_covariance(suspect, original, *, spacing):
    """The paper's covariance-based similarity registration.

    Parameters
    ----------
    suspect : (n, 3) float
    original : (m, 3) float
    spacing : float
        Typical nearest-neighbour distance of the original (sets the inlier cut).

    Returns
    -------
    Similarity
    """
    tree = cKDTree(original)
    best = None
    for hyp in _frame_hypotheses(suspect, original, _sign_flips()):
        fitness, residual, median = _score(tree, apply(hyp, suspect), 3.0 * spacing)
        if best is None or median < best[0]:
            best = (median, Similarity(hyp.rotation, hyp.scale, hyp.translation, fitness, residual))
    return best[1]


def icp_similarity(suspect, tree, original, start, *, spacing, iterations=40, trim=0.9):
    """Trimmed ICP with scale from a starting similarity.

    Each step pairs every moved suspect point with its nearest original point,
    keeps pairs within ``max(3 * spacing, trim-quantile)`` of the distance
    distribution, and solves Umeyama's similarity on them.

    Returns
    -------
    Similarity
        With ``fitness`` (share of suspect points within 3 * spacing) and
        ``residual`` (RMS distance of those points).
    """
    current = start
    previous = np.inf
    for _ in range(iterations):
        moved = apply(current, suspect)
        dist, idx = tree.query(moved)
        cut = max(3.0 * spacing, float(np.quantile(dist, trim)))
        keep = dist <= cut
        if keep.sum() < 4:
            break
        step = umeyama(moved[keep], original[idx[keep]])
        current = _compose(step, current)
        err = float(np.sqrt((dist[keep] ** 2).mean()))
        if previous - err < 1e-6 * spacing:
            break
        previous = err
    fitness, residual, _ = _score(tree, apply(current, suspect), 3.0 * spacing)
    return Similarity(current.rotation, current.scale, current.translation, fitness, residual)


def _compose(outer, inner):
    return Similarity(
        outer.rotation @ inner.rotation,
        outer.scale * inner.scale,
        outer.scale * outer.rotation @ inner.translation + outer.translation,
    )


def register_robust(suspect, original, *, spacing, coarse_points=1500, rng=0, tree=None):
    """Registration that survives removal, resampling, noise and cropping.

    Hypotheses: identity, and the 24 axis-aligned rotations between principal
    frames.  Each is refined by ICP with scale on a subsample; identity is
    kept at once when it already fits (most inliers, residual under the
    spacing).  The best hypothesis (most inliers, then lowest residual) is
    refined on all points.

    Parameters
    ----------
    suspect : (n, 3) float
    original : (m, 3) float
    spacing : float
    coarse_points : int
        Subsample size for scoring the hypotheses.
    rng : int or numpy.random.Generator
        Seeds the subsample.
    tree : cKDTree over ``original``, or any tree with its ``query``
        Built here when None.

    Returns
    -------
    Similarity
    """
    rng = np.random.default_rng(rng)
    tree = cKDTree(original) if tree is None else tree
    sub = suspect
    if len(suspect) > coarse_points:
        sub = suspect[np.sort(rng.choice(len(suspect), coarse_points, replace=False))]
    identity = Similarity(np.eye(3), 1.0, np.zeros(3))
    frames = list(_frame_hypotheses(suspect, original, _axis_rotations()))
    best = None
    for hyp in [identity, *frames]:
        fit = icp_similarity(sub, tree, original, hyp, spacing=spacing, iterations=15)
        if not _plausible(fit.scale, (hyp.scale, frames[0].scale)):
            continue  # collapsed onto a patch of the original, or blown up
        key = (round(fit.fitness, 2), -fit.residual)
        if best is None or key > best[0]:
            best = (key, fit)
        if hyp is identity and fit.fitness > 0.9 and fit.residual < spacing:
            break
    start = best[1] if best is not None else frames[0]
    return icp_similarity(suspect, tree, original, start, spacing=spacing, iterations=60)


def _plausible(scale, expected, factor=2.0):
    """A fitted scale within ``factor`` of any expected one.

    ICP with free scale can shrink a distant suspect onto one patch of the
    original, where every point then "fits"; such a fit is rejected.
    """
    return any(e / factor < scale < e * factor for e in expected)


# ---------------------------------------------------------------------------
# Global registration from feature correspondences, scale unknown (issue 13)
# ---------------------------------------------------------------------------

def umeyama_batch(source, target):
    """Umeyama's similarity for many small correspondence sets at once.

    Parameters
    ----------
    source, target : (h, k, 3) float
        ``h`` sets of ``k`` corresponding points (k >= 3).

    Returns
    -------
    rotation : (h, 3, 3) float, proper
    scale : (h,) float
    translation : (h, 3) float
        Mapping ``source`` onto ``target``: ``scale * R x + t``.
    """
    mu_s = source.mean(axis=1, keepdims=True)
    mu_t = target.mean(axis=1, keepdims=True)
    xs = source - mu_s
    xt = target - mu_t
    cov = np.einsum("hki,hkj->hij", xt, xs) / source.shape[1]
    u, d, vt = np.linalg.svd(cov)
    sign = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    sign[sign == 0] = 1.0
    flip = np.ones((len(source), 3))
    flip[:, 2] = sign
    rotation = np.einsum("hij,hj,hjk->hik", u, flip, vt)
    var_s = (xs**2).sum(axis=(1, 2)) / source.shape[1]
    scale = (d * flip).sum(axis=1) / np.maximum(var_s, 1e-300)
    translation = mu_t[:, 0] - scale[:, None] * np.einsum("hij,hj->hi", rotation, mu_s[:, 0])
    return rotation, scale, translation


def _triplets(source, n_samples, rng, local_radius):
    """Index triplets into the correspondences: half global, half local.

    A local triplet takes its second and third correspondences from the grid
    cell (side ``local_radius``, in source space) of the first.
    """
    n = len(source)
    first = rng.integers(0, n, n_samples)
    out = np.empty((n_samples, 3), dtype=np.int64)
    out[:, 0] = first
    n_local = n_samples // 2 if local_radius and local_radius > 0 else 0
    out[n_local:, 1:] = rng.integers(0, n, (n_samples - n_local, 2))
    if n_local:
        cell = np.floor((source - source.min(axis=0)) / local_radius).astype(np.int64)
        _, label, count = np.unique(cell, axis=0, return_inverse=True, return_counts=True)
        label = label.reshape(-1)
        order = np.argsort(label, kind="stable")
        start = np.concatenate([[0], np.cumsum(count)[:-1]])
        lab = label[first[:n_local]]
        pick = (rng.random((n_local, 2)) * count[lab][:, None]).astype(np.int64)
        out[:n_local, 1:] = order[start[lab][:, None] + pick]
    return out


def ransac_similarity(source, target, *, threshold, iterations=20000, rng=0, local_radius=None,
                      scale_range=(1e-3, 1e3), edge_tolerance=0.15, min_edge=None, max_hypotheses=3000,
                      weights=None, score_points=3000, top=1):
    """Similarity (scale included) from putative correspondences, by RANSAC on 3-point samples.

    Each sample of three correspondences gives a similarity in closed form
    (Umeyama).  Samples are first pruned, TEASER-style, by scale consistency:
    the three ratios target-edge / source-edge must agree within
    ``edge_tolerance`` (a wrong correspondence rarely preserves all three),
    lie in ``scale_range``, and source edges must be longer than
    ``min_edge``.  Surviving hypotheses are scored by their (weighted)
    inliers (correspondences mapped within ``threshold`` of their target);
    the best is refitted on its inliers up to three times.  With
    ``local_radius``, half of the samples pick their second and third
    correspondences within that distance of the first (in source space), so
    that a part occupying a small share of a scene is still sampled.

    Parameters
    ----------
    source, target : (c, 3) float
        Putative correspondences, row by row (many of them wrong).
    threshold : float
        Inlier distance, in target units.
    iterations : int
        Triplets drawn.
    rng : int or numpy.random.Generator
    local_radius : float, optional
        Neighbourhood of the local samples, in source units (None: all global).
    scale_range : (float, float)
        Admissible target / source scales.
    edge_tolerance : float
        Largest relative spread of the three edge ratios of a sample.
    min_edge : float, optional
        Shortest admissible source edge (default: 1 % of the source's extent).
    max_hypotheses : int
        Most consistent samples scored.
    weights : (c,) float, optional
        Weight of each correspondence in the inlier score (default 1).  With
        ``1 / (correspondences sharing its target)``, a hypothesis that
        collapses many source points onto one target point scores low.
    score_points : int
        Hypotheses are ranked on this many correspondences (a seeded subset);
        the best ``max(20, 4 * top)`` are rescored on all.
    top : int
        How many distinct hypotheses to return (best first).  A later
        check (ICP, overlap) often tells the right one better than the
        count of inliers.

    Returns
    -------
    transform : Similarity or None
        Maps source onto target; ``fitness`` is the share of correspondences
        that are inliers, ``residual`` their RMS distance.  ``None`` when no
        sample was consistent.
    inliers : (c,) bool
        With ``top > 1``, a list of up to ``top`` such pairs instead.
    """
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    n = len(source)
    if n < 3:
        return [] if top > 1 else (None, np.zeros(n, dtype=bool))
    rng = np.random.default_rng(rng)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    if min_edge is None:
        min_edge = 0.01 * float(np.linalg.norm(source.max(axis=0) - source.min(axis=0)))
    tri = _triplets(source, int(iterations), rng, local_radius)
    s = source[tri]                                      # (h, 3, 3)
    t = target[tri]
    es = np.linalg.norm(s[:, [0, 1, 2]] - s[:, [1, 2, 0]], axis=2)
    et = np.linalg.norm(t[:, [0, 1, 2]] - t[:, [1, 2, 0]], axis=2)
    ok = (es > min_edge).all(axis=1) & (et > 0).all(axis=1)
    ratio = np.where(ok[:, None], et / np.where(es > 0, es, 1.0), 1.0)
    ok &= ratio.max(axis=1) <= ratio.min(axis=1) * (1.0 + edge_tolerance)
    mean_ratio = ratio.mean(axis=1)
    ok &= (mean_ratio > scale_range[0]) & (mean_ratio < scale_range[1])
    # degenerate (nearly collinear) samples give unstable rotations
    area = np.linalg.norm(np.cross(s[:, 1] - s[:, 0], s[:, 2] - s[:, 0]), axis=1)
    ok &= area > 0.2 * es.max(axis=1) ** 2 * 0.5
    keep = np.flatnonzero(ok)
    if len(keep) == 0:
        return [] if top > 1 else (None, np.zeros(n, dtype=bool))
    if len(keep) > max_hypotheses:
        keep = rng.choice(keep, max_hypotheses, replace=False)
    rot, scale, trans = umeyama_batch(s[keep], t[keep])
    thr2 = threshold**2
    # score every hypothesis on a subset of the correspondences, the best few on all
    probe = np.arange(n) if n <= score_points else np.sort(rng.choice(n, score_points, replace=False))
    scores = np.empty(len(keep))
    for lo in range(0, len(keep), 256):
        sl = slice(lo, lo + 256)
        moved = scale[sl, None, None] * np.einsum("hij,cj->hci", rot[sl], source[probe]) + trans[sl, None, :]
        inside = ((moved - target[probe][None]) ** 2).sum(axis=2) < thr2      # (h, c)
        scores[sl] = inside.astype(np.float64) @ w[probe]
    rescored = []
    for i in np.argsort(-scores)[:max(20, 4 * top)]:
        moved = scale[i] * source @ rot[i].T + trans[i]
        rescored.append((float(w[((moved - target) ** 2).sum(axis=1) < thr2].sum()), int(i)))
    rescored.sort(key=lambda x: -x[0])
    results = []
    for _, i in rescored:
        current = Similarity(rot[i], float(scale[i]), trans[i])
        for _ in range(3):
            dist2 = ((apply(current, source) - target) ** 2).sum(axis=1)
            inliers = dist2 < thr2
            if inliers.sum() < 3:
                break
            current = umeyama(source[inliers], target[inliers])
        dist2 = ((apply(current, source) - target) ** 2).sum(axis=1)
        inliers = dist2 < thr2
        if any(np.mean(np.sum((apply(current, source[probe]) - apply(r, source[probe])) ** 2, axis=1)) < thr2
               for r, _ in results):
            continue   # the same hypothesis again
        residual = float(np.sqrt(dist2[inliers].mean())) if inliers.any() else float("inf")
        results.append((Similarity(current.rotation, current.scale, current.translation,
                                   float(inliers.mean()), residual), inliers))
        if len(results) == top:
            break
    return results if top > 1 else results[0]


def overlap(aligned, tree, original_sample, cut):
    """Quality of a registration seen from both sides.

    Parameters
    ----------
    aligned : (n, 3) float
        Suspect points after registration.
    tree : cKDTree
        Over the original points.
    original_sample : (k, 3) float
        Original points at which coverage is measured (a subsample).
    cut : float
        Inlier distance, in original units.

    Returns
    -------
    fitness : float
        Share of suspect points within ``cut`` of the original.
    coverage : float
        Share of ``original_sample`` within ``cut`` of a suspect point.
    residual : float
        RMS distance of the suspect inliers.
    """
    dist, _ = tree.query(aligned, distance_upper_bound=cut)
    inside = dist < cut
    fitness = float(inside.mean()) if len(aligned) else 0.0
    residual = float(np.sqrt((dist[inside] ** 2).mean())) if inside.any() else float("inf")
    if inside.any():
        back, _ = cKDTree(aligned[inside]).query(original_sample, distance_upper_bound=cut)
        coverage = float(np.isfinite(back).mean())
    else:
        coverage = 0.0
    return fitness, coverage, residual


def _with_fit(transform, suspect, tree, spacing):
    """``transform`` with its fitness (share of suspect points within 3 spacings) and their RMS distance."""
    dist, _ = tree.query(apply(transform, suspect), distance_upper_bound=3.0 * spacing)
    inside = np.isfinite(dist)
    fitness = float(inside.mean())
    residual = float(np.sqrt((dist[inside] ** 2).mean())) if inside.any() else float("inf")
    return Similarity(transform.rotation, transform.scale, transform.translation, fitness, residual)


def refine_part(suspect, tree, original, start, *, spacing, iterations=30, widths=(8.0, 3.0)):
    """Trimmed ICP with scale for partial overlap in both directions.

    The suspect may be part of the original, or contain it among clutter, so
    no quantile of the distances is a safe cut: pairs are kept within a fixed
    distance that narrows from ``widths[0]`` to ``widths[-1]`` times the
    spacing (a coarse start may be a few spacings off).  Each step is the
    Umeyama update of :func:`icp_similarity`; nearest-neighbour queries are
    bounded by the cut, so far clutter costs little.

    Parameters
    ----------
    suspect : (n, 3) float
    tree : cKDTree over ``original``
    original : (m, 3) float
    start : Similarity
    spacing : float
        Median nearest-neighbour distance of the original.
    iterations : int
        Most steps per width.
    widths : sequence of float
        Cuts, in spacings.

    Returns
    -------
    Similarity
        ``fitness``: share of suspect points within 3 spacings of the
        original; ``residual``: their RMS distance.
    """
    current = start
    for width in widths:
        cut = width * spacing
        previous = np.inf
        for _ in range(iterations):
            moved = apply(current, suspect)
            dist, idx = tree.query(moved, distance_upper_bound=cut)
            keep = np.isfinite(dist)
            if keep.sum() < 4:
                break
            step = umeyama(moved[keep], original[idx[keep]])
            current = _compose(step, current)
            err = float(np.sqrt((dist[keep] ** 2).mean()))
            if previous - err < 1e-4 * spacing:
                break
            previous = err
    return _with_fit(current, suspect, tree, spacing)


def refine_plane(suspect, tree, original, normals, start, *, spacing, iterations=20, widths=(3.0, 1.5)):
    """Trimmed point-to-plane ICP with scale (Chen and Medioni 1992, linearised, with a scale term).

    Point-to-point ICP (:func:`refine_part`) slides slowly along a smooth
    surface: on crops of tori with low bumps it stopped 3 to 65 spacings
    from the true pose, where the mark cannot be read.  Minimising the
    distance to the original's tangent planes moves along the surface in a
    few steps.  Each step solves for a small scale change, rotation vector
    and translation about the matched points' centroid; pairs are kept
    within a fixed cut narrowing from ``widths[0]`` to ``widths[-1]``
    spacings, as in :func:`refine_part`.  A direction the planes leave
    wholly unconstrained (sliding on a plane) gets no motion (the
    least-norm solution); a weakly constrained one is not damped.

    Parameters
    ----------
    suspect : (n, 3) float
    tree : cKDTree over ``original``
    original : (m, 3) float
    normals : (m, 3) float
        Unit normals of the original (their sign does not matter).
    start : Similarity
    spacing : float
        Median nearest-neighbour distance of the original.
    iterations : int
        Most steps per cut.
    widths : sequence of float
        Cuts, in spacings.

    Returns
    -------
    Similarity
        ``fitness`` and ``residual`` as :func:`refine_part` gives them.
    """
    current = start
    for width in widths:
        for _ in range(iterations):
            moved = apply(current, suspect)
            dist, idx = tree.query(moved, distance_upper_bound=width * spacing)
            keep = np.isfinite(dist)
            if keep.sum() < 7:
                break
            x, n = moved[keep], normals[idx[keep]]
            centre = x.mean(axis=0)
            xc = x - centre
            # the scale and rotation columns divided by the matches' RMS radius: every unknown
            # is then a length, so the least-norm step does not depend on the model's units
            length = max(float(np.sqrt((xc ** 2).sum(axis=1).mean())), spacing)
            design = np.column_stack([(xc * n).sum(axis=1) / length, np.cross(xc, n) / length, n])  # (k, 7)
            misfit = ((original[idx[keep]] - x) * n).sum(axis=1)
            step, *_ = np.linalg.lstsq(design, misfit, rcond=None)
            step[:4] /= length
            step[0] = np.clip(step[0], -MAX_STEP, MAX_STEP)          # a linearised step stays small:
            angle = np.linalg.norm(step[1:4])                         # the scale never flips sign
            if angle > MAX_STEP:
                step[1:4] *= MAX_STEP / angle
            turn = Rotation.from_rotvec(step[1:4]).as_matrix()
            scale = 1.0 + step[0]
            current = _compose(Similarity(turn, scale, centre + step[4:] - scale * turn @ centre), current)
            reach = abs(step[0]) + np.linalg.norm(step[1:4])
            if reach * np.sqrt((xc ** 2).sum(axis=1).max()) + np.linalg.norm(step[4:]) < 1e-3 * spacing:
                break
    return _with_fit(current, suspect, tree, spacing)


def rotation_search(suspect, original, scale, *, rotations=1000, grid=64, top=12, max_points=3000):
    """Coarse poses of a suspect at a known scale, by exhaustive rotation and FFT translation search.

    The original becomes a grid of soft occupancy (a Gaussian of each voxel
    centre's distance to the nearest original point, sigma one voxel).  For
    each of ``rotations`` fixed rotations (the same on every machine), the
    scaled, rotated suspect becomes a 0/1 grid and its correlation with the
    original over every translation is one FFT product; the best translation
    scores the mean occupancy under the suspect's voxels.  The ``top``
    best-scoring rotations are returned as starting poses for ICP.

    Parameters
    ----------
    suspect : (n, 3) float
    original : (m, 3) float
    scale : float
        Suspect-to-original scale (from the ratio of point spacings).
    rotations : int
    grid : int
        Voxels per side; the grid spans the original padded by the suspect's radius.
    top : int
    max_points : int
        Suspect subsample voxelized per rotation.

    Returns
    -------
    list of (float, Similarity)
        Score (mean occupancy, 0..1) and pose, best first.
    """
    from scipy import fft
    moved = np.asarray(suspect, dtype=np.float64) * scale
    centre = moved.mean(axis=0)
    moved = moved - centre
    moved = moved[:: max(1, len(moved) // max_points)]
    radius = float(np.linalg.norm(moved, axis=1).max())
    lo = original.min(axis=0) - radius
    voxel = float((original.max(axis=0) + radius - lo).max()) / grid
    axes = np.arange(grid)
    cells = np.stack(np.meshgrid(axes, axes, axes, indexing="ij"), axis=-1).reshape(-1, 3)
    dist, _ = cKDTree(original).query(lo + (cells + 0.5) * voxel, distance_upper_bound=4.0 * voxel)
    # single precision: the FFTs cost a quarter of double's, and the scores move by about 1e-7
    occupancy = np.exp(-0.5 * (np.minimum(dist, 4.0 * voxel) / voxel) ** 2).reshape(grid, grid, grid)
    spectrum = fft.rfftn(occupancy.astype(np.float32), workers=1)
    found = []
    for rotation in Rotation.random(rotations, random_state=0).as_matrix():
        index = np.floor(moved @ rotation.T / voxel).astype(np.int64) % grid
        mask = np.zeros((grid, grid, grid), dtype=np.float32)
        mask[index[:, 0], index[:, 1], index[:, 2]] = 1.0
        corr = fft.irfftn(spectrum * np.conj(fft.rfftn(mask, workers=1)), s=mask.shape, workers=1)
        shift = np.unravel_index(int(np.argmax(corr)), corr.shape)
        # x -> R (scale x - centre) + lo + shift * voxel
        found.append((float(corr[shift] / mask.sum()), rotation, lo + np.asarray(shift) * voxel - rotation @ centre))
    found.sort(key=lambda f: -f[0])
    return [(s, Similarity(r, float(scale), t)) for s, r, t in found[:top]]


POSES_FIT = 0.5           # other poses are sought only where this share of the suspect lies on the original,
POSES_CLOSE = 1.0         # and its RMS distance there, beyond its and the original's roughness, at most this (spacings)
POSE_FITNESS_TIE = 0.1     # another pose fits as well: fitness at most this below the chosen pose's,
POSE_RESIDUAL_TIE = 1.25   # and residual at most this times its residual
POSE_APART = 3.0           # spacings: poses whose points lie closer than this (mean) are the same pose
MAX_POSES = 32             # most poses kept beside the chosen one
SYMMETRY_TIE = 0.93        # two principal spreads at least this alike: the third axis is near-symmetric
AXIS_TURNS = 72            # turns about a near-symmetry axis tried from a registration (5 degrees)
TURN_STEP = 1.0           # degrees between the turns :func:`fine_turns` scores about an axis of revolution
TURN_FINE = 0.1           # degrees between its turns about each best one
TURN_KEPT = 4             # its best turns returned
TURN_APART = 3.0          # degrees at least between them
TURN_POINTS = 500         # most suspect points it scores (the dip shows alike on 600 as on 2,400)


def poses_alike(points, tree, sample, chosen, poses, spacing, normals=None):
    """Those of ``poses`` that fit ``points`` about as well as ``chosen``, distinct, tightest first.

    A part of a near-symmetric shape, or a whole copy turned about its
    near-symmetry axis, fits at several poses that overlap cannot tell apart.

    Parameters
    ----------
    points : (n, 3) float
        The suspect (or a subsample).
    tree : cKDTree (or any tree with its ``query``, and ``data`` where ``normals`` are given)
        Over the original points.
    sample : (k, 3) float
        Original points at which coverage is measured.
    chosen : Similarity
    poses : sequence of Similarity
    spacing : float
        Median nearest-neighbour distance of the original.
    normals : (m, 3) float, optional
        Unit normals of the original, row for row with ``tree.data``, for :func:`lies_on`.

    Returns
    -------
    list of Similarity
        Fitness (within 3 spacings) at most :data:`POSE_FITNESS_TIE` below
        the chosen pose's, residual at most :data:`POSE_RESIDUAL_TIE` times
        its own, each :data:`POSE_APART` apart from the chosen pose and the
        others; at most :data:`MAX_POSES`.  Empty where the chosen pose does
        not lay ``points`` on the original (:func:`lies_on`): a suspect that
        is not this original fits nowhere, at many poses alike.
    """
    def fit(pose):
        f, _, r = overlap(apply(pose, points), tree, sample, 3.0 * spacing)
        return f, r

    if not lies_on(points, tree, chosen, spacing, normals):
        return []
    f0, r0 = fit(chosen)
    order = sorted((r, i) for i, (f, r) in enumerate(map(fit, poses))
                   if f >= f0 - POSE_FITNESS_TIE and r <= POSE_RESIDUAL_TIE * max(r0, 1e-3 * spacing))
    return distinct_poses(points, chosen, [poses[i] for _, i in order], spacing)


def lies_on(points, tree, pose, spacing, normals=None):
    """Whether ``pose`` lays the suspect on the original, closely enough to look for other poses alike.

    At least :data:`POSES_FIT` of ``points`` within 3 spacings of an
    original point, and, with the original's ``normals``, the RMS distance of
    those points to the tangent plane at their nearest original point, less
    the :func:`roughness` of the suspect and of the original in quadrature,
    at most :data:`POSES_CLOSE` spacings: a noisy copy lies no closer than
    its noise, and a copy resampled from a rough scan lies at the scan's
    roughness from the tangent planes of its points.  A shape that is not
    this original fits nowhere, at many poses alike, its points spread
    through the band about the surface (an even spread gives 1.7 spacings);
    a copy, cropped, noisy or resampled, lies on the surface.

    Parameters
    ----------
    points : (n, 3) float
        The suspect (or a subsample), in its own coordinates.
    tree : cKDTree (or any tree with its ``query`` and ``data``)
        Over the original points.
    pose : Similarity
    spacing : float
        Median nearest-neighbour distance of the original.
    normals : (m, 3) float, optional
        Unit normals of the original, row for row with ``tree.data``;
        without them only the share is tested.

    Returns
    -------
    bool
    """
    aligned, dist, idx, inside = _band(points, tree, pose, spacing)
    if not len(aligned) or inside.mean() < POSES_FIT:
        return False
    if normals is None:
        return True
    return _plane_excess(aligned, inside, idx, tree, normals) <= (POSES_CLOSE * spacing) ** 2


def closeness(points, tree, pose, spacing, normals):
    """How closely ``pose`` lays ``points`` on the original: near it, and on its tangent planes.

    Parameters
    ----------
    points : (n, 3) float
        The suspect (or a subsample), in its own coordinates.
    tree : cKDTree (or any tree with its ``query`` and ``data``)
        Over the original points.
    pose : Similarity
    spacing : float
        Median nearest-neighbour distance of the original.
    normals : (m, 3) float
        Unit normals of the original, row for row with ``tree.data``.

    Returns
    -------
    near : float
        Share of ``points`` within one spacing of an original point.
    excess : float
        Mean squared distance of the points within 3 spacings to the tangent
        plane at their nearest original point, less the :func:`roughness` of
        the suspect and of the original, squared (what :func:`lies_on` bounds;
        in the original's units, squared); inf where none is within 3 spacings.
    """
    aligned, dist, idx, inside = _band(points, tree, pose, spacing)
    near = float((dist < spacing).mean()) if len(aligned) else 0.0
    return near, (_plane_excess(aligned, inside, idx, tree, normals) if inside.any() else float("inf"))


def _band(points, tree, pose, spacing):
    """``points`` laid by ``pose``, their nearest original points' distances and rows (within 3 spacings),
    and which lie within them."""
    aligned = apply(pose, points)
    dist, idx = tree.query(aligned, distance_upper_bound=3.0 * spacing)
    return aligned, dist, idx, dist < 3.0 * spacing


def _plane_excess(aligned, inside, idx, tree, normals):
    """Mean squared distance of ``aligned[inside]`` to the tangent planes at their nearest original points
    (``idx``), less the roughness of all of ``aligned`` (outliers only make it rougher) and of the original,
    squared."""
    off = np.einsum("ki,ki->k", aligned[inside] - tree.data[idx[inside]], normals[idx[inside]])
    allowed = roughness(aligned) ** 2 + roughness(tree.data, tree=tree) ** 2
    return float(np.mean(off ** 2)) - allowed


def roughness(points, k=16, most=1500, tree=None):
    """Median RMS distance of a point set's neighbourhoods from their own least-squares planes.

    Parameters
    ----------
    points : (n, 3) float
    k : int
        Neighbours of each point (itself included).
    most : int
        About this many neighbourhoods (fewer than twice as many), evenly strided.
    tree : cKDTree (or any tree with its ``query``) over ``points``, optional
        Built here when not given.

    Returns
    -------
    float
        0 for fewer than 4 points.
    """
    if len(points) < 4:
        return 0.0
    k = min(k, len(points))
    _, idx = (tree or cKDTree(points)).query(points[:: max(1, len(points) // most)], k=k)
    nbrs = points[idx]
    centred = nbrs - nbrs.mean(axis=1, keepdims=True)
    least = np.linalg.eigvalsh(np.einsum("nki,nkj->nij", centred, centred))[:, 0]
    return float(np.sqrt(np.median(np.maximum(least, 0.0)) / max(k - 3, 1)))


def distinct_poses(points, chosen, poses, spacing):
    """``poses`` in order, less each within :data:`POSE_APART` spacings (mean over ``points``) of an earlier one.

    ``chosen`` counts as earlier than all; at most :data:`MAX_POSES` are returned.
    """
    kept, placed = [], [apply(chosen, points)]
    for pose in poses:
        moved = apply(pose, points)
        if all(np.linalg.norm(moved - p, axis=1).mean() >= POSE_APART * spacing for p in placed):
            kept.append(pose)
            placed.append(moved)
            if len(kept) == MAX_POSES:
                break
    return kept


def fine_turns(points, tree, transform, anchor, direction, *, step=TURN_STEP, fine=TURN_FINE, kept=TURN_KEPT,
               apart=TURN_APART, bound=None, most=TURN_POINTS):
    """``transform`` turned about an axis to the turns at which ``points`` lie tightest on the original.

    About the axis of a surface of revolution every turn fits nearly alike,
    and ICP barely moves along it; the scan's own detail leaves a narrow dip
    (about a degree wide) in the median distance at the true turn, which
    starts a few degrees apart, refined by ICP, miss.  The median distance
    is scored every ``step`` degrees about the axis; the ``kept`` deepest
    local minima, at least ``apart`` degrees apart, are scanned again every
    ``fine`` degree within a step of them.

    Parameters
    ----------
    points : (n, 3) float
        The suspect (or a subsample).
    tree : cKDTree over the original points, or any tree with its ``query``
    transform : Similarity
        Suspect to original.
    anchor, direction : (3,) float
        A point of the axis and its unit direction, in the original's frame.
    step, fine, apart : float
        Degrees.
    kept : int
    bound : float, optional
        Distance past which a point counts as far (a median beyond it is inf).
    most : int
        Points scored (evenly strided).

    Returns
    -------
    list of Similarity
        Deepest first.
    """
    direction = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    anchor = np.asarray(anchor, dtype=np.float64)
    bound = np.inf if bound is None else float(bound)
    points = points[:: max(1, len(points) // most)]

    def turned(degrees):
        turn = Rotation.from_rotvec(np.radians(degrees) * direction).as_matrix()
        return Similarity(turn @ transform.rotation, transform.scale, turn @ (transform.translation - anchor) + anchor)

    def score(degrees):
        return float(np.median(tree.query(apply(turned(degrees), points), distance_upper_bound=bound)[0]))

    angles = np.arange(0.0, 360.0, step)
    scores = np.array([score(a) for a in angles])
    minima = np.flatnonzero((scores <= np.roll(scores, 1)) & (scores <= np.roll(scores, -1)) & np.isfinite(scores))
    found = []
    for i in minima[np.argsort(scores[minima], kind="stable")]:
        if all(abs((angles[i] - a + 180.0) % 360.0 - 180.0) >= apart for _, a in found):
            around = angles[i] + np.arange(-step, step + fine / 2, fine)
            found.append(min((score(a), a) for a in around))
            if len(found) == kept:
                break
    return [turned(a) for _, a in sorted(found)]


def axis_turns(original, transform, steps=AXIS_TURNS):
    """``transform`` turned about each near-symmetry axis of ``original``, through its centroid.

    An axis is near-symmetric when the spreads along the other two principal
    axes are at least :data:`SYMMETRY_TIE` alike (a vase, a birdbath): its
    principal frame then leaves the turn about it open.

    Parameters
    ----------
    original : (m, 3) float
    transform : Similarity
        Suspect to original.
    steps : int
        Turns per axis, evenly spaced (the identity excluded).

    Returns
    -------
    list of Similarity
        Empty when the original has no near-symmetric axis.
    """
    centroid, axes, _ = principal_frame(original)
    turns = []
    for k in symmetry_axes(original):
        for angle in 2.0 * np.pi * np.arange(1, steps) / steps:
            turn = Rotation.from_rotvec(angle * axes[:, k]).as_matrix()
            turns.append(Similarity(turn @ transform.rotation, transform.scale,
                                    turn @ (transform.translation - centroid) + centroid))
    return turns


def symmetry_axes(original):
    """Indices of the principal axes of ``original`` about which it is near-symmetric (see :data:`SYMMETRY_TIE`).

    An axis is near-symmetric when the spreads along the other two principal
    axes are at least :data:`SYMMETRY_TIE` alike (a vase, a birdbath).

    Returns
    -------
    list of int
    """
    spread = shape_signature(original)
    return [k for k, (i, j) in enumerate(((1, 2), (0, 2), (0, 1)))
            if min(spread[i], spread[j]) >= SYMMETRY_TIE * max(spread[i], spread[j])]


def connected_parts(points, radius, *, min_points=1):
    """The connected parts of a point set: points about ``radius`` apart or closer are linked.

    Points are first pooled in cubic cells of ``radius / 2`` (duplicates and
    dense patches cost no more than one cell each), and cells whose mean
    points lie within ``radius`` are linked, so memory stays linear in the
    number of occupied cells.

    Parameters
    ----------
    points : (n, 3) float
    radius : float
        Linking distance, in the points' units.
    min_points : int
        Parts with fewer points are left out.

    Returns
    -------
    list of (n_i,) int
        Point indices of each part, the largest part first (ties by the
        smallest index, so the order is the same on every machine).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    if n == 0:
        return []
    if not (np.isfinite(radius) and radius > 0):
        return [np.arange(n)] if n >= min_points else []
    cells = np.floor((points - points.min(axis=0)) / (0.5 * radius)).astype(np.int64)
    _, cell_of = np.unique(cells, axis=0, return_inverse=True)
    cell_of = cell_of.ravel()
    counts = np.bincount(cell_of)
    centres = np.stack([np.bincount(cell_of, weights=points[:, d]) for d in range(3)], axis=1) / counts[:, None]
    m = len(counts)
    pairs = cKDTree(centres).query_pairs(float(radius), output_type="ndarray")
    links = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
    _, label = connected_components(links, directed=False)
    label = label[cell_of]
    sizes = np.bincount(label)
    first = np.full(len(sizes), n)
    np.minimum.at(first, label, np.arange(n))
    order = np.lexsort((first, -sizes))
    members = np.split(np.argsort(label, kind="stable"), np.cumsum(sizes)[:-1])
    return [members[c] for c in order if sizes[c] >= min_points]


OBJECT_GAP = 4.0   # spacings: points closer than this belong to one object


def separate_objects(points, spacing, *, min_points=1):
    """The separate objects of a scene: its connected parts at ``OBJECT_GAP`` spacings.

    A part holding 95 % of the points or more is the whole suspect, not an
    object among others, and is left out.

    Parameters
    ----------
    points : (n, 3) float
    spacing : float
        Typical point spacing (the median nearest-neighbour distance).
    min_points : int
        Parts with fewer points are left out.

    Returns
    -------
    list of (n_i,) int, the largest first; empty when the points form one object
    """
    parts = connected_parts(points, OBJECT_GAP * spacing, min_points=min_points)
    return [p for p in parts if len(p) < 0.95 * len(points)]


def shape_signature(points):
    """Spread of a point set along its principal axes, relative to the largest: (1, b, c).

    Unchanged by rotation, translation and uniform scale, so a whole copy of
    an asset has the original's signature wherever and however large it is.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    (3,) float, descending, first entry 1
    """
    centred = np.asarray(points, dtype=np.float64) - np.mean(points, axis=0)
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(centred.T @ centred / max(len(centred), 1)), 0.0))[::-1]
    return spread / spread[0] if spread[0] > 0 else spread
