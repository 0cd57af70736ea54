"""Task functions of the catalogue graph.  Paths in, small results out.

plan (frame, clusters) -> one task per cluster (spectral basis, normals) ->
issue tasks (one per chunk of recipients: synthesis, write, read-back check).
Every task reads its asset itself and shares references through the basis
store, so adding a recipient later costs a synthesis and a write, and the
memory of an issue task holds one copy at a time whatever the recipients.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..io.pointcloud import InputError, check_distinct, read_points, sha256_file, write_points
from ..kernels import digest, fingerprint
from ..kernels import distortion as surface_measures
from ..watermark import WatermarkError, distortion, fingerprint_displacement, fingerprint_length
from .reference import cluster_reference, load_reference, plan_reference

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
    points = _points(plan.path, plan.source_sha256).points
    spec = plan.clusters[cluster_pos]
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
    ref = load_reference(points, params, plan.store, plan.store_key, recorded, source="this run's cluster tasks")
    length = fingerprint_length(len(ref.specs), params)
    bank = fingerprint.chip_bank(material, copy_label(plan.asset_key, row_base["generation"]),
                                 [r for r, _ in items], length)
    side = surface_measures.original_side(points)
    shared = {**row_base, "n_points": plan.n_points, "fingerprint_length": length,
              "cluster_seeds": [s.seed_index for s in ref.specs],
              "cluster_sizes": [int(len(s.members)) for s in ref.specs],
              "cluster_radii": [c["radius"] for c in cluster_results],
              "cluster_membership_digests": recorded["membership"],
              "cluster_basis_digests": recorded["basis"], "tool_version": __version__}
    rows = []
    for j, (recipient, out) in enumerate(items):
        t0 = time.perf_counter()
        marked = points.copy()
        for spec, moved in zip(ref.specs, fingerprint_displacement(ref, fingerprint.signs(bank[j], length)[0],
                                                                    params, points)):
            marked[spec.members] += moved
        out = Path(out)
        pending = out.with_name(f".{out.stem}.pending{out.suffix}")
        write_points(cloud, marked, pending)      # published only once it is checked
        try:
            written = read_points(pending).points
            ratio = _realized_ratio(points, marked, written, out)
        except Exception:
            pending.unlink(missing_ok=True)
            raise
        os.replace(pending, out)
        rows.append({**shared, "recipient": recipient, "output_path": str(out),
                     "output_sha256": sha256_file(out), "realized_ratio": ratio,
                     **distortion(points, written, side=side),
                     "seconds_copy": time.perf_counter() - t0, "status": "ok", "error": None})
    return rows


def _realized_ratio(original, intended, written, out):
    """Share of the intended displacement the written file keeps; refuses unmarked copies."""
    want = intended - original
    got = written - original
    energy = float((want**2).sum())
    ratio = float((want * got).sum()) / energy if energy > 0 else 0.0
    if not np.any(got) or ratio < MIN_REALIZED:
        raise CopyIntegrityError(
            f"{out}: the copy does not differ measurably from its original (the file keeps "
            f"{100 * max(ratio, 0.0):.1f} % of the displacement at its precision); raise beta "
            f"(or max_displacement, when a cap limits the motion)")
    return ratio
