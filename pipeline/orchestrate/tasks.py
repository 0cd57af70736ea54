"""Task functions of the catalogue graph.  Paths in, small results out.

plan (frame, clusters) -> one task per cluster (spectral basis, normals) ->
issue tasks (one per chunk of recipients: synthesis, write, read-back check).
Every task reads its asset itself and shares references through the basis
store, so adding a recipient later costs a synthesis and a write.  An issue
task holds one spectral basis at a time and the copies of as many of its
recipients as fit in MARKED_BYTES (one at least), so its memory is bounded
by the asset, not by its clusters or recipients.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..io.pointcloud import InputError, check_distinct, read_points, sha256_file, write_points
from ..io.basis_store import BasisStore
from ..kernels import clustering, digest, fingerprint
from ..kernels import distortion as surface_measures
from ..watermark import WatermarkError, cluster_fingerprint, distortion, fingerprint_length
from .reference import cluster_reference, plan_reference, verified_clusters

__all__ = ["AssetPlan", "plan_asset", "cluster_task", "issue_task", "CopyIntegrityError", "copy_label"]

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
    cloud = read_points(path)
    if source_sha256 and sha256_file(path) != source_sha256:
        raise InputError(f"{path}: the file changed while the run was planned (sha256 differs)")
    return cloud


def plan_asset(asset_key, path, source_sha256, params, store, store_key):
    """Load an asset and grow its clusters (or take them from the store)."""
    t0 = time.perf_counter()
    points = _points(path, source_sha256).points
    check_distinct(path, points)          # repeated points: a failed row, as in `pointmark embed`
    try:
        centre, phi, specs = plan_reference(points, params, store, store_key)
    except WatermarkError as exc:
        raise InputError(f"{path}: {exc}") from None
    return AssetPlan(asset_key, str(path), source_sha256, len(points), centre, phi, specs, str(store),
                     store_key, time.perf_counter() - t0)


def cluster_task(plan, cluster_pos, params):
    """Spectral basis (and normals) of one cluster, saved to the store; its digests.

    Returns
    -------
    dict with radius, membership, basis (digests) and seconds
    """
    t0 = time.perf_counter()
    spec = plan.clusters[cluster_pos]
    points = None       # a tiled asset's plan stored each cluster's points: no whole read per cluster
    if params.tile_points is None or not BasisStore(plan.store).has(plan.store_key, f"points-{spec.index}"):
        points = _points(plan.path, plan.source_sha256).points
    radius, basis, _ = cluster_reference(points, plan.centre, spec, params, plan.store, plan.store_key)
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
    centre, phi, specs = plan_reference(points, params, plan.store, plan.store_key)
    length = fingerprint_length(len(specs), params)
    bank = fingerprint.chip_bank(material, copy_label(plan.asset_key, row_base["generation"]),
                                 [r for r, _ in items], length)
    measure = _distortion_measure(points)
    shared = {**row_base, "n_points": plan.n_points, "fingerprint_length": length,
              "cluster_seeds": [s.seed_index for s in specs],
              "cluster_sizes": [int(len(s.members)) for s in specs],
              "cluster_radii": [c["radius"] for c in cluster_results],
              "cluster_membership_digests": recorded["membership"],
              "cluster_basis_digests": recorded["basis"], "tool_version": __version__}
    rows = []
    per_group = max(1, MARKED_BYTES // max(points.nbytes, 1))
    for a in range(0, len(items), per_group):
        group = list(enumerate(items))[a:a + per_group]
        t0 = time.perf_counter()
        marked = _marked_copies(points, centre, phi, specs, [bank[j] for j, _ in group], length, params,
                                plan, recorded)
        seconds = (time.perf_counter() - t0) / len(group)
        while group:
            (_, (recipient, out)), copy = group.pop(0), marked.pop(0)
            t0 = time.perf_counter()
            rows.append({**shared, "recipient": recipient, **_publish(cloud, points, copy, Path(out), measure),
                         "seconds_copy": seconds + time.perf_counter() - t0, "status": "ok", "error": None})
            del copy
    return rows


# the marked copies an issue task holds at once: as many as fit, at least one
MARKED_BYTES = 256 * 2**20
# above this many points the copy's surface measures are pooled over grid cells of this many
POOLED_POINTS = 1_000_000


def _marked_copies(points, centre, phi, specs, banks, length, params, plan, recorded):
    """The recipients' copies, synthesised cluster by cluster with one basis in memory at a time."""
    chips = [fingerprint.signs(b, length)[0] for b in banks]
    marked = [points.copy() for _ in banks]
    count = 3 * params.total_bits * params.chip_rate
    for spec, _, basis, normals in verified_clusters(points, centre, specs, params, plan.store, plan.store_key,
                                                    recorded, source="this run's cluster tasks"):
        local = points[spec.members]
        for copy, x in zip(marked, chips):
            copy[spec.members] += cluster_fingerprint(basis, normals, x[spec.index * count:(spec.index + 1) * count],
                                                      phi, local, params)
    return marked


def _distortion_measure(points):
    """The copy's distortion against its original: exact, or pooled over cells on large scenes."""
    if len(points) <= POOLED_POINTS:
        side = surface_measures.original_side(points)
        return lambda written: distortion(points, written, side=side)
    cells = clustering.grid_cells(points, POOLED_POINTS)
    return lambda written: distortion(points, written, cells=cells)


def _publish(cloud, points, marked, out, measure):
    """Write one copy under a pending name, check what the file holds, then rename it into place."""
    pending = out.with_name(f".{out.stem}.pending{out.suffix}")
    write_points(cloud, marked, pending)      # published only once it is checked
    try:
        written = read_points(pending).points
        ratio = _realized_ratio(points, marked, written, out)
    except Exception:
        pending.unlink(missing_ok=True)
        raise
    os.replace(pending, out)
    return {"output_path": str(out), "output_sha256": sha256_file(out), "realized_ratio": ratio,
            **measure(written)}


def _realized_ratio(original, intended, written, out):
    """Share of the intended displacement the written file keeps; refuses unmarked copies."""
    energy = overlap = moved = 0.0
    for a in range(0, len(original), 1 << 20):       # in blocks: no full-size temporaries
        want = intended[a:a + (1 << 20)] - original[a:a + (1 << 20)]
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
