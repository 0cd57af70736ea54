"""Task functions of the catalogue graph.  Paths in, small results out.

Each task reads its asset itself (workers load their own data); the tasks
call the same engine functions as the command line, so a Dask run and a
serial loop write the same bytes.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .. import __version__
from ..io.pointcloud import InputError, read_points, sha256_file, write_points
from ..watermark import (WatermarkError, cluster_basis, cluster_normals, distortion, frame_of,
                         modulate_cluster, payload_bits, plan_clusters)
from ..kernels import modulation

__all__ = ["AssetPlan", "plan_asset", "embed_cluster_task", "assemble_asset"]


@dataclass(frozen=True)
class AssetPlan:
    """What the plan task learns about an asset: its frame and clusters."""

    path: str
    n_points: int
    centre: np.ndarray
    phi: float
    clusters: list          # ClusterSpec
    seconds: float


def _load(path):
    cloud = read_points(path)
    return cloud, cloud.points


def plan_asset(path, params):
    """Load an asset and grow its clusters."""
    t0 = time.perf_counter()
    _, points = _load(path)
    try:
        frame = frame_of(points)
        specs = plan_clusters(points - frame.centre, params)
    except WatermarkError as exc:
        raise InputError(f"{path}: {exc}") from None
    return AssetPlan(str(path), len(points), frame.centre, frame.phi, specs,
                     time.perf_counter() - t0)


def embed_cluster_task(plan, cluster_pos, material, payloads, params):
    """Spectral basis of one cluster, modulated once per recipient payload.

    Returns
    -------
    radius : float
    displacements : (n_recipients, n_c, 3) float
    seconds : float
    """
    t0 = time.perf_counter()
    _, points = _load(plan.path)
    spec = plan.clusters[cluster_pos]
    centred = points - plan.centre
    radius, basis = cluster_basis(centred[spec.members], params)
    normals = cluster_normals(centred, spec.members, params)
    amplitude = params.beta * plan.phi
    disps = np.stack([
        modulate_cluster(basis, spec.index, material,
                         payload_bits(modulation.hex_to_bits(p, params.n_bits), params), amplitude, params,
                         normals)
        for p in payloads
    ])
    return radius, disps, time.perf_counter() - t0


def assemble_asset(plan, cluster_results, outputs, row_base):
    """Apply every recipient's displacements and write the outputs atomically.

    Parameters
    ----------
    plan : AssetPlan
    cluster_results : list of (radius, displacements, seconds)
    outputs : list of (recipient, payload, output_path)
    row_base : dict
        Manifest columns shared by the rows.

    Returns
    -------
    list of dict
        One manifest row per recipient.
    """
    t0 = time.perf_counter()
    cloud, points = _load(plan.path)
    centred = points - plan.centre
    rows = []
    for r, (recipient, payload, out) in enumerate(outputs):
        moved = centred.copy()
        for spec, (_, disps, _) in zip(plan.clusters, cluster_results):
            moved[spec.members] += disps[r]
        marked = moved + plan.centre
        write_points(cloud, marked, out)
        dist = distortion(points, marked)
        rows.append({
            **row_base,
            "output_path": str(out),
            "output_sha256": sha256_file(out),
            "recipient": recipient,
            "payload": payload,
            "n_points": plan.n_points,
            "cluster_seeds": [s.seed_index for s in plan.clusters],
            "cluster_sizes": [int(len(s.members)) for s in plan.clusters],
            "cluster_radii": [float(res[0]) for res in cluster_results],
            **dist,
            "seconds_plan": plan.seconds,
            "seconds_clusters": float(sum(res[2] for res in cluster_results)),
            "status": "ok",
            "error": None,
            "tool_version": __version__,
        })
    seconds = time.perf_counter() - t0
    for row in rows:
        row["seconds_write"] = seconds
    return rows
