"""Embedding and detection for one point set, composed from the kernels.

Arrays in, arrays out: no files, no configs, no secrets (only derived key
material).  The catalogue graph calls the same per-cluster functions
(:func:`plan_clusters`, :func:`embed_cluster`), so a Dask run and a serial run
produce the same bytes.
"""

from __future__ import annotations


import hashlib
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from .config import WatermarkParams, check_code
from .kernels import (clustering, coding, digest, fingerprint, graph, keys, modulation, registration, resampling,
                      revolution, spectral)
from .kernels import distortion as surface_measures
from .nearest import NearestTree

__all__ = [
    "Frame", "ClusterSpec", "frame_of", "plan_clusters",
    "cluster_basis", "cluster_normals", "modulate_cluster", "embed", "embed_with_bases", "detect",
    "detect_with_bases", "estimate_differences", "register", "Undecided", "decode", "decode_poses", "distortion", "WatermarkError",
    "Reference", "compute_reference", "embed_reference", "detect_reference", "fingerprint_length",
    "fingerprint_displacement", "cluster_amplitude", "budget_share",
    "capped", "mark_reach", "cluster_fingerprint", "check_count", "check_digest",
    "fingerprint_observation", "ReferenceMismatch", "params_record", "params_from_record", "ADDED_LATER",
    "band_for", "band_applies", "laid_whole", "lies_on",
]


class WatermarkError(ValueError):
    """The input cannot carry or be checked for the watermark (bad geometry, capacity)."""


class ReferenceMismatch(RuntimeError):
    """The reference rebuilt for detection differs from the one recorded at embedding."""


@dataclass(frozen=True)
class Frame:
    """Working frame of an original: coordinates are centred on its bbox centre."""

    centre: np.ndarray
    phi: float    # largest bbox side
    diag: float   # bbox diagonal


@dataclass(frozen=True)
class ClusterSpec:
    index: int
    seed_index: int
    size_limit: int
    members: np.ndarray = field(repr=False)

    def record(self, radius):
        return {"index": self.index, "seed_index": self.seed_index,
                "size_limit": self.size_limit, "size": int(len(self.members)),
                "radius": float(radius)}


@dataclass(frozen=True)
class Reference:
    """What embedding used and detection must rebuild: frame, clusters, bases, normals.

    Attributes
    ----------
    centre : (3,) float
    phi : float
        Largest bbox side of the original.
    specs : list of ClusterSpec
    bases : list of (n_c, n_coefficients) float
    normals : list of (n_c, 3) float, or None for the xyz displacement
    radii : list of float
    model_normals, spacing, grams : optional
        What detection would otherwise compute per suspect: the original's
        normals (n, 3) and point spacing (n,), and each cluster's
        :func:`kernels.resampling.normal_gram`.
    """

    centre: np.ndarray
    phi: float
    specs: list
    bases: list = field(repr=False)
    normals: list | None = field(repr=False, default=None)
    radii: list = field(default_factory=list)
    model_normals: np.ndarray | None = field(repr=False, default=None)   # (n, 3), for detection
    spacing: np.ndarray | None = field(repr=False, default=None)         # (n,), for detection
    grams: list | None = field(repr=False, default=None)                 # (3K, 3K) per cluster, normal model

    def cut(self, n_coefficients):
        """This reference with each basis cut to its first ``n_coefficients`` vectors (Grams refitted)."""
        if all(b.shape[1] == n_coefficients for b in self.bases):
            return self
        bases = [b[:, :n_coefficients] for b in self.bases]
        grams = None
        if self.grams is not None and self.model_normals is not None:
            grams = [resampling.normal_gram(b, self.model_normals[s.members]) for s, b in zip(self.specs, bases)]
        return replace(self, bases=bases, grams=grams)

    def records(self):
        """The clusters as manifests record them: index, seed_index, size_limit, size, radius."""
        return [s.record(r) for s, r in zip(self.specs, self.radii)]

    def detection_aids(self):
        """Keyword arguments of :func:`estimate_differences` that this reference saves computing."""
        return {"normals": self.model_normals, "grams": self.grams, "spacing": self.spacing}

    def digests(self):
        """Membership and basis digest of every cluster (16 hex digits each)."""
        return {"membership": [digest.membership_digest(s.members) for s in self.specs],
                "basis": [digest.basis_digest(b) for b in self.bases]}

    def verify(self, recorded, source="the ledger"):
        """Raise :class:`ReferenceMismatch` naming what differs from ``recorded`` digests."""
        mine = self.digests()
        check_count(len(self.specs), recorded, source)
        for kind in ("membership", "basis"):
            for i, digest_ in enumerate(mine[kind]):
                check_digest(i, kind, digest_, recorded, source)


def check_count(n_clusters, recorded, source):
    """Raise :class:`ReferenceMismatch` unless ``recorded`` holds ``n_clusters`` clusters."""
    if len(recorded["membership"]) != n_clusters:
        raise ReferenceMismatch(f"reference mismatch: {n_clusters} clusters rebuilt, "
                                f"{len(recorded['membership'])} recorded in {source}")


def check_digest(index, kind, value, recorded, source):
    """Raise :class:`ReferenceMismatch` when cluster ``index``'s ``kind`` digest is not the recorded one."""
    if value != recorded[kind][index]:
        what = "members" if kind == "membership" else "spectral basis"
        raise ReferenceMismatch(
            f"reference mismatch: cluster {index} {what} digest {value} differs from {recorded[kind][index]} "
            f"recorded in {source} (clustering, mesh or eigen-solver code or parameters changed); "
            f"refusing to report on this copy")


def compute_reference(points, params):
    """Frame, clusters, spectral bases and normals of an original (the one computation of a reference).

    :func:`pipeline.orchestrate.reference.build_reference` keeps it in a basis
    store; the catalogue graph runs its steps (:func:`plan_clusters`, then
    :func:`cluster_basis` and :func:`cluster_normals` per cluster) as tasks.

    Parameters
    ----------
    points : (n, 3) float, the original in its own frame
    params : WatermarkParams

    Returns
    -------
    Reference
    """
    frame = frame_of(points)
    centred = points - frame.centre
    specs = plan_clusters(centred, params)
    radii, bases = zip(*(cluster_basis(centred[s.members], params) for s in specs)) if specs else ((), ())
    normals = [cluster_normals(centred, s.members, params) for s in specs] if params.displacement == "normal" else None
    return Reference(frame.centre, frame.phi, specs, list(bases), normals, [float(r) for r in radii])


def fingerprint_length(n_clusters, params):
    """Chips of one recipient's fingerprint: cluster x axis x modulated coefficient."""
    return int(n_clusters) * 3 * params.total_bits * params.chip_rate


def fingerprint_displacement(reference, chips, params, points=None):
    """Displacement of every point for one recipient's fingerprint (centred frame).

    Each cluster's modulated coefficients get alpha * x (eq. 4 with the
    recipient's chips in place of b' p), synthesised with its basis; with
    ``displacement == "normal"`` only the motion along the normals is kept,
    at the same RMS and peak.

    Parameters
    ----------
    reference : Reference
    chips : (fingerprint_length,) float in {-1, +1}
    params : WatermarkParams
    points : (n, 3) float, optional
        The original (any translation); needed when ``params.amplitude ==
        "cluster"``.

    Returns
    -------
    moved : list of (n_c, 3) float, one per cluster, rows of its ``members``
    """
    if params.amplitude == "cluster" and points is None:
        raise ValueError("amplitude 'cluster' needs the original's points")
    count = 3 * params.total_bits * params.chip_rate
    return [cluster_fingerprint(basis, None if reference.normals is None else reference.normals[c],
                                chips[c * count:(c + 1) * count], reference.phi,
                                None if points is None else points[spec.members], params, len(reference.specs))
            for c, (spec, basis) in enumerate(zip(reference.specs, reference.bases))]


def cluster_fingerprint(basis, normals, chips, phi, cluster_points, params, n_planned):
    """Displacement of one cluster's points for its share of a fingerprint.

    Parameters
    ----------
    basis : (n_c, n_coefficients) float
    normals : (n_c, 3) float or None
    chips : (3 * total_bits * chip_rate,) float in {-1, +1}, axis-major
    phi : float, largest bbox side of the whole model
    cluster_points : (n_c, 3) float or None (needed with ``amplitude == "cluster"``)
    params : WatermarkParams
    n_planned : int, clusters planned on the whole model (see :func:`budget_share`)

    Returns
    -------
    (n_c, 3) float
    """
    count = params.total_bits * params.chip_rate
    amplitude = cluster_amplitude(params, phi, cluster_points, n_planned)
    x = np.asarray(chips).reshape(3, count)
    moved = basis[:, params.first_coefficient:params.first_coefficient + count] @ (amplitude * x.T)
    if params.displacement == "normal":
        cap = float(np.sqrt((moved**2).sum(axis=1).max()))
        moved, _ = modulation.along_normals(moved, normals, cap=cap)
    return capped(moved, params)


def fingerprint_observation(estimate, specs, params):
    """The weighted observation y of a suspect (see :func:`kernels.fingerprint.observation`)."""
    coverage = [n / max(len(s.members), 1) for s, n in zip(specs, estimate["support"])]
    return fingerprint.observation(estimate["deltas"], coverage, params.first_coefficient,
                                   params.total_bits * params.chip_rate)


def fingerprint_observations(estimate, specs, params):
    """The observation y at the chosen pose, then at each other pose that fits as well (``other_poses``)."""
    return [fingerprint_observation(e, specs, params) for e in [estimate, *estimate.get("other_poses", ())]]


def band_applies(params):
    """Whether :func:`band_for` needs the asset's points (else ``chip_rate`` stands)."""
    return params.band_noise is not None and params.tile_points is None and params.amplitude == "model"


def band_for(params, points):
    """The parameters this asset is marked with when ``band_noise`` sizes its band, else ``params``.

    The chip rate is the largest at most ``chip_rate`` (and at least what the
    code needs) whose band, the lowest ``total_bits * chip rate``
    coefficients of a cluster of ``cluster_size`` points, keeps ``band_gain``
    under noise of ``band_noise`` phi (:func:`kernels.spectral.surviving_band`;
    uniform noise in [-a, a] moves a point a / sqrt(3) along each tangent
    axis).  beta rises by sqrt(chip_rate / chip rate), so each copy moves as
    far as at ``chip_rate``.  The result has ``band_noise`` None: records
    hold what acted.  Large assets planned by cells (``tile_points``) and
    amplitude per cluster keep ``chip_rate``.

    Parameters
    ----------
    params : WatermarkParams
    points : (n, 3) float, the original

    Returns
    -------
    WatermarkParams
    """
    if params.band_noise is None:
        return params
    fixed = replace(params, band_noise=None, band_gain=ADDED_LATER["band_gain"])
    if not band_applies(params):
        return fixed
    phi = float(np.ptp(points, axis=0).max())
    spacing = float(np.median(resampling.nearest_spacing(points)))
    if phi == 0.0 or spacing == 0.0:
        return fixed                       # frame_of refuses such an asset with its reason
    band = spectral.surviving_band(min(params.cluster_size, len(points)), spacing,
                                   params.band_noise * phi / np.sqrt(3.0), params.band_gain)
    least = coding.least_chip_rate(params.total_bits, params.code)
    rate = int(min(params.chip_rate, max(least, (band - params.first_coefficient) // params.total_bits)))
    return replace(fixed, chip_rate=rate, beta=params.beta * float(np.sqrt(params.chip_rate / rate)))


def frame_of(points):
    """Centre, phi and diagonal of a point set, after checking it is a surface.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    Frame
    """
    lo, hi = points.min(axis=0), points.max(axis=0)
    sides = hi - lo
    phi = float(sides.max())
    if phi == 0.0:
        raise WatermarkError("all points are identical (the bounding box has zero size)")
    sample = points[:: max(1, len(points) // 20000)]
    centred = sample - sample.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    # Collinear up to the precision the coordinates were stored with: the
    # spread across the best line is within the rounding of the file (float32,
    # a LAS scale, a fixed number of decimals), whatever the float type here.
    across = sv[1] / np.sqrt(len(sample))
    if sv[1] <= 1e-9 * sv[0] or across <= 0.5 * _resolution(points):
        raise WatermarkError("the points are collinear; a surface is needed to carry a watermark")
    return Frame(centre=(lo + hi) / 2.0, phi=phi, diag=float(np.linalg.norm(sides)))


def _resolution(points):
    """Coarsest rounding step of the stored coordinates, over the three axes.

    Per axis the larger of the smallest gap between distinct values (a grid,
    e.g. a LAS scale) and the spacing of the float type the values fit in
    (float32 or float64) at the axis's largest magnitude.
    """
    as32 = points.astype(np.float32).astype(np.float64)
    eps = np.finfo(np.float32 if np.array_equal(as32, points) else np.float64).eps
    steps = []
    for axis in points.T:
        values = np.unique(axis)
        gap = float(np.diff(values).min()) if len(values) > 1 else 0.0
        steps.append(max(gap, eps * float(np.abs(axis).max())))
    return max(steps)


def plan_clusters(points, params):
    """Seeds and members of the clusters (paper, "Clustering").

    Parameters
    ----------
    points : (n, 3) float, centred
    params : WatermarkParams

    Returns
    -------
    list of ClusterSpec
    """
    n = len(points)
    check_code(params, WatermarkError)
    if n < params.n_coefficients + spectral.GUARD:
        raise WatermarkError(
            f"the model has {n} points, fewer than the {params.n_coefficients} spectral "
            f"coefficients the payload needs ({params.total_bits} bits x chip rate {params.chip_rate}): "
            f"the payload is longer than the capacity of this model"
        )
    specs = []
    for cell in _cells(points, params):
        seeds = _seed_indices(points[cell], params)
        sizes = np.full(len(seeds), params.cluster_size, dtype=np.int64)
        labels = clustering.grow_clusters(points[cell], seeds, sizes, on_touch=params.on_touch,
                                          cover=params.cover or params.tile_points is not None)
        for c, s in enumerate(seeds):
            members = cell[labels == c]
            if len(members) < params.n_coefficients + spectral.GUARD:
                continue  # too small to carry the payload; recorded by its absence
            specs.append(ClusterSpec(len(specs), int(cell[s]), int(params.cluster_size), members))
    if not specs:
        raise WatermarkError(
            f"no cluster reached the {params.n_coefficients + spectral.GUARD} points the payload needs "
            f"({params.total_bits} bits x chip rate {params.chip_rate}); the payload is longer than "
            f"the capacity: lower n_bits or chip_rate, or raise cluster_size"
        )
    return specs


def _cells(points, params):
    """Point indices planned together: the whole model, or the grid cells of a large one."""
    if params.tile_points is None:
        return [np.arange(len(points), dtype=np.int64)]
    if params.seeds is not None:
        raise WatermarkError("tile_points plans its own seeds in every cell; given seeds cannot apply")
    return clustering.grid_cells(points, params.tile_points)


def _seed_indices(points, params):
    if params.seeds is None:
        n_seeds = params.n_clusters
        if params.cover or params.tile_points is not None:
            n_seeds = max(1, int(np.ceil(len(points) / params.cluster_size)))
        return clustering.farthest_point_seeds(points, min(n_seeds, len(points)))
    seeds = np.asarray(params.seeds)
    if seeds.ndim == 2:
        return clustering.nearest_indices(points, seeds)
    if seeds.min() < 0 or seeds.max() >= len(points):
        raise WatermarkError(f"seed indices must lie in [0, {len(points)}), got {seeds.tolist()}")
    return seeds.astype(np.int64)


def cluster_basis(cluster_points, params):
    """Radius mesh and spectral basis of one cluster.

    Parameters
    ----------
    cluster_points : (n_c, 3) float
    params : WatermarkParams

    Returns
    -------
    radius : float
    basis : (n_c, n_coefficients) float
    """
    radius = graph.valence_radius(cluster_points, params.valence)
    adjacency = graph.radius_graph(cluster_points, radius)
    adjacency, _ = graph.connect_components(cluster_points, adjacency)
    _, basis = spectral.spectral_basis(graph.laplacian(adjacency), params.n_coefficients)
    return radius, basis


def chip_positions(material, cluster_index, params):
    """Coefficient index of every chip of one cluster, (m * c,) int."""
    count = params.total_bits * params.chip_rate
    if params.chip_layout == "interleaved":
        order = keys.key_permutation(material, f"layout/cluster={cluster_index}", count)
    else:
        order = np.arange(count)
    return params.first_coefficient + order


def sequences(material, cluster_index, params):
    """The key's +-1 sequences of one cluster, (3, m * c) float."""
    count = params.total_bits * params.chip_rate
    return np.stack([
        keys.pseudo_random_signs(material, f"cluster={cluster_index}/axis={a}", count)
        for a in range(3)
    ]).astype(np.float64)


def payload_bits(message_bits, params):
    """Message bits followed by their CRC, (total_bits,) uint8."""
    return np.concatenate([message_bits, modulation.crc_bits(message_bits, params.crc_bits)])


def chip_map(params):
    """What carries the coded word: the chip rate (repetition) or the symbol of each chip, (m * c,) int."""
    if params.code == "repetition":
        return params.chip_rate
    count = params.total_bits * params.chip_rate
    return coding.chip_groups(coding.coded_length(params.total_bits, params.code), count)


def modulate_cluster(basis, cluster_index, material, bits, amplitude, params, normals=None):
    """Displacement of one cluster's points from its basis (eq. 2-4 and the synthesis).

    Parameters
    ----------
    basis : (n_c, n_coefficients) float
    cluster_index : int
    material : bytes
        Key material of the key id.
    bits : (total_bits,) {0, 1}
    amplitude : float
        alpha.
    params : WatermarkParams
    normals : (n_c, 3) float, optional
        Unit normals of the cluster's points; needed when
        ``params.displacement == "normal"``.

    Returns
    -------
    (n_c, 3) float
    """
    delta = modulation.spread(coding.encode(bits, params.code), chip_map(params),
                              sequences(material, cluster_index, params), amplitude,
                              chip_positions(material, cluster_index, params))
    moved = basis[:, : len(delta)] @ delta
    if params.displacement == "xyz":
        return moved
    # Only the motion along the normals, at the paper's RMS (the layout does
    # not change it), and no point moves farther than the paper's embedding
    # of this payload would have moved one.
    paper = moved
    if params.chip_layout != "consecutive" or params.code != "repetition":
        paper = modulate_cluster(basis, cluster_index, material, bits, amplitude,
                                 replace(params, displacement="xyz", chip_layout="consecutive",
                                         code="repetition"))
    moved, _ = modulation.along_normals(moved, normals, cap=float(np.sqrt((paper**2).sum(axis=1).max())))
    return moved


def cluster_normals(centred, members, params):
    """Normals of a cluster's points when the displacement needs them, else None.

    Neighbours come from the whole model, so every process gets the same
    normals; with ``tile_points`` (large assets) from the cluster's own
    points, so a cluster task needs no more than its cluster.
    """
    if params.displacement != "normal":
        return None
    if params.tile_points is not None:
        return resampling.estimate_normals(centred[members])
    return resampling.estimate_normals(centred, at=members)


def embed(points, material, message_bits, params):
    """Watermark a point set.

    Parameters
    ----------
    points : (n, 3) float, any frame
    material : bytes
    message_bits : (n_bits,) {0, 1}
    params : WatermarkParams

    Returns
    -------
    watermarked : (n, 3) float, same order and frame as ``points``
    clusters : list of dict (index, seed_index, size_limit, size, radius)
    """
    ref = compute_reference(points, params)
    return embed_reference(points, ref, material, message_bits, params), ref.records()


def embed_reference(points, reference, material, message_bits, params):
    """Watermark an original whose reference is known, (n, 3) float in the original's frame."""
    centred = points - reference.centre
    return embed_with_bases(centred, reference.specs, reference.bases, material, message_bits, params,
                            reference.phi, reference.normals) + reference.centre


def embed_with_bases(centred, specs, bases, material, message_bits, params, phi, normals=None):
    """Watermark centred points whose clusters and bases are known, (n, 3) float.

    ``normals`` (one (n_c, 3) per cluster) saves recomputing them.
    """
    bits = payload_bits(message_bits, params)
    moved = centred.copy()
    for i, (spec, basis) in enumerate(zip(specs, bases)):
        alpha = cluster_amplitude(params, phi, centred[spec.members], len(specs))
        along = normals[i] if normals is not None else cluster_normals(centred, spec.members, params)
        moved[spec.members] += capped(modulate_cluster(basis, spec.index, material, bits, alpha, params, along),
                                      params)
    return moved


def cluster_amplitude(params, phi, cluster_points, n_planned):
    """alpha = beta * phi of one cluster, times :func:`budget_share`.

    Parameters
    ----------
    params : WatermarkParams
    phi : float
        Largest bbox side of the whole model (the paper's phi).
    cluster_points : (n_c, 3) float
        Used when ``params.amplitude == "cluster"``: phi is then the
        cluster's own largest bbox side, so a cluster of a 1 km tile moves
        by its local extent, not the tile's.
    n_planned : int
        Clusters planned on the whole model.

    Returns
    -------
    float
    """
    if params.amplitude == "cluster":
        return params.beta * float(np.ptp(cluster_points, axis=0).max()) if len(cluster_points) else 0.0
    return params.beta * phi * budget_share(params, n_planned)


def budget_share(params, n_planned):
    """Factor on alpha of clusters that cover a model on the paper's distortion budget.

    A cluster's displacement has energy alpha^2 x its modulated chips
    whatever its size (the basis is orthonormal), so ``n_planned`` clusters
    at alpha * sqrt(n_clusters / n_planned) move the model by the root mean
    square of the paper's ``n_clusters``: the copy keeps the paper's distance
    to the surface (``params.shares_budget``).  1.0 otherwise.
    """
    if not params.shares_budget:
        return 1.0
    n_seeds = params.n_clusters if params.seeds is None else len(params.seeds)
    return float(np.sqrt(min(1.0, n_seeds / max(int(n_planned), 1))))


def capped(moved, params):
    """A cluster's displacement (n_c, 3), scaled down as a whole so no point moves farther than the cap.

    Scaling the whole cluster keeps the spread-spectrum pattern (a clip per
    point would add a distortion correlated with no chip); detection
    normalises each cluster's energy, so it needs no record of the factor.
    """
    cap = params.max_displacement
    if cap is None or len(moved) == 0:
        return moved
    peak = float(np.sqrt((moved**2).sum(axis=1).max()))
    return moved if peak <= cap else moved * (cap / peak)


def distortion(original, watermarked, side=None, cells=None):
    """Distortion metrics relative to the bbox diagonal.

    RMSE of the point displacements (same order) and the symmetric Hausdorff
    distance of ROBUSTNESS.md; the RMS distance of each watermarked point to
    the tangent plane of its nearest original point (the part of the motion
    that changes the surface rather than its sampling); and the measures of
    :func:`pipeline.kernels.distortion.surface_distortion`: MRMS and
    Hausdorff distance between the two surfaces (both directions), normal
    deviation and the MSDM-style roughness measure.

    Parameters
    ----------
    original, watermarked : (n, 3) float
    side : dict, optional
        :func:`pipeline.kernels.distortion.original_side` of ``original``
        (saves recomputing it for every copy of one original).
    cells : list of (n_t,) int, optional
        Large scenes: the surface measures are computed cell by cell and
        pooled (:func:`pipeline.kernels.distortion.pooled_distortion`).

    Returns
    -------
    dict with rmse_rel_diag, hausdorff_rel_diag, surface_rmse_rel_diag,
    mrms_rel_diag, surface_hausdorff_rel_diag, normal_deviation_deg, msdm
    """
    diag = _diag(original)
    squares = sum(float(np.einsum("ij,ij->", d, d)) for d in
                  (watermarked[a:a + 2**20] - original[a:a + 2**20] for a in range(0, len(original), 2**20)))
    rmse = float(np.sqrt(squares / max(len(original), 1)))
    if cells is not None:
        surface = surface_measures.pooled_distortion(original, watermarked, cells)
    else:
        surface = surface_measures.surface_distortion(original, watermarked, side)
    return {"rmse_rel_diag": rmse / diag, "hausdorff_rel_diag": surface["hausdorff"] / diag,
            "surface_rmse_rel_diag": surface["surface_rms_forward"] / diag,
            "mrms_rel_diag": surface["mrms"] / diag,
            "surface_hausdorff_rel_diag": surface["surface_hausdorff"] / diag,
            "normal_deviation_deg": surface["normal_deviation_deg"], "msdm": surface["msdm"]}


def detect(suspect, original, material, params, detect_params):
    """Informed detection of a watermark in a suspect point set.

    Parameters
    ----------
    suspect : (m, 3) float, any order, count and similarity frame
    original : (n, 3) float, the reference
    material : bytes
    params : WatermarkParams
    detect_params : DetectParams

    Returns
    -------
    dict
        bits, message (HEX), bit_scores, p_value, detected, crc_ok,
        registration and per-cluster support.
    """
    return detect_reference(suspect, original, compute_reference(original, params), material, params,
                            detect_params)


def detect_reference(suspect, original, reference, material, params, detect_params):
    """Detection against an original whose reference is known; the result of :func:`detect`."""
    return detect_with_bases(suspect - reference.centre, original - reference.centre, reference.specs,
                             reference.bases, material, params, detect_params)


def detect_with_bases(suspect, reference, specs, bases, material, params, detect_params):
    """Detection when the original's clusters and bases are already known.

    ``suspect`` and ``reference`` are in the original's working frame.
    """
    estimate = estimate_differences(suspect, reference, specs, bases, detect_params, params, every_pose=True)
    return decode_poses(estimate, specs, material, params, detect_params)


REGISTERED = (0.05, 0.1)   # least fitness (share of the suspect on the original) and coverage of a registration


def estimate_differences(suspect, reference, specs, bases, detect_params, params, *, normals=None,
                         grams=None, spacing=None, deep=True, times=None, every_pose=False):
    """Register the suspect and estimate every cluster's r-hat - r (independent of the key).

    ``params`` are the embedding's (:class:`WatermarkParams`): its
    displacement model and the reach of the mark (:func:`mark_reach`).
    ``normals`` (n, 3), ``grams`` (per cluster) and ``spacing`` (n,) of the
    reference may come from the basis store (see :class:`Reference`); they are
    computed here when not given.  ``deep`` and ``times`` are :func:`register`'s:
    with ``deep=False`` a suspect that only the deep registration steps could
    place raises :class:`Undecided` (``times`` then holds the quick steps' seconds).
    ``every_pose``: also find and read the other poses that fit about as well
    (a fingerprint reader and :func:`decode_poses` read and count each).

    Returns
    -------
    dict with ``seconds_quick`` and ``seconds_deep`` (the registration's two parts), ``deltas`` (list of (K, 3) float), ``support`` and ``registration``
        (method, scale, fitness and coverage within 3 spacings, residual,
        rotation, translation, ``failed`` when fitness or coverage is
        under :data:`REGISTERED`; at the chosen pose also ``lies_on``
        (:func:`lies_on`; None under half the suspect within 3 spacings),
        ``whole`` (:func:`laid_whole`) and, where whole, ``sampling``: the
        suspect's median spacing there over the original's), and ``other_poses``: the same three for
        each other pose that fits about as well (a part of a near-symmetric
        shape, :func:`register`; empty unless ``every_pose``), which a
        fingerprint reader scores too and counts.
    """
    t0 = time.perf_counter()
    spacing = resampling.nearest_spacing(reference) if spacing is None else spacing
    if normals is None and detect_params.correspondence != "paper":
        normals = resampling.estimate_normals(reference)      # once, for the registration and the fit
    tree = NearestTree(reference)
    times = {} if times is None else times
    others = []
    try:
        transform = register(suspect, reference, float(np.median(spacing)), detect_params, tree, normals,
                             deep=deep, times=times, poses=others if every_pose else None)
    except Undecided:
        times["quick"] = time.perf_counter() - t0      # the reference's spacing, normals and tree too
        raise
    t1 = time.perf_counter()

    def at(pose, chosen=False):
        aligned = registration.apply(pose, suspect)
        fitness, coverage, _ = registration.overlap(aligned, tree, _coverage_sample(reference),
                                                    3.0 * float(np.median(spacing)))
        deltas, support = _coefficient_differences(aligned, reference, specs, bases, detect_params, params,
                                                   normals, grams, spacing)
        record = _registration_record(pose, fitness, coverage, reference, detect_params)
        if chosen:
            step = float(np.median(spacing))
            # under half the suspect within 3 spacings it cannot lie on the surface: not measured (None)
            record["lies_on"] = (lies_on(suspect, tree, pose, step, normals)
                                 if fitness >= registration.POSES_FIT else None)
            record["whole"] = laid_whole(len(suspect), fitness, coverage, record["lies_on"])
            if record["whole"]:       # the suspect's own spacing at this pose, in the original's
                record["sampling"] = _own_spacing(suspect) * pose.scale / step
        return {"deltas": deltas, "support": support, "registration": record}

    return {
        "seconds_registration": t1 - t0,
        "seconds_quick": t1 - t0 - times["deep"],
        "seconds_deep": times["deep"],
        **at(transform, chosen=True),
        "other_poses": [at(pose) for pose in others],
        "seconds_estimate": time.perf_counter() - t1,
    }


WHOLE_OFF = 16        # most suspect points beyond 3 spacings of the original for a copy laid on it whole
WHOLE_COVERAGE = 0.8  # least share of the original covered by such a copy
LIES_ON_POINTS = 1500  # suspect points its distance to the surface is measured on


def laid_whole(n_points, fitness, coverage, on_surface):
    """Whether a pose lays the whole suspect on the original, and it covers the original: the suspect is
    a copy of it whole (an unmarked original, a copy under another key) with nothing else beside it.

    At most :data:`WHOLE_OFF` suspect points lie beyond 3 spacings of the
    original, ``coverage`` is at least :data:`WHOLE_COVERAGE`, and the
    suspect lies on the surface, not merely near it (:func:`lies_on`, which
    needs the original's normals: without them, None, and so False).  A scan
    then checks the other candidates only where they may hold that surface
    (:func:`pipeline.orchestrate.candidates.after_whole`).

    Parameters
    ----------
    n_points : int
        The suspect's points.
    fitness, coverage : float
        Share of the posed suspect within 3 spacings of the original, and of
        the original within 3 spacings of it (:func:`registration.overlap`).
    on_surface : bool or None
        :func:`lies_on` at that pose.

    Returns
    -------
    bool
    """
    return bool(on_surface) and coverage >= WHOLE_COVERAGE and n_points - round(fitness * n_points) <= WHOLE_OFF


def lies_on(suspect, tree, pose, spacing, normals=None):
    """Whether ``pose`` lays the suspect on the original's surface, not merely near it.

    :func:`registration.lies_on` on at most :data:`LIES_ON_POINTS` of the
    suspect's points: half of them within 3 spacings, and there no farther
    from the tangent planes than the roughness of both allows.

    Parameters
    ----------
    suspect : (n, 3) float
    tree : NearestTree of the original (m, 3)
    pose : registration.Similarity
    spacing : float
        Median nearest-neighbour distance of the original.
    normals : (m, 3) float, optional

    Returns
    -------
    bool or None
        None without the original's normals.
    """
    if normals is None:
        return None
    sub = suspect[:: max(1, len(suspect) // LIES_ON_POINTS)]
    return bool(registration.lies_on(sub, tree, pose, spacing, normals))


def _own_spacing(points):
    """The median nearest-neighbour distance of a point set (float), in its own units."""
    return float(np.median(resampling.nearest_spacing(points)))


def _registration_record(transform, fitness, coverage, reference, detect_params):
    return {
        "method": detect_params.registration,
        "scale": float(transform.scale),
        "fitness": float(fitness),
        "coverage": float(coverage),
        # too little of either cloud lies on the other: nothing was registered
        "failed": bool(fitness < REGISTERED[0] or coverage < REGISTERED[1]),
        "residual_rel_diag": float(transform.residual) / _diag(reference),
        "rotation": np.asarray(transform.rotation, dtype=np.float64).tolist(),
        "translation": np.asarray(transform.translation, dtype=np.float64).tolist(),
    }


def decode(estimate, specs, material, params, detect_params):
    """Correlate estimated differences with one key's sequences: bits, scores, p-value."""
    qs, energies = [], []
    for spec, delta in zip(specs, estimate["deltas"]):
        q, energy = modulation.despread(delta, chip_map(params), sequences(material, spec.index, params),
                                        chip_positions(material, spec.index, params))
        qs.append(q)
        energies.append(energy)
    coverage = [n / max(len(s.members), 1) for s, n in zip(specs, estimate["support"])]
    z = modulation.combine_scores(np.array(qs), np.array(energies), coverage=coverage)   # per coded symbol
    bits, margin = coding.decode_soft(z, params.total_bits, params.code)
    message = bits[: params.n_bits]
    crc_ok = None
    if params.crc_bits:
        crc_ok = bool(np.array_equal(modulation.crc_bits(message, params.crc_bits), bits[params.n_bits:]))
    p_value = modulation.p_value_present(z)
    if params.code != "repetition":
        # a coded word spreads the energy over more symbols than bits, which the
        # chi-square test pays for; the decoded word's correlation does not.
        # Bonferroni over the two tests keeps the p-value valid.
        word = coding.encode(bits, params.code)
        p_value = min(1.0, 2.0 * min(p_value, modulation.p_value_codeword(z, word, params.total_bits)))
    return {
        "message": modulation.bits_to_hex(message),
        "bits": message.tolist(),
        "bit_scores": margin[: params.n_bits].tolist(),
        "crc_ok": crc_ok,
        "p_value": p_value,
        "detected": bool(p_value < detect_params.p_threshold),
        "registration": estimate["registration"],
        "clusters": [{"index": s.index, "support": int(n)} for s, n in zip(specs, estimate["support"])],
    }


def decode_poses(estimate, specs, material, params, detect_params):
    """:func:`decode` at every pose an estimate read; the least p-value, times the number of poses.

    A part or a sparse copy of a near-symmetric original fits it about as
    well at several poses (:func:`register`), and the mark reads only at the
    true one.  The pose whose presence p-value is least gives the bits; that
    p-value times the number of poses (Bonferroni) keeps the bound on a false
    detection.  Ties go to the registration's own pose.

    Parameters
    ----------
    estimate : dict
        :func:`estimate_differences` (``other_poses`` empty unless ``every_pose``).

    Returns
    -------
    dict
        :func:`decode`'s, at the pose read, with ``poses``: how many were read.
    """
    reads = [decode({**estimate, **pose}, specs, material, params, detect_params)
             for pose in [estimate, *estimate.get("other_poses", ())]]
    best = min(range(len(reads)), key=lambda i: (reads[i]["p_value"], i))
    out = reads[best]
    out["p_value"] = min(1.0, out["p_value"] * len(reads))
    out["detected"] = bool(out["p_value"] < detect_params.p_threshold)
    out["poses"] = len(reads)
    return out


def _diag(points):
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


def _coverage_sample(reference):
    """At most about 4,000 reference points, at which coverage is measured."""
    return reference[:: max(1, len(reference) // 4000)]


class Undecided(Exception):
    """A quick registration (``deep=False``) that only the expensive steps could settle."""


def register(suspect, reference, spacing, detect_params, tree, normals=None, *, deep=True, times=None, poses=None):
    """Suspect-to-reference similarity by ``detect_params.registration``, with its effort settings.

    The robust registration is a cascade.  Its quick steps (principal frames
    and ICP; the suspect's separate objects registered whole) settle whole
    copies and scenes that hold the original whole.  Its deep steps (the
    feature-based global RANSAC, the exhaustive rotation search) are for
    parts, crops and junk, and cost 10 to 100 times more.

    Parameters
    ----------
    suspect : (n, 3) float
    reference : (m, 3) float
    spacing : float
        Median nearest-neighbour distance of the reference.
    detect_params : DetectParams
    tree : NearestTree (or cKDTree) of ``reference``
    normals : (m, 3) float, optional
    deep : bool
        False: raise :class:`Undecided` where the deep steps would run.
    times : dict, optional
        Filled with ``quick`` and ``deep``: seconds of each part.
    poses : list, optional
        Filled with the other poses that fit about as well as the one
        returned: where the rotation search chose it, a part of a
        near-symmetric shape (:func:`features.register_search`); and for
        an original with a near-symmetry axis, the chosen pose turned about
        it (:func:`_turned_poses`), for a whole copy and a part alike.

    Returns
    -------
    registration.Similarity
    """
    times = {} if times is None else times
    times.update(quick=0.0, deep=0.0)
    t0 = time.perf_counter()
    method = detect_params.registration
    if method == "none":
        return registration.Similarity(np.eye(3), 1.0, np.zeros(3))
    if method == "paper":
        return registration.register_covariance(suspect, reference, spacing=spacing)
    if method == "global":
        from . import features   # open3d: imported only when used

        found = features.register_global(suspect, reference, spacing=spacing,
                                         iterations=detect_params.ransac_iterations).transform
        times["deep"] = time.perf_counter() - t0
        return found
    robust = registration.register_robust(suspect, reference, spacing=spacing, tree=tree)
    # a whole copy overlaps the original from both sides; a part of it, the
    # asset among clutter or junk, or a fit collapsed to a tiny scale (every
    # point "near" the original) does not, and there the principal frames
    # mean little: the scene's separate objects that look like the original
    # are registered whole, and failing that the feature-based global step
    # competes.  A sparse copy (10 % of the points) covers its original at
    # its own spacing, not the original's.
    sampling = _own_spacing(suspect) * robust.scale
    fitness, coverage, _ = registration.overlap(registration.apply(robust, suspect), tree,
                                                _coverage_sample(reference), 3.0 * max(spacing, sampling))
    if min(fitness, coverage) >= 0.8:
        # its ICP trims at a quantile of the distances, which junk points and
        # resampled borders widen, and they then pull the scale (1.7-2.4 %
        # short at 50 % outliers on sparse scans): polish with fixed cuts
        found = registration.refine_part(suspect, tree, reference, robust, spacing=spacing,
                                         widths=POLISH_WIDTHS, iterations=POLISH_ITERATIONS)
        if poses is not None:
            poses.extend(_turned_poses(suspect, reference, found, spacing, tree, normals))
        times["quick"] = time.perf_counter() - t0
        return found
    from . import features   # open3d: imported only when needed

    # the same quantile bias: one fixed cut before the other registrations compete
    robust = registration.refine_part(suspect, tree, reference, robust, spacing=spacing,
                                      widths=(3.0,), iterations=features.FINAL_ITERATIONS)
    placed = _register_parts(suspect, reference, spacing, tree)
    tried = [robust] if placed is None else [robust, placed]
    ranked = [features.overlap_of(t, suspect, reference, spacing) for t in tried]
    best = tried[features.best_overlap(ranked)]
    search = placed is not None and features.needs_search(best, suspect, reference, spacing)
    times["quick"] = time.perf_counter() - t0
    if placed is not None and not search:     # the original, whole, on one of the suspect's objects
        found = features.polish(suspect, reference, best, spacing=spacing, normals=normals)
        if poses is not None:
            _add_turns(poses, suspect, reference, found, spacing, tree, normals)
        return found
    if not deep:
        raise Undecided("the quick registration steps leave it undecided")
    t1 = time.perf_counter()
    if placed is None:
        tried.append(features.register_global(suspect, reference, spacing=spacing,
                                               iterations=detect_params.ransac_iterations).transform)
        ranked.append(features.overlap_of(tried[-1], suspect, reference, spacing))
        best = tried[features.best_overlap(ranked)]
        search = features.needs_search(best, suspect, reference, spacing)
    if search and detect_params.search_screen and not features.search_screen(
            suspect, reference, spacing=spacing, rotations=detect_params.search_rotations,
            poses=detect_params.search_poses, normals=normals):
        search = False           # a coarse search lays it on the original nowhere: the full one would not
    if search:
        # a part of a near solid of revolution: its axis and profile, then the turn about the axis
        turned = _revolution_pose(suspect, reference, spacing, tree, normals)
        if turned is not None:
            tried.append(turned)
            ranked.append(features.overlap_of(turned, suspect, reference, spacing))
            best = tried[features.best_overlap(ranked)]
            if best is turned and not features.needs_search(turned, suspect, reference, spacing):
                if poses is not None:
                    _add_turns(poses, suspect, reference, turned, spacing, tree, normals)
                times["deep"] = time.perf_counter() - t1
                return turned
        # a part laid loosely on a smooth shape, where features mislead: search every rotation
        others = []
        searched = features.register_search(suspect, reference, spacing=spacing, normals=normals,
                                            rotations=detect_params.search_rotations,
                                            poses=detect_params.search_poses, others=others)
        if searched is not None:
            tried.append(searched)
            ranked.append(features.overlap_of(searched, suspect, reference, spacing))
            best = tried[features.best_overlap(ranked)]
            if best is searched:
                if poses is not None:
                    poses.extend(others)
                    _add_turns(poses, suspect, reference, searched, spacing, tree, normals)
                times["deep"] = time.perf_counter() - t1
                return searched          # register_search ends with the polish already
            others = [searched, *others]     # the search's poses, beside another step's
    # point-to-point ICP slides slowly along smooth surfaces: finish on the tangent planes
    found = features.polish(suspect, reference, best, spacing=spacing, normals=normals)
    if search and poses is not None and searched is not None:
        poses.extend(registration.poses_alike(suspect, tree, _coverage_sample(reference), found, others, spacing,
                                              normals))
    if poses is not None:
        _add_turns(poses, suspect, reference, found, spacing, tree, normals)
    times["deep"] = time.perf_counter() - t1
    return found


POLISH_WIDTHS = (3.0, 1.5)   # fixed ICP cuts (spacings) polishing a whole copy's registration
POLISH_ITERATIONS = 60       # most ICP steps per cut
SCREEN_ITERATIONS = 3        # ICP steps (at the first cut) a turned start gets before it is screened
SCREEN_FITNESS = 3 * registration.POSE_FITNESS_TIE    # then: fitness at most this below the chosen pose's,
SCREEN_RESIDUAL = 2 * registration.POSE_RESIDUAL_TIE  # and residual at most this times its own, to go on
PART_SHAPE = 0.3         # most |log| difference of principal spreads for a part tried whole
MAX_PARTS = 3            # most parts registered whole, the most original-like first


def _turned_poses(suspect, reference, found, spacing, tree, normals=None, most=1500):
    """Poses of the suspect turned about the original's near-symmetry axes that fit as well as ``found``.

    The principal frames of a near solid of revolution leave the turn about
    its axis open, and ICP settles wherever it starts: each turn of
    :func:`registration.axis_turns` is refined on at most ``most`` points,
    and so are the best turns about its fitted axis of revolution
    (:func:`registration.fine_turns`: the true turn is a dip about a degree
    wide, and the principal axis of a scan can lie degrees off the axis).
    Each gets :data:`SCREEN_ITERATIONS` ICP steps first, and goes on only
    where it then fits within :data:`SCREEN_FITNESS` and
    :data:`SCREEN_RESIDUAL` of ``found`` (turns 5 degrees apart leave one
    near any pose that fits); those that fit about as well
    (:func:`registration.poses_alike`) are refined on all.  Empty for an
    original without such an axis, and where ``found`` does not lay the
    suspect on it (:func:`registration.lies_on`).
    """
    sub = suspect[:: max(1, len(suspect) // most)]
    sample = _coverage_sample(reference)
    starts = registration.axis_turns(reference, found)
    if not starts or not registration.lies_on(sub, tree, found, spacing, normals):
        return []
    anchor, direction, _ = _revolution_axis(reference, normals)
    starts += registration.fine_turns(sub, tree, found, anchor, direction, bound=3.0 * spacing)

    def refined(points, start, widths=POLISH_WIDTHS, steps=POLISH_ITERATIONS):
        return registration.refine_part(points, tree, reference, start, spacing=spacing, widths=widths,
                                        iterations=steps)

    # a few ICP steps first: only a turn that then fits nearly as well as ``found`` (its fit on
    # ``sub``: no step) is refined in full
    chosen = refined(sub, found, steps=0)
    floor = max(chosen.residual, 1e-3 * spacing)
    screened = [p for p in (refined(sub, s, POLISH_WIDTHS[:1], SCREEN_ITERATIONS) for s in starts)
                if p.fitness >= chosen.fitness - SCREEN_FITNESS and p.residual <= SCREEN_RESIDUAL * floor]
    alike = registration.poses_alike(sub, tree, sample, found, [refined(sub, p) for p in screened], spacing, normals)
    return registration.distinct_poses(suspect, found, [refined(suspect, p) for p in alike], spacing)


_AXES: "dict[tuple, tuple]" = {}     # sha256 of an original's coordinates and normals -> its axis of revolution
CACHED_AXES = 16


def _revolution_axis(reference, normals=None):
    """:func:`revolution.revolution_axis` of an original, kept per process by the hash of its coordinates
    and of the normals given (None: estimated), so that no check's axis depends on an earlier check's."""
    def digest(array):
        return hashlib.sha256(np.ascontiguousarray(array, dtype=np.float64).tobytes()).hexdigest()

    key = (digest(reference), None if normals is None else digest(normals))
    if key not in _AXES:
        normals = resampling.estimate_normals(reference) if normals is None else normals
        if len(_AXES) >= CACHED_AXES:
            _AXES.pop(next(iter(_AXES)))
        _AXES[key] = revolution.revolution_axis(reference, normals)
    return _AXES[key]


def _add_turns(poses, suspect, reference, found, spacing, tree, normals=None):
    """``poses`` with :func:`_turned_poses` of ``found`` added, the tightest :data:`registration.MAX_POSES` kept."""
    turned = _turned_poses(suspect, reference, found, spacing, tree, normals)
    if turned:
        poses[:] = registration.poses_alike(suspect, tree, _coverage_sample(reference), found, [*poses, *turned],
                                            spacing, normals)


REVOLUTION_STARTS = 8     # coarse poses of :func:`revolution.revolution_poses` refined by ICP
REVOLUTION_SCALE = 0.1    # most |log| change of scale in that ICP


def _revolution_pose(suspect, reference, spacing, tree, normals, most=1500):
    """A part of a near solid of revolution registered by its axis and profile (:mod:`kernels.revolution`).

    None for an original without a near-symmetry axis, and for a part that
    fixes no axis.  The best :data:`REVOLUTION_STARTS` coarse poses are
    refined by ICP on at most ``most`` points; the tightest, by the median
    distance to the original, is refined on every point and polished.
    """
    from . import features   # open3d: imported only when used

    if not registration.symmetry_axes(reference):
        return None
    normals = resampling.estimate_normals(reference) if normals is None else normals
    scale = features.scale_hint(features.dense_part(suspect), spacing)
    if scale is None:
        return None
    axis = _revolution_axis(reference, normals)
    starts = revolution.revolution_poses(suspect, resampling.estimate_normals(suspect), reference, axis, tree, spacing,
                                         scale, nearest=NearestTree)[:REVOLUTION_STARTS]
    if not starts:
        return None
    sub = suspect[:: max(1, len(suspect) // most)]

    def tightness(pose):
        return float(np.median(tree.query(registration.apply(pose, sub))[0]))

    fits = [registration.refine_part(sub, tree, reference, pose, spacing=spacing, iterations=30) for _, pose in starts]
    # the profile fixed the scale: a fit that shrank is collapsing (every point near one spot)
    fits = [f for f, (_, pose) in zip(fits, starts)
            if f.scale > 0 and abs(np.log(f.scale / pose.scale)) < REVOLUTION_SCALE]
    if not fits:
        return None
    best = min(fits, key=tightness)
    best = registration.refine_part(suspect, tree, reference, best, spacing=spacing, widths=POLISH_WIDTHS,
                                    iterations=POLISH_ITERATIONS)
    return features.polish(suspect, reference, best, spacing=spacing, normals=normals)


def _register_parts(suspect, reference, spacing, tree):
    """Whole-to-whole registration of the suspect's separate object that is the original, if any.

    A scene of separate objects is split into its connected parts; those
    whose principal spreads match the original's (:func:`registration.shape_signature`,
    unchanged by similarity transforms) are registered by ``register_robust``
    alone, most alike first.  Returns the first transform (suspect
    coordinates) that lays part of the suspect over the whole original
    (:func:`_whole_on_part`), else None.
    """
    least = max(200, min(len(suspect) // 50, len(reference) // 5))   # a part must be able to hold the original
    parts = registration.separate_objects(suspect, float(np.median(resampling.nearest_spacing(suspect))),
                                          min_points=least)
    target = _signature(reference)
    gaps = [(float(np.abs(_signature(suspect[part]) - target).max()), part) for part in parts]
    alike = sorted((g for g in gaps if g[0] < PART_SHAPE), key=lambda g: g[0])   # stable: ties keep size order
    for _, part in alike[:MAX_PARTS]:
        found = registration.register_robust(suspect[part], reference, spacing=spacing, tree=tree)
        if _whole_on_part(found, suspect, reference, spacing, tree):
            return found
    return None


def _signature(points):
    """log of the principal spreads relative to the largest, floored at 0.05 (flat parts compare too)."""
    return np.log(np.maximum(registration.shape_signature(points)[1:], 0.05))


def _whole_on_part(transform, suspect, reference, spacing, tree):
    """Whether a registration lays part of the suspect over (nearly) all of the original, closely."""
    _, coverage, residual = registration.overlap(registration.apply(transform, suspect), tree,
                                                 _coverage_sample(reference), 3.0 * spacing)
    return coverage >= 0.8 and residual < spacing


def _coefficient_differences(aligned, reference, specs, bases, detect_params, params, normals=None,
                             grams=None, spacing=None):
    if detect_params.correspondence == "paper":
        resampled, _ = resampling.snap_to_original(reference, aligned)
        deltas = [e.T @ (resampled[s.members] - reference[s.members]) for s, e in zip(specs, bases)]
        support = [int(np.any(resampled[s.members] != reference[s.members], axis=1).sum()) for s in specs]
        return deltas, support
    return resampling.fit_spectral_displacement(
        reference, normals, aligned, [s.members for s in specs], bases,
        iterations=detect_params.iterations, ridge=detect_params.ridge,
        tangential_gate=detect_params.tangential_gate, ratio_gate=detect_params.ratio_gate,
        gate_switch=detect_params.gate_switch, normal_only=params.displacement == "normal", grams=grams,
        spacing=spacing, trim=detect_params.outlier_trim,
        reach=None if detect_params.outlier_trim is None else mark_reach(params, reference, specs, bases),
    )


def mark_reach(params, reference, specs, bases):
    """Misfit along the normal that the message and a fingerprint can cause at each point.

    :func:`kernels.modulation.spread_reach` on each cluster's used columns,
    at most twice the cap (each mark is capped on its own).  Over 18 issued
    copies of 6 leak-benchmark assets (clusters of 2,400 points, beta 0.002)
    no point moved farther than 0.61 of its reach, and 99.9 % of them under
    0.43.

    Parameters
    ----------
    params : WatermarkParams
    reference : (n, 3) float, the original in its working frame
    specs : list of ClusterSpec
    bases : list of (n_c, K) float

    Returns
    -------
    (n,) float, 0 outside the clusters
    """
    phi = float(np.ptp(reference, axis=0).max())
    used = slice(params.first_coefficient, params.first_coefficient + params.total_bits * params.chip_rate)
    reach = np.zeros(len(reference))
    for s, e in zip(specs, bases):
        alpha = cluster_amplitude(params, phi, reference[s.members], len(specs))
        reach[s.members] = modulation.spread_reach(e[:, used], alpha)
    if params.max_displacement is not None:
        reach = np.minimum(reach, 2.0 * params.max_displacement)
    return reach


def params_record(params):
    """Plain-dict view of parameters for manifests and JSON.

    ``cover_amplitude`` is recorded as it acted: "full" wherever no budget is
    shared (records written before the key meant that).
    """
    record = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(params).items()}
    record["cover_amplitude"] = "paper" if params.shares_budget else "full"
    return record


# parameters added after records began, with what a record written before them meant (never the
# current default: an old row keeps the parameters it was issued under)
ADDED_LATER = {"amplitude": "model", "max_displacement": None, "tile_points": None, "code": "repetition",
               "cover_amplitude": "full", "band_noise": None, "band_gain": 0.6}


def params_from_record(record):
    """WatermarkParams of a :func:`params_record` dict, as written by any release."""
    values = {**ADDED_LATER, **record}
    seeds = values.get("seeds")
    values["seeds"] = None if seeds is None else tuple(tuple(s) if isinstance(s, list) else s for s in seeds)
    return WatermarkParams(**values)
