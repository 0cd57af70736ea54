"""Task functions of the catalogue graph.  Paths in, small results out.

plan (frame, clusters) -> one task per cluster (spectral basis, normals) ->
issue tasks (one per chunk of recipients: synthesis, write, read-back check).
Tasks read their own data and share references through the basis store
(a tiled asset's cluster task reads only its cluster's points from there),
so adding a recipient later costs a synthesis and a write.  An issue task
reads the bases once, one at a time, and holds the marked copies of its
recipients when they fit in MARKED_BYTES, else one copy at a time built from
scratch files: its memory is bounded by the asset, not by its clusters or
recipients.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..io.pointcloud import InputError, check_distinct, read_coordinates, read_points, sha256_file, write_points
from ..io.basis_store import BasisStore
from ..io.paths import pending_path
from ..io.scratch import Scratch
from ..kernels import clustering, digest, fingerprint
from ..kernels import distortion as surface_measures
from ..watermark import WatermarkError, cluster_fingerprint, distortion, fingerprint_length
from .reference import (MissingClusterPoints, cluster_points_name, cluster_reference, plan_reference,
                        verified_clusters)

__all__ = ["AssetPlan", "plan_asset", "cluster_task", "issue_task", "CopyIntegrityError", "copy_label",
           "realized_ratio", "MIN_REALIZED"]

# an issued copy must keep at least this share of its displacement at the file's precision
MIN_REALIZED = 0.5


def copy_label(asset_key, generation):
    """What a fingerprint is drawn for besides the recipient: the asset and its generation number."""
    return f"{asset_key}/g{int(generation)}"


class CopyIntegrityError(WatermarkError):
    """A copy that does not differ measurably from its original."""


@dataclass(frozen=True)
class AssetPlan:
    """What the plan task learns about an asset: its frame and clusters."""

    asset_key: str
    path: str
    source_sha256: str
    n_points: int
    centre: np.ndarray
    phi: float
    clusters: list          # ClusterSpec
    store: str
    store_key: str
    seconds: float


def _points(path, source_sha256):
    cloud = read_points(path, distinct=True)       # an original: repeated points are refused early
    if source_sha256 and sha256_file(path) != source_sha256:
        raise InputError(f"{path}: the file changed while the run was planned (sha256 differs)")
    return cloud


def plan_asset(asset_key, path, source_sha256, params, store, store_key, keep_original=False):
    """Load an asset and grow its clusters (or take them from the store); keep its bytes there if asked."""
    t0 = time.perf_counter()
    points = _points(path, source_sha256).points
    if keep_original:
        _keep(path, source_sha256, store)
    check_distinct(path, points)          # repeated points: a failed row, as in `pointmark embed`
    try:
        centre, phi, specs = plan_reference(points, params, store, store_key, cluster_points=True)
    except WatermarkError as exc:
        raise InputError(f"{path}: {exc}") from None
    return AssetPlan(asset_key, str(path), source_sha256, len(points), centre, phi, specs, str(store),
                     store_key, time.perf_counter() - t0)


def _keep(path, source_sha256, store):
    """The original's bytes into the basis store (once), checked against the hash the run planned with."""
    suffix = Path(path).suffix.lower()
    if BasisStore(store).kept_original(source_sha256, suffix) is not None:
        return
    data = Path(path).read_bytes()
    if hashlib.sha256(data).hexdigest() != source_sha256:
        raise InputError(f"{path}: the file changed while the run was planned (sha256 differs)")
    BasisStore(store).keep_original(data, source_sha256, suffix)


def cluster_task(plan, cluster_pos, params):
    """Spectral basis (and normals) of one cluster, saved to the store; its digests.

    Returns
    -------
    dict with radius, membership, basis (digests) and seconds
    """
    t0 = time.perf_counter()
    spec = plan.clusters[cluster_pos]
    part = None
    if params.tile_points is not None:      # the plan stored the cluster's points: no read of the asset
        try:
            part = cluster_reference(None, plan.centre, spec, params, plan.store, plan.store_key)
        except MissingClusterPoints:
            pass                            # not stored, or damaged: read the asset
    if part is None:
        points = _points(plan.path, plan.source_sha256).points
        part = cluster_reference(points, plan.centre, spec, params, plan.store, plan.store_key)
        if params.tile_points is not None:  # stored again for the next run
            BasisStore(plan.store).save_array(plan.store_key, cluster_points_name(spec.index),
                                              points[spec.members] - plan.centre)
    radius, basis, _ = part
    return {"radius": float(radius), "membership": digest.membership_digest(spec.members),
            "basis": digest.basis_digest(basis), "seconds": time.perf_counter() - t0}


def issue_task(plan, cluster_results, material, items, params, row_base):
    """Write one watermarked copy per recipient of ``items``; one ledger row each.

    Parameters
    ----------
    plan : AssetPlan
    cluster_results : list of dict (from :func:`cluster_task`)
    material : bytes
        Key material of the key id (never the master secret).
    items : list of (recipient, output_path)
    params : WatermarkParams
    row_base : dict
        Ledger columns shared by the rows.

    Returns
    -------
    list of dict
    """
    cloud = _points(plan.path, plan.source_sha256)
    points = cloud.points
    recorded = {"membership": [c["membership"] for c in cluster_results],
                "basis": [c["basis"] for c in cluster_results]}
    centre, phi, specs = plan.centre, plan.phi, plan.clusters      # checked against the digests below
    length = fingerprint_length(len(specs), params)
    bank = fingerprint.chip_bank(material, copy_label(plan.asset_key, row_base["generation"]),
                                 [r for r, _ in items], length)
    measure = _distortion_measure(points, params)
    shared = {**row_base, "n_points": plan.n_points, "fingerprint_length": length,
              "cluster_seeds": [s.seed_index for s in specs],
              "cluster_sizes": [int(len(s.members)) for s in specs],
              "cluster_radii": [c["radius"] for c in cluster_results],
              "cluster_membership_digests": recorded["membership"],
              "cluster_basis_digests": recorded["basis"], "tool_version": __version__}
    chips = fingerprint.signs(bank, length, dtype=np.int8)          # (recipients, length), +-1
    t0 = time.perf_counter()
    copies = _marked_copies(points, centre, phi, specs, chips, params, plan, recorded,
                            Path(items[0][1]).parent if items else Path(plan.store))
    rows = []
    try:
        for (recipient, out), copy in zip(items, copies):
            row, written = _write_pending(cloud, points, copy, Path(out))
            del copy                       # the copy as intended is not needed for the measures
            rows.append({**shared, "recipient": recipient, **row, **measure(written), "status": "ok", "error": None})
            del written
    except BaseException:
        for row in rows:                   # nothing of a failed chunk is left to publish
            Path(row["pending_path"]).unlink(missing_ok=True)
        raise
    for row in rows:       # the bases are read once for all the task's copies: its mean time per copy
        row["seconds_copy"] = (time.perf_counter() - t0) / len(rows)
    return rows


# the marked copies an issue task holds at once; more recipients than fit go through scratch files
MARKED_BYTES = 256 * 2**20
# above this many points a tiled asset's surface measures are pooled over grid cells of this many
POOLED_POINTS = 250_000


def _marked_copies(points, centre, phi, specs, chips, params, plan, recorded, near):
    """Each recipient's marked copy (n, 3), in order, the bases read once and one at a time.

    When the copies fit in :data:`MARKED_BYTES` they are synthesised together
    in memory; otherwise each recipient's displacements go to a scratch file
    cluster by cluster, and the copies are built from them one at a time.
    Clusters are disjoint, so both add each point's displacement once: the
    same bytes.
    """
    count = 3 * params.total_bits * params.chip_rate
    clusters = verified_clusters(points, centre, specs, params, plan.store, plan.store_key, recorded,
                                 source="this run's cluster tasks")

    def moved(spec, basis, normals, x):
        return cluster_fingerprint(basis, normals, x[spec.index * count:(spec.index + 1) * count], phi,
                                   points[spec.members], params, len(specs))

    if len(chips) * points.nbytes <= MARKED_BYTES:
        marked = [points.copy() for _ in chips]
        for spec, _, basis, normals in clusters:
            for copy, x in zip(marked, chips):
                copy[spec.members] += moved(spec, basis, normals, x)
        while marked:
            yield marked.pop(0)
        return
    with Scratch(near) as scratch:
        for spec, _, basis, normals in clusters:
            for j, x in enumerate(chips):
                scratch.append(j, moved(spec, basis, normals, x))
        order = np.concatenate([s.members for s in specs])
        for j in range(len(chips)):
            copy = points.copy()
            copy[order] += scratch.read(j)
            yield copy


def _distortion_measure(points, params):
    """The copy's distortion against its original: exact, or pooled over cells for a large tiled asset."""
    if params.tile_points is None or len(points) <= POOLED_POINTS:
        side = surface_measures.original_side(points)
        return lambda written: distortion(points, written, side=side)
    cells = clustering.grid_cells(points, POOLED_POINTS)
    return lambda written: distortion(points, written, cells=cells)


def _write_pending(cloud, points, marked, out):
    """Write one copy under its pending name and check what the file holds.

    The copy is published (linked to ``out``) by the run once its ledger row
    is durable.

    Returns
    -------
    row : dict (output path, pending path, sha256, realized ratio)
    written : (n, 3) float, the coordinates the file holds
    """
    pending = pending_path(out)
    write_points(cloud, marked, pending)
    try:
        written = read_coordinates(pending)
        ratio = realized_ratio(points, marked, written, out)
    except Exception:
        pending.unlink(missing_ok=True)
        raise
    return {"output_path": str(out), "pending_path": str(pending), "output_sha256": sha256_file(pending),
            "realized_ratio": ratio}, written


def realized_ratio(original, intended, written, out):
    """Share of the intended displacement the written file keeps; refuses unmarked copies."""
    energy = overlap = moved = 0.0
    for a in range(0, len(original), 1 << 20):       # in blocks: no full-size temporaries
        want = intended[a:a + (1 << 20)] - original[a:a + (1 << 20)]
        # motion within a few float64 steps of the coordinates is round-off, not a mark (a 1e-300 cap)
        want[np.abs(want) <= 8 * np.spacing(np.abs(original[a:a + (1 << 20)]).max())] = 0.0
        got = written[a:a + (1 << 20)] - original[a:a + (1 << 20)]
        energy += float((want**2).sum())
        overlap += float((want * got).sum())
        moved += float(np.abs(got).sum())
    ratio = overlap / energy if energy > 0 else 0.0
    if moved == 0 or ratio < MIN_REALIZED:
        raise CopyIntegrityError(
            f"{out}: the copy does not differ measurably from its original (the file keeps "
            f"{100 * max(ratio, 0.0):.1f} % of the displacement at its precision); raise beta "
            f"(or max_displacement, when a cap limits the motion)")
    return ratio
