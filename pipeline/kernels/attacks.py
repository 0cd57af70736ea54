"""Attacks on point sets, as defined in ROBUSTNESS.md (seeded, pure functions).

Every attack takes ``points`` (n, 3) and a ``rng`` and returns new points;
phi is the largest bbox side of the input.  Chains are lists of
``(name, strength)`` applied in order by :func:`apply_chain`.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "rotation_matrix", "similarity", "paper_similarity", "random_similarity", "noise_uniform",
    "noise_gaussian", "removal", "crop_plane", "crop", "quantize", "smooth", "shuffle", "apply_chain", "ATTACKS",
    "outliers", "scene", "clutter", "random_rotation", "sample_triangles", "STRENGTHS", "check_strength",
    "chain_size", "MAX_POINTS", "MAX_GROWTH",
]


def _phi(points):
    return float((points.max(axis=0) - points.min(axis=0)).max())


def rotation_matrix(axis, degrees):
    """(3, 3) rotation about a coordinate axis ('x', 'y' or 'z')."""
    a = np.radians(degrees)
    c, s = np.cos(a), np.sin(a)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def similarity(points, rotation, scale=1.0, translation=(0.0, 0.0, 0.0)):
    """x -> scale * R x + t.

    Parameters
    ----------
    points : (n, 3) float
    rotation : (3, 3) float
    scale : float
    translation : (3,) float
    """
    return scale * points @ np.asarray(rotation).T + np.asarray(translation, dtype=np.float64)


def paper_similarity(points, rng=None):
    """The paper's transform: 10 deg about x, then 30 deg about y, scale 0.6."""
    rot = rotation_matrix("y", 30.0) @ rotation_matrix("x", 10.0)
    return similarity(points, rot, 0.6)


def random_similarity(points, rng=None):
    """A uniformly random rotation, scale in [0.1, 10] (log-uniform), translation up to 2 phi."""
    rng = np.random.default_rng(rng)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1.0
    scale = float(np.exp(rng.uniform(np.log(0.1), np.log(10.0))))
    return similarity(points, q, scale, rng.uniform(-2.0, 2.0, 3) * _phi(points))


def noise_uniform(points, strength, rng=None):
    """Uniform noise per coordinate in [-a, a], a = strength * phi (strength 0.005 = 0.5 %)."""
    rng = np.random.default_rng(rng)
    return points + rng.uniform(-1.0, 1.0, points.shape) * strength * _phi(points)


def noise_gaussian(points, strength, rng=None):
    """Gaussian noise per coordinate, standard deviation strength * phi."""
    rng = np.random.default_rng(rng)
    return points + rng.normal(0.0, strength * _phi(points), points.shape)


def removal(points, fraction, rng=None):
    """Keep a random ``fraction`` of the points (order kept)."""
    rng = np.random.default_rng(rng)
    keep = max(1, int(round(fraction * len(points))))
    return points[np.sort(rng.choice(len(points), keep, replace=False))]


def crop_plane(points, fraction, rng=None):
    """A random plane (unit normal, offset) with a ``fraction`` of the points on its positive side."""
    rng = np.random.default_rng(rng)
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    return normal, float(np.quantile(points @ normal, 1.0 - fraction))


def crop(points, fraction, rng=None):
    """Keep the ``fraction`` of points on one side of a random plane through the model."""
    normal, offset = crop_plane(points, fraction, rng)
    return points[points @ normal >= offset]


def quantize(points, bits, rng=None):
    """Round coordinates to a grid of phi / 2**bits (anchored at the bbox minimum)."""
    step = _phi(points) / float(2 ** int(bits))
    lo = points.min(axis=0)
    return lo + np.round((points - lo) / step) * step


def smooth(points, iterations, rng=None, *, k=8, lam=0.5):
    """Laplacian smoothing on the k-nearest-neighbour graph, lambda 0.5."""
    _, idx = cKDTree(points).query(points, k=k + 1)
    out = points.copy()
    for _ in range(int(iterations)):
        out = out + lam * (out[idx[:, 1:]].mean(axis=1) - out)
    return out


def shuffle(points, rng=None):
    """Permute the point order."""
    rng = np.random.default_rng(rng)
    return points[rng.permutation(len(points))]


def random_rotation(rng=None):
    """A uniformly random proper rotation, (3, 3) float."""
    rng = np.random.default_rng(rng)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1.0
    return q


def outliers(points, fraction, rng=None):
    """Add ``fraction * n`` points drawn uniformly in the bounding box (the originals kept, first).

    Parameters
    ----------
    points : (n, 3) float
    fraction : float
        0.5 adds half as many outliers as there are points.

    Returns
    -------
    (n + round(fraction * n), 3) float
    """
    rng = np.random.default_rng(rng)
    lo, hi = points.min(axis=0), points.max(axis=0)
    extra = rng.uniform(lo, hi, (int(round(fraction * len(points))), 3))
    return np.concatenate([points, extra])


def scene(points, others, factor, rng=None, *, gap=0.15):
    """Place the points among unrelated objects: clutter of ``factor`` times their count.

    Objects are taken from ``others`` in turn (again, with a new pose, until
    the clutter holds ``round(factor * n)`` points): each is centred,
    randomly rotated, scaled so its largest bbox side is 0.6 to 1.4 times
    the asset's, subsampled to at most its remaining share, and put next to
    the asset on a random direction at a distance leaving about ``gap`` x
    phi between bounding spheres (the objects surround the asset but do not
    intersect it).

    Parameters
    ----------
    points : (n, 3) float
        The asset, in any frame.
    others : list of (m_i, 3) float
        Unrelated objects.
    factor : float
        Clutter points as a multiple of ``n``.

    Returns
    -------
    (n + round(factor * n), 3) float
        The asset's points first, then the clutter.
    """
    rng = np.random.default_rng(rng)
    phi = _phi(points)
    centre = (points.min(axis=0) + points.max(axis=0)) / 2.0
    radius = float(np.linalg.norm(points - centre, axis=1).max())
    remaining = int(round(factor * len(points)))
    placed, directions = [], []
    ring = 0
    while remaining > 0 and others:
        other = np.asarray(others[len(placed) % len(others)], dtype=np.float64)
        share = min(remaining, len(other), max(remaining // max(len(others) - len(placed), 1), 1))
        o_centre = (other.min(axis=0) + other.max(axis=0)) / 2.0
        obj = (other - o_centre) * (rng.uniform(0.6, 1.4) * phi / _phi(other))
        obj = obj[rng.choice(len(obj), share, replace=False)] @ random_rotation(rng).T
        r_obj = float(np.linalg.norm(obj, axis=1).max())
        for _ in range(100):   # a direction away from the objects placed so far on this ring
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            if all(d @ e < 0.5 for e in directions):
                break
        else:
            directions, ring = [], ring + 1      # ring full: start a wider one
        directions.append(d)
        placed.append(obj + centre + d * (radius + r_obj + gap * phi) * (1 + 1.5 * ring))
        remaining -= share
    return np.concatenate([points, *placed]) if placed else points.copy()


def _blob(rng, n):
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    r = np.ones(n)
    for _ in range(5):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        r += 0.08 * np.sin(rng.uniform(1.0, 4.0) * np.pi * v @ axis + rng.uniform(0, 2 * np.pi))
    return v * r[:, None] * rng.uniform(0.5, 1.0, 3)


def box(rng, n, sides=None):
    """(n, 3) points on the surface of a centred box, its six faces equally likely.

    ``sides`` (3,) default to seeded draws in [0.4, 1) (the clutter's boxes).
    """
    sides = rng.uniform(0.4, 1.0, 3) if sides is None else np.asarray(sides, dtype=np.float64)
    face = rng.integers(0, 6, n)
    p = rng.uniform(-0.5, 0.5, (n, 3))
    p[np.arange(n), face % 3] = np.where(face < 3, -0.5, 0.5)
    return p * sides


def _cylinder(rng, n):
    a = rng.uniform(0, 2 * np.pi, n)
    h = rng.uniform(-0.5, 0.5, n)
    r = rng.uniform(0.2, 0.4)
    return np.column_stack([r * np.cos(a), r * np.sin(a), h])


def clutter(points, factor, rng=None, *, n_objects=4):
    """Place the points among procedural objects (bumpy blobs, boxes, cylinders): see :func:`scene`.

    Parameters
    ----------
    points : (n, 3) float
    factor : float
        Clutter points as a multiple of ``n`` (3 = three times the asset).

    Returns
    -------
    (about (1 + factor) * n, 3) float, the asset's points first
    """
    rng = np.random.default_rng(rng)
    makers = [_blob, box, _cylinder]
    share = max(int(round(factor * len(points) / n_objects)), 10)
    others = [makers[i % 3](rng, share) for i in range(n_objects)]
    return scene(points, others, factor, rng)


def sample_triangles(vertices, triangles, n_points, rng=None, *, grid=1e-4):
    """Area-uniform samples on a triangle soup, whatever its order.

    Each triangle draws its samples from a counter-based hash of its corners
    (rounded to ``grid``) and a seed taken from ``rng``: about
    ``1.25 n_points`` candidates in all, each with a random priority, of
    which the ``n_points`` of lowest priority are kept.  Reordering the
    triangles, their corners or the vertices changes nothing; a triangle
    that differs changes its own candidates, and the others' only where the
    total area moves a count or the cut.

    Parameters
    ----------
    vertices : (v, 3) float
    triangles : (t, 3) int
    n_points : int
    rng : int or numpy.random.Generator
    grid : float
        Rounding of the corners (in the units of ``vertices``) before they
        are hashed, well above the noise of the reconstruction's float32
        vertices and well below its cells.

    Returns
    -------
    (n_points, 3) float, in random order
    """
    seed = np.uint64(np.random.default_rng(rng).integers(0, 2**63))
    corners, tri_hash = _canonical_triangles(vertices, triangles, grid, seed)
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    if not area.sum() > 0:
        raise ValueError("the surface has no area to sample (no triangles, or only degenerate ones)")
    scale = 1.25 * n_points / area.sum()
    while True:
        count = np.floor(scale * area + _uniform(tri_hash, 0)).astype(np.int64)
        if count.sum() >= n_points:
            break
        scale *= 1.5
    owner = np.repeat(np.arange(len(area)), count)
    counter = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count) + 1
    point_hash = _mix(tri_hash[owner] ^ _mix(counter.astype(np.uint64)))
    keep = np.argsort(_uniform(point_hash, 1), kind="stable")[:n_points]
    owner, point_hash = owner[keep], point_hash[keep]
    u, v = _uniform(point_hash, 2), _uniform(point_hash, 3)
    flip = u + v > 1.0                                              # fold the square onto the triangle
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    a, b, c = corners[owner, 0], corners[owner, 1], corners[owner, 2]
    return a + u[:, None] * (b - a) + v[:, None] * (c - a)


def _canonical_triangles(vertices, triangles, grid, seed):
    """Corners in lexicographic order of their rounded coordinates, and a hash of each triangle.

    Returns
    -------
    corners : (t, 3, 3) float
    tri_hash : (t,) uint64
        From the rounded corners and the seed; a triangle given more than
        once mixes in its occurrence after the first (copies draw their own
        samples).
    """
    key = np.round(vertices[triangles] / grid).astype(np.int64)     # (t, 3, 3)
    flat = key.reshape(-1, 3)
    rank = np.empty(len(flat), dtype=np.int64)
    rank[np.lexsort(flat.T[::-1])] = np.arange(len(flat))
    corner_order = np.argsort(rank.reshape(-1, 3), axis=1)[:, :, None]
    corners = np.take_along_axis(vertices[triangles], corner_order, axis=1)
    key = np.take_along_axis(key, corner_order, axis=1).reshape(len(key), 9)
    tri_hash = np.full(len(key), seed, dtype=np.uint64)
    for column in key.view(np.uint64).T:
        tri_hash = _mix(tri_hash ^ column)
    order = np.lexsort(key.T[::-1])
    ranked = key[order]
    same = np.r_[False, (ranked[1:] == ranked[:-1]).all(axis=1)]
    start = np.maximum.accumulate(np.where(same, 0, np.arange(len(order))))
    occurrence = np.empty(len(order), dtype=np.uint64)
    occurrence[order] = (np.arange(len(order)) - start).astype(np.uint64)
    return corners, np.where(occurrence > 0, _mix(tri_hash ^ occurrence), tri_hash)


def _mix(x):
    """SplitMix64 finaliser, elementwise on uint64."""
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def _uniform(h, stream):
    """Uniform in [0, 1) from hashes ``h``, one independent stream per integer."""
    x = _mix(h + np.uint64(0x9E3779B97F4A7C15 * (stream + 1) % 2**64))
    return (x >> np.uint64(11)).astype(np.float64) / float(2**53)


# name -> (function, takes a strength)
ATTACKS = {
    "similarity": (paper_similarity, False),
    "random_similarity": (random_similarity, False),
    "noise": (noise_uniform, True),
    "gaussian_noise": (noise_gaussian, True),
    "removal": (removal, True),
    "crop": (crop, True),
    "quantize": (quantize, True),
    "smooth": (smooth, True),
    "shuffle": (shuffle, False),
    "outliers": (outliers, True),
    "clutter": (clutter, True),
}


# name -> (whole number?, lowest, highest, lowest allowed?) of the strength; absent: takes none
STRENGTHS = {
    "noise": (False, 0.0, 1.0, True),             # share of phi
    "gaussian_noise": (False, 0.0, 1.0, True),
    "removal": (False, 0.0, 1.0, False),          # share of the points kept
    "crop": (False, 0.0, 1.0, False),
    "quantize": (True, 1, 52, True),              # bits per coordinate (a double holds 52)
    "smooth": (True, 0, 1000, True),              # iterations
    "outliers": (False, 0.0, 100.0, True),        # points added per point
    "clutter": (False, 0.0, 100.0, True),
    "resample": (True, 1, None, True),            # points (bounded by chain_size)
    "simplify": (True, 1, None, True),            # vertices
}
# an attacked copy holds at most this many points, and at most this many times the input's
MAX_POINTS = 50_000_000
MAX_GROWTH = 100


def check_strength(name, strength):
    """Check an attack's strength before any point is read.

    Parameters
    ----------
    name : str
    strength : float or None

    Returns
    -------
    float, int or None
        The strength, as an int for the counted attacks (``quantize:8.0`` -> 8).

    Raises
    ------
    ValueError
        Naming the attack, the strength and the range.
    """
    if name not in STRENGTHS:
        if strength is not None:
            raise ValueError(f"{name} takes no strength (got {strength:g})")
        return None
    whole, low, high, closed = STRENGTHS[name]
    if strength is None:
        raise ValueError(f"attack {name!r} needs a strength, e.g. {name}:{1000 if whole else 0.5}")
    if not np.isfinite(strength):
        raise ValueError(f"{name}: the strength {strength!r} is not a finite number")
    if whole and float(strength) != int(strength):
        raise ValueError(f"{name}: the strength {strength:g} is not a whole number")
    high = MAX_POINTS if high is None else high
    if strength < low or (strength == low and not closed) or strength > high:
        side = "[" if closed else "("
        raise ValueError(f"{name}: the strength {strength:g} is outside {side}{low:g}, {high:g}]")
    return int(strength) if whole else float(strength)


def chain_size(chain, n_points):
    """Points a chain leaves at most, refused above ``MAX_POINTS`` or ``MAX_GROWTH`` times the input.

    Parameters
    ----------
    chain : list of (str, float or None)
        Checked strengths.
    n_points : int
        Points of the input.

    Returns
    -------
    int
    """
    bound = min(MAX_POINTS, MAX_GROWTH * n_points)
    n = n_points
    for name, strength in chain:
        if name in ("removal", "crop"):
            n = max(1, int(np.ceil(strength * n)))
        elif name in ("outliers", "clutter"):
            n = n + int(round(strength * n)) + (40 if name == "clutter" else 0)
        elif name in ("resample", "simplify"):
            n = int(strength)
        if n > bound:
            raise ValueError(f"{name}:{strength:g} would make {n} points; at most {bound} (the smaller of "
                             f"{MAX_POINTS} and {MAX_GROWTH} times the input's {n_points})")
    return n


def apply_chain(points, chain, rng=None):
    """Apply ``[(name, strength or None), ...]`` in order with one generator.

    Parameters
    ----------
    points : (n, 3) float
    chain : list of (str, float or None)
    rng : int or numpy.random.Generator

    Returns
    -------
    (m, 3) float
    """
    rng = np.random.default_rng(rng)
    for name, strength in chain:
        if name not in ATTACKS:
            raise ValueError(f"unknown attack {name!r}; known: {sorted(ATTACKS)}")
        func, needs = ATTACKS[name]
        strength = check_strength(name, strength)
        points = func(points, strength, rng) if needs else func(points, rng)
    return points
