"""Local shape features (FPFH) for part-to-whole registration and candidate search.

open3d computes the features and faiss searches a large catalogue's index
of them, so this module sits outside :mod:`pipeline.kernels`; the robust
estimation on top of them (RANSAC with scale, trimmed ICP) is pure NumPy in
:mod:`pipeline.kernels.registration`.

Scale.  FPFH depends on the radius it is computed over, and a suspect's
scale is unknown.  Every cloud is therefore described in units of a *voxel*
(points are voxel-downsampled, normals estimated within 2 voxels, FPFH
within 5): for the original the voxel is set from its median point spacing
so that about ``target`` keypoints remain; for a suspect the voxel is the
original's times a hypothesised scale.  The first hypothesis assumes the
suspect has the original's sampling density (then the spacing ratio is the
scale); the others step by sqrt(2) around it, so a resampled copy or a scene
whose clutter has another density is still described at a radius within
about 20 % of the right one, which FPFH tolerates.
"""

from __future__ import annotations

import hashlib
import io
import time
from collections import Counter, OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from .kernels import registration
from .kernels.descriptor import D2_BINS, cumulative_distance, cut_descriptors, d2_descriptor, descriptor_distance
from .kernels.resampling import estimate_normals, nearest_spacing
from .nearest import NearestTree

__all__ = [
    "fpfh", "voxel_for", "match", "register_global", "GlobalResult",
    "FeatureIndex", "build_index", "describe", "describe_scales", "train_ivf", "fold_fpfh", "fold_queries", "nearest_exact", "geometry_hash", "harmonic", "best_overlap", "overlap_order", "overlap_of", "dense_part", "median_spacing", "scale_hint",
    "suspect_views", "dense_view", "polish", "struck_out",
]

NORMAL_RADIUS = 2.0     # voxels
FEATURE_RADIUS = 5.0    # voxels


def _o3d():
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def median_spacing(points, sample=20000, rng=0):
    """Median nearest-neighbour distance, on a seeded subsample of large clouds."""
    if len(points) > sample:
        # a random subsample's own spacing is larger; measure the sample's
        # distances to the whole cloud instead
        idx = np.random.default_rng(rng).choice(len(points), sample, replace=False)
        dist, _ = cKDTree(points).query(points[idx], k=2)
        return float(np.median(dist[:, 1]))
    return float(np.median(nearest_spacing(points)))


def voxel_for(points, spacing, target=4000):
    """Voxel size that leaves about ``target`` keypoints on a surface sampled at ``spacing``."""
    # a surface of n points at spacing s has an area of about n s^2 / 2, and
    # voxel-downsampling keeps about 2 points per voxel-sized patch of it
    return float(spacing * np.sqrt(max(len(points), 1) / target))


def fpfh(points, voxel, *, most=None, rng=0):
    """Voxel-downsampled keypoints and their FPFH descriptors.

    Parameters
    ----------
    points : (n, 3) float
    voxel : float
        Downsampling voxel; normals are estimated within 2 voxels and FPFH
        within 5, so the descriptor of a scaled copy matches when ``voxel``
        is scaled with it.
    most : int, optional
        Keep at most this many keypoints, a seeded (``rng``) subsample of
        them in their order: only theirs are described, from every
        keypoint's neighbourhood, so each row is the one the whole set would
        give it.
    rng : int
        Seed of that subsample.

    Returns
    -------
    keypoints : (k, 3) float
    features : (k, 33) float32
        Each row normalised to unit L2 norm.
    """
    o3d = _o3d()
    origin = points.min(axis=0)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector((points - origin) / voxel))
    down = cloud.voxel_down_sample(1.0)
    if len(down.points) < 5:
        return np.empty((0, 3)), np.empty((0, 33), dtype=np.float32)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=NORMAL_RADIUS, max_nn=30))
    keys = np.asarray(down.points) * voxel + origin
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=FEATURE_RADIUS, max_nn=100)
    if most is not None and len(keys) > most:
        # sorted: open3d returns the selected rows in ascending index order, whatever order they are given
        pick = np.sort(np.random.default_rng(rng).choice(len(keys), most, replace=False))
        feat = o3d.pipelines.registration.compute_fpfh_feature(down, search, pick.tolist())
        keys = keys[pick]
    else:
        feat = o3d.pipelines.registration.compute_fpfh_feature(down, search)
    f = np.asarray(feat.data).T.astype(np.float32)
    f /= np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12)
    return keys, f


def match(query, reference, *, chunk=2048):
    """Nearest neighbours in feature space, both ways.

    Features are unit vectors, so the nearest is the largest dot product,
    found by matrix products in chunks (much faster than a k-d tree in 33
    dimensions).

    Parameters
    ----------
    query : (k, d) float, unit rows
    reference : (r, d) float, unit rows

    Returns
    -------
    forward : (k,) int
        Nearest reference row of every query row.
    back : (r,) int
        Nearest query row of every reference row.

    Of equal products the first row is kept, both ways (for finite products).
    """
    query = np.asarray(query, dtype=np.float32)
    reference = np.asarray(reference, dtype=np.float32)
    forward = np.empty(len(query), dtype=np.int64)
    best = np.full(len(reference), -np.inf, dtype=np.float32)
    back = np.zeros(len(reference), dtype=np.int64)
    cols = np.arange(len(reference))
    for lo in range(0, len(query), chunk):
        sim = query[lo:lo + chunk] @ reference.T                          # (c, r): one product, both ways
        forward[lo:lo + chunk] = sim.argmax(axis=1)
        if len(reference) >= MATCH_ROW_SCAN:
            # the first query row of the greatest product, row by row: argmax down the columns
            # of a wide C-ordered array reads it across the cache (71 against 11 ms, 2,048 x 6,000)
            for i, row in enumerate(sim, start=lo):
                better = row > best
                np.copyto(best, row, where=better)
                back[better] = i
            continue
        rows = sim.argmax(axis=0)
        value = sim[rows, cols]
        better = value > best
        best[better] = value[better]
        back[better] = rows[better] + lo
    return forward, back


MATCH_ROW_SCAN = 1024    # reference rows from which :func:`match` scans a chunk's rows one by one


def dense_part(points, k=6, factor=3.0):
    """Points whose k-th neighbour is within ``factor`` x the median such distance.

    Drops sparse outliers (uniform junk in the bounding box) before features
    are computed; surface points of any density above a third of the
    typical one stay.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    (m, 3) float
    """
    if len(points) <= k + 1:
        return points
    dist, _ = cKDTree(points).query(points, k=k + 1)
    kth = dist[:, -1]
    return points[kth <= factor * np.median(kth)]


@dataclass
class GlobalResult:
    """Outcome of :func:`register_global`."""

    transform: registration.Similarity   # suspect -> original, after ICP
    fitness: float                       # share of suspect points within 3 spacings of the original
    coverage: float                      # share of the original within 3 spacings of the suspect
    residual: float                      # RMS distance of the suspect inliers (original units)
    scale_hypothesis: float
    ransac_inliers: int
    seconds: float
    tried: list = field(default_factory=list)

    @property
    def score(self):
        """Overlap seen from both sides (harmonic mean of fitness and coverage)."""
        return harmonic(self.fitness, self.coverage)

    def failed(self, min_fitness=0.1, min_coverage=0.1):
        """True when too little of either cloud lies on the other: no registration."""
        return self.fitness < min_fitness or self.coverage < min_coverage


class _Original:
    """Everything about the original that a registration needs, computed once."""

    def __init__(self, points, spacing, target):
        self.points = points
        self.spacing = spacing
        self.tree = NearestTree(points)
        self.voxel = voxel_for(points, spacing, target)
        self.keypoints, self.features = fpfh(points, self.voxel)
        self.diag = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
        rng = np.random.default_rng(0)
        self.sample = points[rng.choice(len(points), min(len(points), 4000), replace=False)]
        self._normals = None

    @property
    def normals(self):
        """(m, 3) unit normals of the original, for point-to-plane ICP (computed when first asked)."""
        if self._normals is None:
            self._normals = estimate_normals(self.points, tree=self.tree)
        return self._normals


_CACHE: "OrderedDict[tuple, _Original]" = OrderedDict()
CACHED_ORIGINALS = 8     # originals whose registration state a process keeps (a worker checks the same few often)
CACHED_BYTES = 512 * 2**20   # and at most about this much of it (points, tree, normals: ~4 copies of the points)


def _original(points, spacing, target, normals=None):
    # keyed by the hash of every coordinate: two originals that differ in one point never share state
    content = np.ascontiguousarray(points, dtype=np.float64)
    key = (points.shape, hashlib.sha256(content.tobytes()).hexdigest(), float(spacing), target)
    if key in _CACHE:
        _CACHE.move_to_end(key)
    else:
        _CACHE[key] = _Original(content.copy(), spacing, target)     # a copy: the caller's array may change
        while len(_CACHE) > 1 and (len(_CACHE) > CACHED_ORIGINALS
                                   or sum(4 * o.points.nbytes for o in _CACHE.values()) > CACHED_BYTES):
            _CACHE.popitem(last=False)                  # the least recently used first; the newest stays
    if normals is not None and _CACHE[key]._normals is None:
        _CACHE[key]._normals = normals
    return _CACHE[key]


def harmonic(fitness, coverage):
    """Overlap seen from both sides: the harmonic mean of fitness and coverage (0 when both are 0)."""
    return 0.0 if fitness + coverage == 0 else 2 * fitness * coverage / (fitness + coverage)


GOOD_RESIDUAL = 1.0   # spacings: a pose a few degrees off leaves more; the search goes on


def _good(result, good, spacing):
    return (result is not None and min(result.fitness, result.coverage) >= good
            and result.residual < GOOD_RESIDUAL * spacing)


FINAL_ITERATIONS = 300    # most ICP steps of the final refinement (it stops once converged)
PLANE_ITERATIONS = 20     # most point-to-plane ICP steps per cut (:func:`polish`, the search's poses)
PERTURBATIONS = (-30.0, -15.0, 15.0, 30.0)   # degrees, about each axis through the overlap's centre


def _multistart(sub, ref, original, transform, spacing):
    """Best ICP result from ``transform`` and from it turned by each of :data:`PERTURBATIONS`.

    Chosen by :func:`best_overlap`.
    """
    from scipy.spatial.transform import Rotation

    aligned = registration.apply(transform, sub)
    dist, _ = ref.tree.query(aligned, distance_upper_bound=3.0 * spacing)
    if not np.isfinite(dist).any():
        return transform
    centre = aligned[np.isfinite(dist)].mean(axis=0)
    starts = [transform]
    for axis in np.eye(3):
        for angle in PERTURBATIONS:
            turn = Rotation.from_rotvec(np.radians(angle) * axis).as_matrix()
            starts.append(registration.Similarity(turn @ transform.rotation, transform.scale,
                                                  turn @ (transform.translation - centre) + centre))
    fits, ranked = [], []
    for start in starts:
        fine = registration.refine_part(sub, ref.tree, original, start, spacing=spacing, iterations=100)
        f, c, r = registration.overlap(registration.apply(fine, sub), ref.tree, ref.sample[:1000], 3.0 * spacing)
        fits.append(fine)
        ranked.append((harmonic(f, c), r, f))
    return fits[best_overlap(ranked)]


OVERLAP_TIE = 0.05   # overlaps this close count as equal: the smaller residual decides
TIGHTER = 3.0          # a pose this many times tighter than the tied best, fitting as fully, wins ...
TIGHTER_OVERLAP = 0.25  # ... if its overlap is at least this share of the largest


def overlap_order(ranked, tie=OVERLAP_TIE):
    """Indices of registrations, best first, by ``(overlap, residual[, fitness])``.

    Among those whose overlap (harmonic mean of fitness and coverage) is
    within ``tie`` of the largest, the smallest residual goes first.  A pose
    slightly too large, or turned about a near-symmetry axis, can cover a
    little more of the original than the true one with several times its
    residual: the overlap alone would pick it.  For a small part that bias
    outgrows any tie (a 10 % crop of a vase laid 10 % too large, higher up,
    overlaps 0.52 against the true pose's 0.18, at 1.17 spacings of
    residual against 0.08), so a pose :data:`TIGHTER` times tighter than the
    tied best goes first when it fits as fully (``fitness`` within ``tie``;
    the residual counts only the points that fit) and its overlap is at least
    :data:`TIGHTER_OVERLAP` of the largest (a fit shrunk k times is k times
    tighter and covers k^2 times less).  Then the rest, tightest first.

    Parameters
    ----------
    ranked : sequence of (float, float) or (float, float, float)
        Overlap, residual and (default 1) fitness of each registration.

    Returns
    -------
    list of int
    """
    rows = [(r[0], r[1], r[2] if len(r) > 2 else 1.0) for r in ranked]
    top = max(h for h, _, _ in rows)
    tied = sorted((r, i) for i, (h, r, _) in enumerate(rows) if h >= top - tie)
    lead, lead_fit = tied[0][0], rows[tied[0][1]][2]
    tighter = sorted((r, i) for i, (h, r, f) in enumerate(rows)
                     if TIGHTER_OVERLAP * top <= h < top - tie and r * TIGHTER <= lead and f >= lead_fit - tie)
    first = [i for _, i in tighter] + [i for _, i in tied]
    placed = set(first)
    rest = sorted((r, i) for i, (_, r, _) in enumerate(rows) if i not in placed)
    return first + [i for _, i in rest]


def best_overlap(ranked, tie=OVERLAP_TIE):
    """Index of the best registration among ``(overlap, residual[, fitness])``: the first of :func:`overlap_order`."""
    return overlap_order(ranked, tie)[0]


def overlap_of(transform, suspect, original, spacing):
    """``(overlap, residual, fitness)`` of a registration, for :func:`best_overlap`."""
    ref = _original(original, spacing, 4000)
    f, c, r = registration.overlap(registration.apply(transform, suspect), ref.tree, ref.sample, 3.0 * spacing)
    return harmonic(f, c), r, f


def _icp_subsample(points, n, gen):
    """At most ``n`` of ``points``, drawn by ``gen`` and kept in their order (all of them when fewer)."""
    if len(points) <= n:
        return points
    return points[np.sort(gen.choice(len(points), n, replace=False))]


SEARCH_RESIDUAL = 0.5   # spacings: a part registered with more residual than this is searched again


def needs_search(transform, suspect, original, spacing):
    """Whether a registration leaves the suspect a poorly fitting part, so :func:`register_search` may do better.

    A crop laid where it belongs fits within the noise; one laid on the
    wrong place of a smooth shape fits everywhere, loosely.
    """
    ref = _original(original, spacing, 4000)
    fitness, coverage, residual = registration.overlap(registration.apply(transform, suspect), ref.tree,
                                                       ref.sample, 3.0 * spacing)
    return min(fitness, coverage) < 0.8 and residual > SEARCH_RESIDUAL * spacing


def scale_hint(dense, spacing):
    """The scale of a part (``dense``, :func:`dense_part`) on its original: the ratio of point spacings.

    A crop keeps its spacing.  None when the part's points coincide.
    """
    spread = median_spacing(dense)
    return spacing / spread if np.isfinite(spread) and spread > 0.0 else None


SEARCH_REFINED = 6     # of the search's coarse poses, refined on the ICP subsample (the best on every point)


def register_search(suspect, original, *, spacing, rotations, poses, icp_points=6000, rng=0, normals=None,
                    others=None):
    """Part-to-whole registration without features: :func:`registration.rotation_search` then ICP.

    The scale comes from the ratio of point spacings (a crop keeps its
    spacing).  Each of the ``poses`` best coarse poses of ``rotations``
    rotations is refined by a short trimmed ICP on about 1,500 points; the
    :data:`SEARCH_REFINED` best (ordered as :func:`best_overlap` orders)
    again on the ICP subsample, and the best of those on every point.

    A part of a near-symmetric shape (a piece of a solid of revolution) fits
    at many poses, and overlap alone cannot tell which is true.  With
    ``others`` given, the distinct poses that fit about as well as the
    chosen one (:func:`registration.poses_alike`) are refined the same way
    and appended to it, so that a detector can read the mark at each of them.

    Parameters
    ----------
    suspect : (n, 3) float
    original : (m, 3) float
    spacing : float
        Median nearest-neighbour distance of the original.
    rotations, poses : int
        ``detection.search_rotations`` and ``detection.search_poses``.
    icp_points : int
    rng : int
    normals : (m, 3) float, optional
        The original's normals, when the caller has them (else estimated once per original).
    others : list, optional
        Filled with the other poses (registration.Similarity) that fit about
        as well, at most ``registration.MAX_POSES``, tightest first.

    Returns
    -------
    registration.Similarity, or None when the suspect's spacing gives no scale (coincident points)
    """
    ref = _original(original, spacing, 4000, normals)
    dense = dense_part(suspect)
    scale = scale_hint(dense, spacing)
    if scale is None:
        return None
    sub = _icp_subsample(suspect, icp_points, np.random.default_rng(rng))
    probe = sub[:: max(1, len(sub) // 1500)]

    def refined(points, start, iterations, sample):
        fine = registration.refine_part(points, ref.tree, original, start, spacing=spacing, iterations=iterations)
        fine = registration.refine_plane(points, ref.tree, original, ref.normals, fine, spacing=spacing,
                                         iterations=PLANE_ITERATIONS)
        f, c, r = registration.overlap(registration.apply(fine, points), ref.tree, sample, 3.0 * spacing)
        return (harmonic(f, c), r, f), fine

    starts = registration.rotation_search(dense, original, scale, rotations=rotations, top=poses)
    quick = [refined(probe, start, 30, ref.sample[:1000]) for _, start in starts]
    quick = [quick[i] for i in overlap_order([rank for rank, _ in quick])]
    fits = [refined(sub, q[1], 60, ref.sample) for q in quick[:SEARCH_REFINED]]
    best = fits[best_overlap([rank for rank, _ in fits])][1]

    def final(pose):
        return polish(suspect, original, registration.refine_part(suspect, ref.tree, original, pose, spacing=spacing,
                                                                  widths=(3.0,), iterations=FINAL_ITERATIONS),
                      spacing=spacing, normals=normals)

    chosen = final(best)
    if others is not None:
        alike = registration.poses_alike(probe, ref.tree, ref.sample[:1000], chosen, [q[1] for q in quick], spacing,
                                         ref.normals)
        others.extend(registration.distinct_poses(probe, chosen, [final(pose) for pose in alike], spacing))
    return chosen


SCREEN_GRID = 32        # voxels per side of the screen's rotation search (the search's is 64: an eighth of the FFTs)
SCREEN_SCALES = (1.0, 2**0.5)   # factors on the scale hint it searches at (junk beside a copy widens its spacing)
SCREEN_DENSE = 1.5      # the part it places: points whose 6th neighbour is within this x the median (junk out)
SCREEN_PROBE = 500      # suspect points of its short ICP from each coarse pose
SCREEN_KEPT = 3         # of those, refined at the ICP subsample's resolution, best first
SCREEN_NEAR = 0.3       # a pose lays the suspect on the original: this share of it within one spacing, ...
SCREEN_EXCESS = 0.5     # ... or its squared distance to the tangent planes beyond both roughnesses at most this
                        # (spacings^2): calibrated on the leak benchmark, bench/coarse_screen.py


def search_screen(suspect, original, *, spacing, rotations, poses, normals=None, seen=None):
    """Whether the rotation search can lay a part on the original: a coarse search of its own first.

    :func:`register_search` costs an innocent candidate more than any other
    step, and finds nothing there.  This screen runs the same search on a
    grid of :data:`SCREEN_GRID` voxels, for the suspect's densest points
    (:data:`SCREEN_DENSE`: junk beside a copy would widen its spacing and
    so shrink the scale hint), at the scale hint and
    :data:`SCREEN_SCALES` times it, refines each of its ``poses // 2`` best
    coarse poses per scale by a short ICP on :data:`SCREEN_PROBE` points, and
    the :data:`SCREEN_KEPT` best of all (as :func:`overlap_order` orders) on
    the ICP subsample, to the tangent planes.  The search is worth running
    where one of them lays the suspect on the surface: :data:`SCREEN_NEAR`
    of it within one spacing, or as close to the tangent planes as the
    roughness of both allows (:data:`SCREEN_EXCESS`; a noisy copy).

    Parameters
    ----------
    suspect : (n, 3) float
    original : (m, 3) float
    spacing : float
        Median nearest-neighbour distance of the original.
    rotations, poses : int
        ``detection.search_rotations`` and ``detection.search_poses``.
    normals : (m, 3) float, optional
    seen : list, optional
        Filled with ``(near, excess)`` of each pose refined, ``excess`` in
        squared spacings (:func:`registration.closeness`), until one passes.

    Returns
    -------
    bool
        False where no pose lies on the original (the search is skipped); True
        also where the suspect's spacing gives no scale (the search decides).
    """
    ref = _original(original, spacing, 4000, normals)
    dense = dense_part(suspect, factor=SCREEN_DENSE)
    scale = scale_hint(dense, spacing)
    if scale is None:
        return True
    probe = dense[:: max(1, len(dense) // SCREEN_PROBE)]
    sub = dense[:: max(1, len(dense) // 3000)]
    quick, refined = [], set()
    for factor in SCREEN_SCALES:
        for _, start in registration.rotation_search(dense, original, scale * factor, rotations=rotations,
                                                     grid=SCREEN_GRID, top=max(1, poses // 2), max_points=1500):
            fit = registration.refine_part(probe, ref.tree, original, start, spacing=spacing, iterations=20)
            f, c, r = registration.overlap(registration.apply(fit, probe), ref.tree, ref.sample[:1000], 3.0 * spacing)
            quick.append(((harmonic(f, c), r, f), fit))
        for i in overlap_order([rank for rank, _ in quick])[:SCREEN_KEPT]:
            if i in refined:
                continue
            refined.add(i)
            fine = registration.refine_part(sub, ref.tree, original, quick[i][1], spacing=spacing, iterations=30)
            fine = registration.refine_plane(sub, ref.tree, original, ref.normals, fine, spacing=spacing,
                                             iterations=PLANE_ITERATIONS)
            near, excess = registration.closeness(sub, ref.tree, fine, spacing, ref.normals)
            if seen is not None:
                seen.append((near, excess / spacing ** 2))
            if near >= SCREEN_NEAR or excess <= SCREEN_EXCESS * spacing ** 2:
                return True
    return False


def polish(suspect, original, transform, *, spacing, normals=None):
    """A part's registration after point-to-plane ICP (:func:`registration.refine_plane`), if that ranks better.

    Both are ranked by :func:`best_overlap`; on a tie the given one stays.

    Parameters
    ----------
    suspect : (n, 3) float
    original : (m, 3) float
    transform : registration.Similarity
    spacing : float
    normals : (m, 3) float, optional
        As for :func:`register_search`.

    Returns
    -------
    registration.Similarity
    """
    ref = _original(original, spacing, 4000, normals)
    fine = registration.refine_plane(suspect, ref.tree, original, ref.normals, transform, spacing=spacing,
                                     iterations=PLANE_ITERATIONS)
    tried = [transform, fine]
    return tried[best_overlap([overlap_of(t, suspect, original, spacing) for t in tried])]


SCALES = (1.0, 2**0.5, 2**-0.5, 2.0, 0.5, 2**1.5, 2**-1.5)


def register_global(suspect, original, *, spacing, iterations, target=4000, scales=SCALES, good=0.2, rng=0,
                    icp_points=6000, candidates_per_pool=8):
    """Part-to-whole similarity registration from FPFH correspondences.

    For each scale hypothesis (relative to the spacing ratio of suspect and
    original): describe the suspect at the scaled voxel, match to the
    original's features, estimate a similarity by RANSAC with scale
    (:func:`registration.ransac_similarity`), refine by trimmed ICP with a
    fixed cut (:func:`registration.refine_part`) and score the overlap from
    both sides (the best hypothesis has the highest harmonic mean of the
    fitness and the coverage).

    Parameters
    ----------
    suspect : (n, 3) float
    original : (m, 3) float
    spacing : float
        Median nearest-neighbour distance of the original.
    target : int
        About how many keypoints describe the original.
    scales : sequence of float
        Scale hypotheses, as factors on the spacing ratio.
    iterations : int
        RANSAC samples per hypothesis (``detection.ransac_iterations``).
    good : float
        The search ends at the first hypothesis whose fitness and coverage
        both reach this, with a residual under 2 spacings.
    rng : int
    icp_points : int
        Suspect subsample for the ICP.
    candidates_per_pool : int
        Distinct RANSAC hypotheses checked by a short ICP per pool of
        correspondences.

    Returns
    -------
    GlobalResult
    """
    t0 = time.perf_counter()
    ref = _original(original, spacing, target)
    gen = np.random.default_rng(rng)
    dense = dense_part(suspect)
    ratio = median_spacing(dense) / spacing
    sub = _icp_subsample(suspect, icp_points, gen)
    probe = sub[:: max(1, len(sub) // 1500)]
    best = None
    tried = []
    for factor in scales:
        s = ratio * factor
        keys, feats = fpfh(dense, ref.voxel * s)
        if len(keys) < 3:
            continue
        forward, back = match(feats, ref.features)
        # Two pools of correspondences: every suspect keypoint's nearest
        # original one (best when the suspect is part of the asset) and every
        # original keypoint's nearest suspect one (best when the asset is part
        # of a larger scene, whose clutter would swamp the first pool).
        pools = {"forward": (np.arange(len(keys)), forward), "back": (back, np.arange(len(ref.keypoints)))}
        for pool, (iq, ir) in pools.items():
            # each keypoint counts once however many correspondences it takes part in
            weights = 1.0 / np.maximum(np.bincount(ir, minlength=len(ref.keypoints))[ir],
                                       np.bincount(iq, minlength=len(keys))[iq])
            # features at this hypothesis only match at about this scale
            candidates = registration.ransac_similarity(
                keys[iq], ref.keypoints[ir], threshold=2.0 * ref.voxel, iterations=iterations, rng=gen,
                min_edge=2.0 * ref.voxel * s, scale_range=(1.0 / (1.6 * s), 1.6 / s), weights=weights,
                local_radius=0.3 * ref.diag * s, top=candidates_per_pool)
            # the inlier count is a weak judge among the best hypotheses; a
            # short ICP on a small subsample and the overlap decide
            checked = []
            for coarse, inliers in candidates:
                quick = registration.refine_part(probe, ref.tree, original, coarse, spacing=spacing,
                                                 iterations=10)
                f, c, _ = registration.overlap(registration.apply(quick, probe), ref.tree, ref.sample[:1000],
                                               3.0 * spacing)
                checked.append((harmonic(f, c), quick, inliers))
            if not checked:
                continue
            _, quick, inliers = max(checked, key=lambda x: x[0])
            fine = registration.refine_part(sub, ref.tree, original, quick, spacing=spacing)
            fitness, coverage, residual = registration.overlap(
                registration.apply(fine, suspect), ref.tree, ref.sample, 3.0 * spacing)
            result = GlobalResult(
                registration.Similarity(fine.rotation, fine.scale, fine.translation, fitness, residual),
                fitness, coverage, residual, float(s), int(inliers.sum()), 0.0)
            tried.append({"scale_hypothesis": float(s), "pool": pool, "fitness": fitness, "coverage": coverage,
                          "residual": residual, "ransac_inliers": int(inliers.sum()),
                          "correspondences": int(len(iq))})
            if best is None or result.score > best.score:
                best = result
            if _good(best, good, spacing):
                break
        if _good(best, good, spacing):
            break
    if best is None:
        identity = registration.Similarity(np.eye(3), 1.0, np.zeros(3), 0.0, float("inf"))
        best = GlobalResult(identity, 0.0, 0.0, float("inf"), float("nan"), 0, 0.0)
    else:
        # final refinement on every suspect point, from the best of a few
        # rotated starts (RANSAC on a near-symmetric shape can stop a few
        # tens of degrees off, in a basin the ICP cannot leave)
        start = _multistart(sub, ref, original, best.transform, spacing)
        # point-to-point ICP slides slowly along a smooth surface: let it run
        # to convergence (a few tenths of a second)
        fine = registration.refine_part(suspect, ref.tree, original, start, spacing=spacing,
                                        widths=(3.0,), iterations=FINAL_ITERATIONS)
        fitness, coverage, residual = registration.overlap(
            registration.apply(fine, suspect), ref.tree, ref.sample, 3.0 * spacing)
        best.transform = registration.Similarity(fine.rotation, fine.scale, fine.translation, fitness, residual)
        best.fitness, best.coverage, best.residual = fitness, coverage, residual
    best.tried = tried
    best.seconds = time.perf_counter() - t0
    return best


# ---------------------------------------------------------------------------
# Part-to-whole candidate search over a catalogue (issue 13)
# ---------------------------------------------------------------------------

INDEX_VOXEL = 4.0          # keypoint voxel, in median spacings of the cloud described
INDEX_KEYPOINTS = 2000     # most keypoints kept per asset (and per suspect description): 1.5 GB at 10,000 assets
QUERY_SCALES = (1.0, 2**-0.5, 0.5, 2**0.5)   # suspect voxel factors (fewer points than issued: smaller)

# Catalogues of more than a few assets: faiss IVF (:func:`train_ivf`).  bench/index_scale.py, one loaded
# core, seconds per suspect (12,000 descriptors): exact 12 to 35 at 30,000 rows, 11 to 31 at 99,000; the
# IVF 0.2 to 0.4, 0.5 to 0.7.  On the leak benchmark (31 assets, 57,656 rows; bench/triage_ivf.py) the IVF
# left every leak's asset at the same stage of the cascade and every innocent's candidates as many, at
# 0.40 s a suspect's search against 3.07 (median).  Below IVF_MIN rows (a few assets) the search stays
# exact.
IVF_MIN = 20_000      # index rows from which the search goes through a faiss IVF
IVF_PROBE = 16        # cells searched per query (of :func:`ivf_cells`)
VOTE_RATIO = 0.9      # Lowe's ratio test across assets (:meth:`FeatureIndex.votes`)
VOTE_NEIGHBOURS = 8   # nearest rows a descriptor's ratio test looks among
VOTE_CHUNK = 1024     # descriptors searched at once
BACKGROUND_POINTS = 20000   # points of the seeded background geometry (:func:`background_votes`)
BACKGROUND_WIDE = 64  # nearest rows kept per background descriptor, from which one asset's are struck out
IVF_GRAPH_SEARCH = 64  # candidates the HNSW graph of the cells keeps while finding a query's cells
IVF_CELL_ROWS = 1024  # most rows a cell holds on average, past sqrt(N) (a million rows): the search stays flat
IVF_ITERATIONS = 10   # k-means iterations of the coarse quantizer
IVF_SAMPLE = 64       # training rows per cell (a seeded subsample of larger sets)
IVF_CODEC = "SQfp16"  # faiss codes of each row's residual from its cell's centroid
FOLDED = 32           # coordinates an FPFH row is stored with (:func:`fold_fpfh`)
_UNFOLD = np.concatenate([np.ones(11), np.zeros(11), -np.ones(10)]).astype(np.float32)   # bin 33 from the 32


def describe(points, *, factor=1.0, max_keypoints=None, rng=0):
    """FPFH keypoints of a cloud at ``INDEX_VOXEL * factor`` of its own median spacing.

    Outliers are dropped first (:func:`dense_part`), so the voxel follows the
    surface's sampling; at most ``max_keypoints`` (default :data:`INDEX_KEYPOINTS`) are kept (seeded
    subsample).

    Returns
    -------
    keypoints : (k, 3) float
    features : (k, 33) float32, unit rows
    """
    return describe_scales(points, (factor,), max_keypoints=max_keypoints, rng=rng)[0]


def describe_scales(points, factors=None, *, max_keypoints=None, rng=0):
    """:func:`describe` at each voxel factor (default :data:`QUERY_SCALES`), the dense part and its
    spacing found once.

    Returns
    -------
    list of (keypoints (k, 3) float, features (k, 33) float32), one per factor
    """
    dense = dense_part(np.asarray(points, dtype=np.float64))
    spacing = median_spacing(dense)
    most = INDEX_KEYPOINTS if max_keypoints is None else max_keypoints
    return [fpfh(dense, INDEX_VOXEL * factor * spacing, most=most, rng=rng)
            for factor in (QUERY_SCALES if factors is None else factors)]


def geometry_hash(points, decimals=3):
    """Order- and format-independent hash of a point set's geometry (sha256, hex).

    Centres on the centroid, divides by the RMS distance from it, rounds to
    ``decimals`` digits and sorts the rows, so a re-save in another format
    (float32 or ASCII with enough digits), a re-ordering, a translation or a
    uniform rescale give the same hash; any real edit changes it.  Rotations
    are not undone (a rotated copy is a new geometry; the feature index finds
    it).  A coordinate lying within float noise of a rounding boundary can
    flip; the hash is a fast path, never the only check.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    str, 64 hex digits
    """
    p = np.asarray(points, dtype=np.float64)
    p = p - p.mean(axis=0)
    rms = float(np.sqrt((p**2).sum(axis=1).mean())) or 1.0
    q = np.round(p / rms * 10**decimals).astype(np.int64)
    q = q[np.lexsort(q.T[::-1])]
    h = hashlib.sha256(b"pointmark-geometry-v1")
    h.update(np.ascontiguousarray(q).tobytes())
    return h.hexdigest()


@dataclass
class FeatureIndex:
    """Local descriptors of a whole catalogue; a suspect's descriptors vote for assets.

    Attributes
    ----------
    keys : list of str, asset keys
    features : (N, 33) float32, unit rows, every asset's keypoint descriptors; None when ``ivf`` holds them
    owner : (N,) int32, index into ``keys`` of each row
    hashes : list of str, :func:`geometry_hash` of each asset
    prior : (n_assets,) float
        Share of votes each asset draws from unrelated background (procedural
        clutter, junk points): "hub" assets whose descriptors resemble
        anything are discounted by it.
    ivf : faiss.IndexIVFScalarQuantizer, optional
        The descriptors of a large catalogue (:func:`train_ivf`), faiss id =
        row of ``owner``; None: ``features`` searched exactly.
    shapes : (V, D2_BINS) float, optional
        Shape distributions (D2) of every asset, whole, cut
        (:func:`~pipeline.kernels.descriptor.cut_descriptors`) and its
        dense view (:func:`dense_view`).
    shape_owner : (V,) int32, optional
        Index into ``keys`` of each row of ``shapes``.
    sources : list of str, optional
        sha256 of the file each asset was described from (set by whoever
        builds the index from files), so a later catalogue that holds the
        same bytes can grow this index instead of describing them again.
    """

    keys: list
    features: np.ndarray
    owner: np.ndarray
    hashes: list
    prior: np.ndarray = None
    ivf: object = None
    shapes: np.ndarray = None
    shape_owner: np.ndarray = None
    sources: list = None

    def __post_init__(self):
        self._forget_background()

    @property
    def n_rows(self):
        """Descriptors indexed (N)."""
        return len(self.owner)

    def save(self, path):
        """Write the index as a ``.npz`` file."""
        from .io.pointcloud import atomic_write_bytes

        atomic_write_bytes(path, self.to_bytes())

    def to_bytes(self):
        """The index as the bytes of one ``.npz`` file (a faiss index as the uint8 array ``ivf``)."""
        return self._npz({"features": self.features} if self.ivf is None
                         else {"ivf": _faiss().serialize_index(self.ivf)})

    def to_parts(self):
        """The index as the bytes of a ``.npz`` file and of its faiss index apart (None for an exact index).

        The ``.npz`` records the faiss bytes' sha256 (``ivf_sha256``), so that
        file's own hash covers both; kept apart, the faiss index can be
        memory-mapped (:meth:`load` with ``open_ivf``) and shared by every
        process that searches it.

        Returns
        -------
        npz : bytes
        ivf : bytes or None
        """
        if self.ivf is None:
            return self.to_bytes(), None
        ivf = _faiss().serialize_index(self.ivf).tobytes()
        return self._npz({"ivf_sha256": np.array(hashlib.sha256(ivf).hexdigest())}), ivf

    def _npz(self, extra):
        buf = io.BytesIO()
        if self.shapes is not None:
            extra.update(shapes=self.shapes, shape_owner=self.shape_owner)
        if self.sources is not None:
            extra.update(sources=np.array(self.sources, dtype=str))
        np.savez(buf, keys=np.array(self.keys, dtype=str), owner=self.owner,
                 hashes=np.array(self.hashes, dtype=str), prior=self.prior, **extra)
        return buf.getvalue()

    @classmethod
    def load(cls, path, open_ivf=None):
        """An index from a ``.npz`` file (path or file object).

        ``open_ivf(sha256)`` returns the faiss index that :meth:`to_parts`
        kept apart (mapped) or its bytes, given the sha256 the ``.npz``
        recorded for it: it finds the file and checks it.
        """
        data = np.load(path)
        ivf = _faiss().deserialize_index(data["ivf"]) if "ivf" in data.files else None
        if "ivf_sha256" in data.files:
            if open_ivf is None:
                raise ValueError(f"{path}: the index's faiss part is kept apart: give open_ivf")
            ivf = open_ivf(str(data["ivf_sha256"]))
            if isinstance(ivf, (bytes, bytearray)):
                ivf = _faiss().deserialize_index(np.frombuffer(ivf, dtype=np.uint8))
        feats = data["features"] if "features" in data.files else None
        shapes = (data["shapes"], data["shape_owner"]) if "shapes" in data.files else (None, None)
        sources = [str(h) for h in data["sources"]] if "sources" in data.files else None
        return cls([str(k) for k in data["keys"]], feats, data["owner"],
                   [str(h) for h in data["hashes"]], data["prior"], ivf, *shapes, sources)

    def with_ivf(self, *, rng=0):
        """This index searched through a faiss IVF (:func:`train_ivf`) trained on all its descriptors.

        ``self`` is left as it is; the copy holds its descriptors in the IVF
        only (``features`` None) and keeps ``prior`` (:func:`background_votes`
        recomputes it for the new search).
        """
        if self.ivf is not None:
            return self
        ivf = train_ivf(self.features, len(self.features), rng=rng)
        _add_rows(ivf, self.features)
        return replace(self, features=None, ivf=ivf)

    def nearest(self, queries, k, *, probe=IVF_PROBE, without=None):
        """The ``k`` most similar index rows of each query row: exact, or through ``ivf``.

        Parameters
        ----------
        queries : (c, 33) float32, unit rows
        k : int
        probe : int
            Cells of ``ivf`` searched per query.
        without : str, optional
            An asset key whose rows are left out of the search.

        Returns
        -------
        top : (c, k) int, most similar first; -1 where the IVF's probed cells hold fewer than k rows
        similarity : (c, k) float, -inf where ``top`` is -1
        """
        rows = None if without is None else np.flatnonzero(self.owner == self.keys.index(without))
        if self.ivf is None:
            if rows is None:
                return nearest_exact(queries, self.features, k)
            kept = np.setdiff1d(np.arange(self.n_rows), rows)
            if len(kept) == 0:
                return np.full((len(queries), k), -1), np.full((len(queries), k), -np.inf)
            top, val = nearest_exact(queries, self.features[kept], min(k, len(kept)))
            pad = k - top.shape[1]
            return (np.pad(kept[top], ((0, 0), (0, pad)), constant_values=-1),
                    np.pad(val, ((0, 0), (0, pad)), constant_values=-np.inf))
        faiss = _faiss()
        if rows is None or not len(rows):
            params = faiss.SearchParametersIVF(nprobe=probe)
        else:
            # an asset's rows are added together (FeatureIndex.add): one range of faiss ids
            assert rows[-1] - rows[0] + 1 == len(rows), "an asset's index rows are not contiguous"
            inside = faiss.IDSelectorRange(int(rows[0]), int(rows[-1]) + 1)
            outside = faiss.IDSelectorNot(inside)             # both kept alive through the search
            params = faiss.SearchParametersIVF(nprobe=probe, sel=outside)
        val, top = self.ivf.search(fold_queries(queries), k, params=params)
        return top, np.where(top >= 0, val, -np.inf)

    def add(self, keys, descriptors, hashes, shapes=None):
        """Append assets from their descriptors, in place (``prior`` is left as it was).

        Parameters
        ----------
        keys : list of str, new asset keys
        descriptors : list of (k_i, 33) float32, unit rows, per asset
        hashes : list of str, per asset
        shapes : list of (V_i, D2_BINS) float, optional, per asset
        """
        self._refuse_indexed(keys)
        self._forget_background()                      # every asset's background share changes with the rows
        faiss = _faiss() if self.ivf is not None else None
        if faiss is not None and not isinstance(faiss.downcast_InvertedLists(self.ivf.invlists),
                                                faiss.ArrayInvertedLists):
            # faiss aborts the process on an add to mapped lists: refuse before it is reached
            raise ValueError("a memory-mapped index cannot grow: load it whole (FeatureIndex.load, read, not mapped)")
        first = len(self.keys)
        feats = (np.concatenate(descriptors).astype(np.float32) if descriptors
                 else np.zeros((0, 33), dtype=np.float32))
        if self.ivf is not None:
            _check_fpfh(feats)                        # before anything changes
        owner = np.concatenate([np.full(len(f), first + i, dtype=np.int32) for i, f in enumerate(descriptors)]
                               + [np.zeros(0, dtype=np.int32)])
        if self.ivf is None:
            self.features = np.concatenate([self.features, feats])
        else:
            _add_rows(self.ivf, feats)               # the coarse quantizer stays as trained
        self.keys, self.hashes = self.keys + list(keys), self.hashes + list(hashes)
        self.owner = np.concatenate([self.owner, owner])
        if shapes is not None:
            old = self.shapes if self.shapes is not None else np.zeros((0, D2_BINS))
            old_owner = self.shape_owner if self.shape_owner is not None else np.zeros(0, dtype=np.int32)
            self.shapes = np.concatenate([old] + list(shapes))
            self.shape_owner = np.concatenate([old_owner] + [np.full(len(v), first + i, dtype=np.int32)
                                                             for i, v in enumerate(shapes)])
        if self.prior is not None:
            self.prior = np.concatenate([self.prior, np.zeros(len(keys))])

    def _refuse_indexed(self, keys):
        twice = sorted(set(keys) & set(self.keys)) + sorted(k for k, n in Counter(keys).items() if n > 1)
        if twice:
            raise ValueError(f"asset keys already indexed or given twice: {twice}")

    def can_grow_to(self, n_assets):
        """Whether :meth:`extend` to ``n_assets`` assets keeps the search as fast as a fresh index's.

        An IVF's cells stay as trained, and a query searches :data:`IVF_PROBE`
        of them: at more than four times the rows it was trained for
        (:func:`ivf_cells`) each cell holds too many rows, and the index is
        built afresh instead.  An exact index can always grow.
        """
        if self.ivf is None:
            return True
        rows = self.n_rows * n_assets / max(len(self.keys), 1)
        nlist = self.ivf.nlist
        return rows <= 4 * min(nlist * nlist, nlist * IVF_CELL_ROWS)

    def extend(self, clouds):
        """Add assets to the index in place, as :func:`build_index` would have indexed them.

        An IVF keeps its coarse quantizer (faiss ``add``: nothing is
        retrained); an exact index that reaches :data:`IVF_MIN` rows is
        trained then.  ``prior`` is recomputed (:func:`background_votes`):
        every asset's background share depends on every other's descriptors.

        Parameters
        ----------
        clouds : dict of asset_key -> (n, 3) float, keys not yet indexed
        """
        self._refuse_indexed(list(map(str, clouds)))
        self.add(*_describe_assets(clouds))
        if self.ivf is None and self.n_rows >= IVF_MIN:
            trained = self.with_ivf()
            self.features, self.ivf = trained.features, trained.ivf
            self._forget_background()
        self.prior = background_votes(self)

    def _forget_background(self):
        """Drop what :meth:`_prior_without` kept: the rows or their search changed."""
        self._priors_without, self._background_wide = {}, None

    def shape_distances(self, points, whole=False):
        """Per asset, the least D2 distance between any view of the suspect and any of the asset.

        The suspect's views (:func:`suspect_views`) are its points, its dense
        part and its separate objects; an asset's are it whole, cut, and its
        own dense view.  So a copy with outliers (of an unevenly sampled scan
        too), an asset among other objects and a crop are each compared with
        what they derive from.

        Parameters
        ----------
        points : (n, 3) float
        whole : bool
            Also return the least distance to each asset's whole view alone.

        Returns
        -------
        (n_assets,) float, inf for an asset with no shape views; with
        ``whole``, a pair of such arrays (any view, the whole view)
        """
        out, out_whole = np.full(len(self.keys), np.inf), np.full(len(self.keys), np.inf)
        if self.shapes is None or len(self.shapes) == 0:
            return (out, out_whole) if whole else out
        cumulative, starts = self._cumulative_shapes()
        views = np.array([d2_descriptor(view - view.mean(axis=0)) for view in suspect_views(points)])   # never empty
        dist = cumulative_distance(views, cumulative).min(axis=0)
        np.minimum.at(out, self.shape_owner[starts], np.minimum.reduceat(dist, starts))
        if not whole:
            return out
        owners, first = np.unique(self.shape_owner, return_index=True)   # an asset's whole view comes first
        out_whole[owners] = dist[first]
        return out, out_whole

    def _prior_without(self, key):
        """:func:`background_votes` with ``key`` left out, kept per asset until :meth:`add` changes the rows.

        Every asset's is read off one wider search of the background
        (:meth:`_background_lists`): a query's nearest rows outside ``key``
        are its nearest rows with ``key``'s struck out, wherever the wider
        list keeps enough of them.  The few queries whose list does not are
        searched again without ``key`` (:meth:`nearest`).
        """
        kept = self._priors_without
        if key not in kept:
            share, asset, k = np.zeros(len(self.keys)), self.keys.index(key), min(VOTE_NEIGHBOURS, self.n_rows)
            lists, complete = self._background_lists() if k else ([], True)      # no rows: no votes
            for feats, top, val in lists:
                top, val, short = struck_out(top, val, self.owner, asset, k, complete)
                if short.any():
                    top[short], val[short] = self.nearest(feats[short], k, without=key)
                share += self._ratio_votes(top, val) / len(feats)
            kept[key] = share / max(len(lists), 1)
        return kept[key]

    def _background_lists(self):
        """The background's descriptors and their :data:`BACKGROUND_WIDE` nearest rows, searched once per index.

        Returns
        -------
        lists : list of (features (m, 33) float32, top (m, w) int, similarity (m, w) float)
        complete : bool
            Whether each list holds every index row (w is all of them).
        """
        if self._background_wide is None:
            wide, lists = min(BACKGROUND_WIDE, self.n_rows), []
            for feats in _background(BACKGROUND_POINTS, 0):
                found = [self.nearest(feats[lo:lo + VOTE_CHUNK], wide) for lo in range(0, len(feats), VOTE_CHUNK)]
                lists.append((feats, np.vstack([t for t, _ in found]), np.vstack([v for _, v in found])))
            self._background_wide = (lists, wide == self.n_rows)
        return self._background_wide

    def _cumulative_shapes(self):
        """``shapes``' cumulative histograms and where each run of one owner's rows starts, kept while
        ``shapes`` is the same array (:meth:`add` replaces it)."""
        kept = getattr(self, "_cumulative", None)
        if kept is None or kept[0] is not self.shapes:
            starts = np.flatnonzero(np.r_[True, self.shape_owner[1:] != self.shape_owner[:-1]])
            kept = (self.shapes, np.cumsum(self.shapes, axis=-1), starts)
            self._cumulative = kept
        return kept[1], kept[2]

    def twins(self, lenders, within):
        """Assets of the same shape as each lender, sampled otherwise: whole views within ``within``.

        The ratio test of :meth:`votes` splits a suspect's votes among such
        assets (a bunny at 8,000 and at 1,900 points), so one of them may
        draw almost none of the votes that its twin draws.

        Parameters
        ----------
        lenders : list of str, asset keys
        within : float, D2 distance between the assets' whole views (:func:`d2_descriptor`)

        Returns
        -------
        dict of lender key -> list of [asset key, distance], the lender left out
        """
        if self.shapes is None or not lenders:
            return {}
        owners, first = np.unique(self.shape_owner, return_index=True)   # an asset's whole view comes first
        whole = self.shapes[first]
        out = {}
        for key in lenders:
            row = np.flatnonzero(owners == self.keys.index(key))
            if len(row) == 0:
                continue
            d = np.atleast_1d(descriptor_distance(whole[row[0]], whole))
            out[key] = [[self.keys[owners[j]], float(d[j])] for j in np.argsort(d, kind="stable")
                        if d[j] <= within and owners[j] != owners[row[0]]]
        return out

    def exact(self, points):
        """Asset keys whose geometry hash equals the suspect's (re-saves, re-orderings)."""
        h = geometry_hash(points)
        return [k for k, other in zip(self.keys, self.hashes) if other == h]

    def votes(self, features, *, ratio=VOTE_RATIO, chunk=VOTE_CHUNK, neighbours=VOTE_NEIGHBOURS, probe=IVF_PROBE,
              without=None):
        """Votes per asset of one set of suspect descriptors.

        Each descriptor votes for the asset of its nearest index descriptor
        when that is clearly nearer than the nearest descriptor of any
        other asset (Lowe's ratio test across assets: ``d1 < ratio * d_other``
        among the ``neighbours`` nearest; ``probe`` cells searched through an IVF).
        ``without``: an asset key left out, as if it were not indexed.

        Returns
        -------
        (n_assets,) float
        """
        out = np.zeros(len(self.keys))
        if len(features) == 0 or self.n_rows == 0:
            return out
        neighbours = min(neighbours, self.n_rows)
        for lo in range(0, len(features), chunk):
            top, val = self.nearest(features[lo:lo + chunk], neighbours, probe=probe, without=without)
            out += self._ratio_votes(top, val, ratio)
        return out

    def _ratio_votes(self, top, val, ratio=VOTE_RATIO):
        """Votes per asset of queries' nearest rows (:meth:`nearest`'s answer): the ratio test of :meth:`votes`."""
        out = np.zeros(len(self.keys))
        dist = np.sqrt(np.maximum(2.0 - 2.0 * val, 0.0))            # inf where no row was found
        owners = np.where(top >= 0, self.owner[top], -1)
        other = owners != owners[:, :1]
        d_other = np.where(other, dist, np.inf).min(axis=1)
        ok = dist[:, 0] < ratio * d_other
        np.add.at(out, owners[ok, 0], 1.0)
        return out

    def rank(self, points, top_k, without=None):
        """The ``top_k`` assets a suspect most likely derives from.

        An exact geometry hash puts its asset first.  Otherwise the suspect
        is described at several voxel sizes (its sampling may differ from
        the issued copy's); per size, votes are normalised by the suspect's
        descriptor count, and an asset keeps its best size.

        Parameters
        ----------
        points : (n, 3) float
        top_k : int
        without : str, optional
            An asset key left out, as if it were not indexed: the votes that
            asset split with others of the same surface go to them, and so
            does its background share (it is ranked last, at -inf).

        Returns
        -------
        list of (asset_key, votes) ; votes is a share of the suspect's descriptors (inf for an exact hash)
        """
        without = without if without in self.keys else None
        exact = set(self.exact(points)) - {without}
        score = np.full(len(self.keys), -np.inf)
        prior = self.prior if self.prior is not None else np.zeros(len(self.keys))
        if without is not None and self.prior is not None:
            prior = self._prior_without(without)              # its background share goes to others too
        for _, feats in describe_scales(points):
            if len(feats):
                score = np.maximum(score, self.votes(feats, without=without) / len(feats) - prior)
        if without is not None:
            score[self.keys.index(without)] = -np.inf
        ranked = sorted(range(len(self.keys)), key=lambda i: (self.keys[i] not in exact, -score[i]))
        return [(self.keys[i], float("inf") if self.keys[i] in exact else float(score[i]))
                for i in ranked[:top_k]]


def _describe_assets(clouds):
    """Keys, descriptors, geometry hashes and shape views of each cloud, for :meth:`FeatureIndex.add`."""
    keys, feats, hashes, shapes = [], [], [], []
    for key, points in clouds.items():
        _, f = describe(points)
        keys.append(str(key))
        feats.append(f)
        hashes.append(geometry_hash(points))
        centred = np.asarray(points, dtype=np.float64) - np.mean(points, axis=0)
        dense = dense_view(centred)
        shapes.append(np.vstack([d2_descriptor(centred), cut_descriptors(centred),
                                 d2_descriptor(dense - dense.mean(axis=0))]))
    return keys, feats, hashes, shapes


def build_index(clouds, *, ivf=None):
    """Index the local descriptors of every asset.

    Parameters
    ----------
    clouds : dict of asset_key -> (n, 3) float
    ivf : bool, optional
        Search through a faiss IVF (:func:`train_ivf`); by default from
        :data:`IVF_MIN` index rows on.

    Returns
    -------
    FeatureIndex
    """
    index = FeatureIndex([], np.zeros((0, 33), dtype=np.float32), np.zeros(0, dtype=np.int32), [])
    index.add(*_describe_assets(clouds))
    if ivf or (ivf is None and index.n_rows >= IVF_MIN):
        index = index.with_ivf()
    index.prior = background_votes(index)
    return index


MAX_VIEW_PARTS = 6       # separate objects of a suspect described, the largest first
VIEW_DENSE = 2.0         # outlier cut of the dense view, in median k-th neighbour distances


def dense_view(points):
    """:func:`dense_part` twice at ``VIEW_DENSE``: a cloud without its sparse outliers.

    On a scan sampled unevenly it also drops the sparsest few per cent of
    the surface, so each asset is described by its own dense view too.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    (m, 3) float
    """
    return dense_part(dense_part(points, factor=VIEW_DENSE), factor=VIEW_DENSE)


def suspect_views(points):
    """What of a suspect may be an asset: its points, its dense part, its separate objects.

    The dense part drops sparse outliers (:func:`dense_part` twice, at
    ``VIEW_DENSE`` times the median neighbour distance: junk in the bounding
    box raises that median, so one pass keeps most of it); the objects
    are its separate objects (:func:`registration.separate_objects`) of at
    least 1/20 of it, the largest ``MAX_VIEW_PARTS``.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    list of (n_i, 3) float
    """
    points = np.asarray(points, dtype=np.float64)
    dense = dense_view(points)
    views = [points, dense] if len(dense) < len(points) else [points]
    if len(dense) >= 400:
        parts = registration.separate_objects(dense, float(np.median(nearest_spacing(dense))),
                                              min_points=max(200, len(dense) // 20))
        views += [dense[p] for p in parts[:MAX_VIEW_PARTS]]
    return views


EXACT_BLOCK = 64   # columns a block: a row's k-th greatest block maximum bounds its k-th greatest similarity
EXACT_SPARE = 4    # a row with more than 4 k + 64 columns at or above its bound (equal similarities) is selected linearly


def nearest_exact(queries, features, k):
    """The ``k`` most similar rows of ``features`` for each query row (unit rows: cosine).

    The k-th greatest of a row's block maxima (blocks of
    :data:`EXACT_BLOCK` columns) is a lower bound of its k-th greatest
    similarity: each of those k blocks holds a value at least as great.
    Only the few columns at or above it are sorted, not all N.  Rows that
    the bound does not narrow (many equal similarities, NaN) are selected
    in linear time instead.  Equal similarities come in column order; NaN
    counts as the least.

    Parameters
    ----------
    queries : (c, d) float
    features : (N, d) float
    k : int, 1 to N

    Returns
    -------
    top : (c, k) int, most similar first
    similarity : (c, k) float
    """
    return _top_k(queries @ features.T, k)


def _top_k(sim, k):
    """:func:`nearest_exact`'s answer from the similarities ``sim`` (c, N)."""
    c, n = sim.shape
    if not 1 <= k <= n:
        raise ValueError(f"k = {k}: the nearest rows asked must be 1 to the {n} rows")
    top, val = np.empty((c, k), dtype=np.int64), np.empty((c, k), dtype=sim.dtype)
    hard = np.ones(c, dtype=bool)
    blocks = n // EXACT_BLOCK
    if blocks >= k:
        maxima = sim[:, :blocks * EXACT_BLOCK].reshape(c, blocks, EXACT_BLOCK).max(axis=2)
        bound = np.partition(maxima, blocks - k, axis=1)[:, blocks - k]
        above = sim >= bound[:, None]
        count = above.sum(axis=1)
        hard = (count < k) | (count > EXACT_SPARE * k + EXACT_BLOCK)
        above[hard] = False
        easy = np.flatnonzero(~hard)
        rows, cols = np.nonzero(above)
        vals = sim[rows, cols]
        order = np.lexsort((cols, -vals, rows))                            # by row, greatest first, then column
        rows, cols, vals = rows[order], cols[order], vals[order]
        pick = np.searchsorted(rows, easy)[:, None] + np.arange(k)
        top[easy], val[easy] = cols[pick], vals[pick]
    if hard.any():
        top[hard], val[hard] = _top_select(sim[hard], k)
    return top, val


def _top_select(sim, k):
    """:func:`nearest_exact`'s answer for each row of ``sim`` (c, N), in linear time but for rows with NaN."""
    key = -sim                                                             # NaN last, as in a sort
    kth = np.partition(key, k - 1, axis=1)[:, k - 1:k]
    chosen, equal = key < kth, key == kth
    need = k - chosen.sum(axis=1)                                          # equal ones to take, first first
    ties = np.flatnonzero(equal.sum(axis=1) > need)
    chosen |= equal
    chosen[ties] &= ~equal[ties] | _first_true(equal[ties], need[ties])
    short = np.isnan(kth[:, 0])                                            # fewer than k numbers
    cols = np.empty((len(sim), k), dtype=np.int64)
    cols[~short] = np.nonzero(chosen[~short])[1].reshape(-1, k)            # exactly k a row, in column order
    cols[short] = np.lexsort((np.broadcast_to(np.arange(sim.shape[1]), key[short].shape), key[short]), axis=1)[:, :k]
    vals = np.take_along_axis(sim, cols, axis=1)
    order = np.lexsort((cols, -vals), axis=1)
    return np.take_along_axis(cols, order, axis=1), np.take_along_axis(vals, order, axis=1)


def _first_true(mask, count, width=1024):
    """(t, N) bool: the first ``count[i]`` True entries of each row of ``mask``, by blocks of ``width`` columns."""
    out = np.zeros_like(mask)
    seen = np.zeros(len(mask), dtype=np.int64)
    for lo in range(0, mask.shape[1], width):
        block = mask[:, lo:lo + width]
        ranks = np.cumsum(block, axis=1, dtype=np.int64) + seen[:, None]
        out[:, lo:lo + width] = block & (ranks <= count[:, None])
        seen = ranks[:, -1]
        if (seen >= count).all():
            break
    return out


def _faiss():
    import faiss

    return faiss


@contextmanager
def _one_thread(faiss):
    """faiss on one OpenMP thread inside the block (seeded k-means gives the same cells however run)."""
    before = faiss.omp_get_max_threads()
    faiss.omp_set_num_threads(1)
    try:
        yield
    finally:
        faiss.omp_set_num_threads(before)


def fold_fpfh(features):
    """FPFH rows without their last bin, which the other 32 determine.

    open3d normalises each of FPFH's three 11-bin histograms to the same sum
    (before the unit norm, which keeps them equal), so bin 33 is the first
    histogram's sum less the third's other ten bins.  A query folded by
    :func:`fold_queries` has exactly the inner product with the 32 that it
    has with the 33 (and 32 = 4 x 8 lets faiss use its SIMD kernels, about
    4x faster than at 33).

    Parameters
    ----------
    features : (n, 33) float32, FPFH rows

    Returns
    -------
    (n, 32) float32

    Raises
    ------
    ValueError
        For rows whose histograms' sums differ (not FPFH): folding them would change their similarities.
    """
    _check_fpfh(features)
    return np.ascontiguousarray(features[:, :FOLDED], dtype=np.float32)


def _check_fpfh(features):
    blocks = np.asarray(features, dtype=np.float32).reshape(len(features), 3, 11).sum(axis=2)
    if len(features) and np.abs(blocks - blocks[:, :1]).max() > 1e-4:
        raise ValueError("descriptor rows whose three histograms' sums differ are not FPFH: the IVF cannot hold them")


def fold_queries(queries):
    """(c, 32) float32: queries whose inner product with a :func:`fold_fpfh`-ed row is theirs with the row."""
    queries = np.asarray(queries, dtype=np.float32)
    return np.ascontiguousarray(queries[:, :FOLDED] + queries[:, FOLDED:] * _UNFOLD)


def ivf_cells(n_rows):
    """Cells of a faiss IVF for ``n_rows`` descriptors: sqrt(N), and past a million rows N / :data:`IVF_CELL_ROWS`.

    A query reads :data:`IVF_PROBE` cells; at sqrt(N) cells that is
    16 sqrt(N) rows (1.1 s a suspect at 3 million rows, 3.5 s at 30
    million), at a fixed size a cell it stays 16,384 rows however large the
    catalogue (``bench/index_scale.py``).
    """
    n_rows = max(int(n_rows), 1)
    return int(max(np.sqrt(n_rows), n_rows / IVF_CELL_ROWS))


def train_ivf(sample, n_rows, *, rng=0):
    """An empty faiss IVF for about ``n_rows`` descriptors, its coarse cells trained on ``sample``.

    ``IndexIVFScalarQuantizer``, inner product, :data:`IVF_CODEC` (fp16)
    codes of each row's residual from its cell's centroid, in :func:`fold_fpfh`'s 32
    coordinates: 64 bytes a row, 72 with faiss's id, 76 with the owner
    (1.5 GB for 10,000 assets of :data:`INDEX_KEYPOINTS` descriptors).  8-bit codes (SQ8,
    44 bytes a row) or PQ are too coarse for FPFH: a tenth
    of a suspect's descriptors have a runner-up within 2e-4 of their
    nearest row's cosine, and on the real scans SQ8 found the exact nearest
    row for 82 % of a kitten crop's descriptors, PQ (11 x 8 bits) for 15 %,
    fp16 for 99.5 % (``bench/index_scale.py``; on synthetic catalogues SQ8
    found it for 47 % against 98 %, and searched no faster).  :func:`ivf_cells` cells,
    each query searched in its :data:`IVF_PROBE` nearest, found through an
    HNSW graph of the cells' centroids (32 links a node; at 30,000 cells
    a flat scan of them would cost as much as the rows).  Spherical k-means
    and the graph built on one thread, seeded by ``rng``: the same sample
    gives the same index bytes in any process.

    Parameters
    ----------
    sample : (m, 33) float32, FPFH unit rows (faiss trains on a seeded ``IVF_SAMPLE`` a cell of them)
    n_rows : int
    rng : int

    Returns
    -------
    faiss.IndexIVFScalarQuantizer, trained, empty
    """
    faiss = _faiss()
    cells = max(1, min(ivf_cells(n_rows), len(sample)))
    ivf = faiss.index_factory(FOLDED, f"IVF{cells}_HNSW32,{IVF_CODEC}", faiss.METRIC_INNER_PRODUCT)
    ivf.cp.seed, ivf.cp.niter, ivf.cp.spherical = rng, IVF_ITERATIONS, True
    ivf.cp.max_points_per_centroid = IVF_SAMPLE
    with _one_thread(faiss):
        ivf.train(fold_fpfh(np.asarray(sample, dtype=np.float32)))
    faiss.downcast_index(ivf.quantizer).hnsw.efSearch = IVF_GRAPH_SEARCH
    return ivf


def _add_rows(ivf, features, chunk=1_000_000):
    """Append descriptor rows to ``ivf`` (faiss ids continue from its row count)."""
    for lo in range(0, len(features), chunk):
        ivf.add(fold_fpfh(features[lo:lo + chunk]))


def background_votes(index, n_points=BACKGROUND_POINTS, rng=0, without=None):
    """Share of votes each asset draws from unrelated, seeded background geometry.

    The background is the procedural clutter of :func:`attacks.clutter`
    (blobs, boxes, cylinders) and uniform junk in a box, described at every
    query scale (once per process).  ``without``: an asset key left out
    (:meth:`FeatureIndex.votes`).

    Returns
    -------
    (n_assets,) float
    """
    share = np.zeros(len(index.keys))
    described = _background(n_points, rng)
    for feats in described:
        share += index.votes(feats, without=without) / len(feats)
    return share / max(len(described), 1)


def struck_out(top, val, owner, asset, k, complete=False):
    """Each query's ``k`` nearest rows not owned by ``asset``, read off a wider list of its nearest rows.

    Parameters
    ----------
    top : (m, w) int, nearest rows, most similar first, -1 past the last found (w >= k)
    val : (m, w) float, their similarities, -inf where ``top`` is -1
    owner : (N,) int, each row's asset
    asset : int
    k : int
    complete : bool
        Whether the lists hold every row, so that nothing lies past them.

    Returns
    -------
    top : (m, k) int, -1 where fewer than k are left
    val : (m, k) float
    short : (m,) bool
        Queries left with fewer than ``k`` rows while their list was full:
        rows past the list may belong among them, so they must be searched again.
    """
    keep = (top >= 0) & (owner[np.maximum(top, 0)] != asset)
    order = np.argsort(~keep, axis=1, kind="stable")[:, :k]
    got = np.take_along_axis(keep, order, axis=1)
    out_top = np.where(got, np.take_along_axis(top, order, axis=1), -1)
    out_val = np.where(got, np.take_along_axis(val, order, axis=1), -np.inf).astype(val.dtype)
    short = ~got[:, -1] & (top[:, -1] >= 0) & (not complete)
    return out_top, out_val, short


_BACKGROUND: "dict[tuple, list]" = {}     # (n_points, rng) -> the background's descriptors at every scale


def _background(n_points, rng):
    if (n_points, rng) not in _BACKGROUND:
        from .kernels import attacks

        gen = np.random.default_rng(rng)
        scenes = [attacks.clutter(gen.normal(size=(10, 3)), n_points / 10.0, gen),
                  gen.uniform(-1.0, 1.0, (n_points // 4, 3))]
        _BACKGROUND[(n_points, rng)] = [feats for points in scenes for _, feats in describe_scales(points)
                                        if len(feats)]
    return _BACKGROUND[(n_points, rng)]
