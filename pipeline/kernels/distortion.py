"""Distortion of a marked point set as the mesh-watermarking field measures it.

Surfaces are represented by local planes: the surface of a point set near a
query point is the tangent plane of its nearest point, whose normal is the
smallest principal direction of that point's ``k`` nearest neighbours (so an
unchanged copy is at distance 0, and a point slid along the surface is not
counted as distortion).  On this surface:

* ``mrms``: the larger of the two one-sided RMS point-to-surface distances
  (marked points to the original's surface and back), as Metro computes the
  MRMS of the LIRIS benchmark (Wang et al. 2011) on meshes;
* ``surface_hausdorff``: the larger of the two one-sided maximum distances;
* ``normal_deviation``: mean angle between the normals of corresponding
  points (a marked point and its nearest original point), in degrees;
* ``msdm``: a structural roughness measure in the spirit of MSDM (Lavoue et
  al. 2006), with the surface variation lambda_0 / (lambda_0 + lambda_1 +
  lambda_2) of each point in place of the mesh curvature: local windows
  compare mean, contrast and structure, combined as MSDM does; 0 for
  identical roughness, towards 1 as the marked copy gets rougher or smoother.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["local_planes", "to_surface", "msdm", "original_side", "surface_distortion", "pooled_distortion"]

_BLOCK = 1 << 15      # queries per block of local_planes


def local_planes(points, queries, k=16, tree=None):
    """Local plane of ``points`` near each query.

    Parameters
    ----------
    points : (n, 3) float
    queries : (m, 3) float
    k : int
    tree : cKDTree of ``points``, optional

    Returns
    -------
    centroids : (m, 3) float
    normals : (m, 3) float, unit, unoriented
    variation : (m,) float
        Surface variation lambda_0 / sum(lambda) of the neighbourhood, in [0, 1/3].
    """
    k = min(k, len(points))
    tree = tree or cKDTree(points)
    m = len(queries)
    centroids, normals, variation = np.empty((m, 3)), np.empty((m, 3)), np.empty(m)
    for a in range(0, m, _BLOCK):         # in blocks: (block, k, 3) temporaries, not (m, k, 3)
        _, idx = tree.query(queries[a:a + _BLOCK], k=k)
        nbrs = points[idx.reshape(-1, k)]
        centroids[a:a + _BLOCK] = nbrs.mean(axis=1)
        centred = nbrs - centroids[a:a + _BLOCK, None, :]
        values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))
        total = values.sum(axis=1)
        variation[a:a + _BLOCK] = np.where(total > 0, values[:, 0] / np.where(total > 0, total, 1.0), 0.0)
        normals[a:a + _BLOCK] = vectors[:, :, 0]
    return centroids, normals, variation


def to_surface(queries, points, normals, nearest):
    """Distance of each query to the tangent plane of its nearest point of ``points``.

    Parameters
    ----------
    queries : (m, 3) float
    points : (n, 3) float
    normals : (n, 3) float, unit, of ``points``
    nearest : (m,) int
        Index of each query's nearest point.

    Returns
    -------
    (m,) float
    """
    return np.abs(np.einsum("ni,ni->n", queries - points[nearest], normals[nearest]))


def msdm(original_variation, marked_variation, windows):
    """MSDM-style structural distance of two roughness fields on the same points.

    Parameters
    ----------
    original_variation, marked_variation : (n,) float
    windows : (c, w) int
        Neighbourhoods (indices into the fields), one per window centre.

    Returns
    -------
    float in [0, 1]
    """
    x, y = original_variation[windows], marked_variation[windows]
    mx, my = x.mean(axis=1), y.mean(axis=1)
    sx, sy = x.std(axis=1), y.std(axis=1)
    sxy = ((x - mx[:, None]) * (y - my[:, None])).mean(axis=1)
    tiny = 1e-30
    lum = np.abs(mx - my) / np.maximum(np.maximum(mx, my), tiny)
    con = np.abs(sx - sy) / np.maximum(np.maximum(sx, sy), tiny)
    stru = np.abs(sx * sy - sxy) / np.maximum(sx * sy, tiny)
    stru = np.where(sx * sy > tiny, np.minimum(stru, 1.0), 0.0)
    local = np.cbrt(0.4 * lum**3 + 0.4 * con**3 + 0.2 * stru**3)
    return float(np.cbrt((local**3).mean()))


def original_side(original, k=16, window=64, max_windows=20_000):
    """What :func:`surface_distortion` needs of the original, computed once for many copies.

    Parameters
    ----------
    original : (n, 3) float
    k : int
        Points per local plane.
    window : int
        Points per MSDM window.
    max_windows : int
        MSDM windows are centred on at most this many points (an even stride
        through the file), so memory stays bounded on large scenes.

    Returns
    -------
    dict: tree, normals (n, 3), variation (n,), windows (w, window), k
    """
    tree = cKDTree(original)
    _, normals, variation = local_planes(original, original, k, tree)
    centres = np.arange(0, len(original), max(1, -(-len(original) // max_windows)))
    _, windows = tree.query(original[centres], k=min(window, len(original)))
    return {"tree": tree, "normals": normals, "variation": variation,
            "windows": windows.reshape(len(centres), -1), "k": k}


def surface_distortion(original, marked, side=None):
    """Point and surface distances, normal deviation and MSDM of a marked copy.

    Parameters
    ----------
    original : (n, 3) float
    marked : (m, 3) float, any order and count (a copy, same frame)
    side : dict, optional
        :func:`original_side` of ``original`` (computed when not given).

    Returns
    -------
    dict, distances in the points' units
        hausdorff (nearest points, both ways), surface_rms_forward (marked
        points to the original's surface), surface_rms_backward (the
        original's points to the copy's surface), mrms, surface_hausdorff,
        normal_deviation_deg, msdm.
    """
    side = side or original_side(original)
    n_orig = side["normals"]
    marked_tree = cKDTree(marked)
    _, n_marked, v_marked = local_planes(marked, marked, side["k"], marked_tree)
    d_forward, near = side["tree"].query(marked)
    d_back, back = marked_tree.query(original)
    forward = to_surface(marked, original, n_orig, near)
    backward = to_surface(original, marked, n_marked, back)
    # the angle from atan2 of |cross| and |dot|: exact 0 for equal normals, unlike arccos near 1
    a, b = n_marked, n_orig[near]
    angle = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.abs(np.einsum("ni,ni->n", a, b)))
    forward_rms = float(np.sqrt((forward**2).mean()))
    return {
        "hausdorff": float(max(d_forward.max(), d_back.max())),
        "surface_rms_forward": forward_rms,
        "surface_rms_backward": float(np.sqrt((backward**2).mean())),
        "mrms": max(forward_rms, float(np.sqrt((backward**2).mean()))),
        "surface_hausdorff": float(max(forward.max(), backward.max())),
        "normal_deviation_deg": float(np.degrees(angle).mean()),
        # roughness of the copy carried onto the original's points (nearest marked point)
        "msdm": msdm(side["variation"], v_marked[back], side["windows"]),
    }


def pooled_distortion(original, marked, cells):
    """:func:`surface_distortion` of a large scene, cell by cell, pooled.

    Each cell's measures use only its own points (memory bounded by the
    cell); RMS values pool by their squares, maxima by the maximum, means
    and the MSDM cube mean weighted by the points.  The measures are local,
    so pooling differs from the whole-scene figures near cell borders (whose
    nearest neighbours are sought within the cell: the Hausdorff distance is
    an upper bound) and in MSDM, whose windows are sampled per cell.

    Parameters
    ----------
    original, marked : (n, 3) float, corresponding rows (a copy of the same order)
    cells : list of (n_t,) int, a partition of the rows

    Returns
    -------
    dict, as :func:`surface_distortion`
    """
    parts = [(len(c), surface_distortion(original[c], marked[c])) for c in cells if len(c)]
    weight = np.array([w for w, _ in parts], dtype=np.float64)
    weight /= weight.sum()

    def rms(name):
        return float(np.sqrt(sum(w * p[name] ** 2 for w, (_, p) in zip(weight, parts))))

    forward, backward = rms("surface_rms_forward"), rms("surface_rms_backward")
    return {"hausdorff": max(p["hausdorff"] for _, p in parts),
            "surface_rms_forward": forward, "surface_rms_backward": backward, "mrms": max(forward, backward),
            "surface_hausdorff": max(p["surface_hausdorff"] for _, p in parts),
            "normal_deviation_deg": float(sum(w * p["normal_deviation_deg"] for w, (_, p) in zip(weight, parts))),
            "msdm": float(np.cbrt(sum(w * p["msdm"] ** 3 for w, (_, p) in zip(weight, parts))))}
