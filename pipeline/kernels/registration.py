"""Registration of a suspect point set onto the original (paper, "Point Set Registration").

``register_covariance`` is the paper's method: centroids, principal axes
(covariance matrix, as in Gottschalk's OBB) and a scale from the spread along
them.  Axis signs are ambiguous; the four proper sign choices are scored by
the median distance to the original.

``register_robust`` goes further: identity and all 24 axis-aligned rotations
of the principal frame are each refined by trimmed ICP with scale
(Umeyama's closed form on nearest neighbours, pairs beyond a robust cut
dropped, so partial overlap does not pull), and the best fit wins.

A transform maps suspect coordinates x to ``scale * x @ rotation.T + translation``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "Similarity", "apply", "umeyama", "principal_frame", "register_covariance",
    "icp_similarity", "register_robust",
]


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


def register_robust(suspect, original, *, spacing, coarse_points=1500, rng=0):
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

    Returns
    -------
    Similarity
    """
    rng = np.random.default_rng(rng)
    tree = cKDTree(original)
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
