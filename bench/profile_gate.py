"""Calibrate ``revolution.PROFILE_CUT`` on the leak benchmark: each candidate axis's first profile match.

For every leak of an asset with a near-symmetry axis (issue the benchmark first: ``python
bench/run.py leaks`` or ``python bench/rescan_compare.py issue``), the median distance, in the
original's spacings, of the leak's profile about each of its two candidate axes to its asset's
profile at the best scale and height (:func:`revolution.match_profile`): what the revolution step
sees before it turns.  ``neg I K``: every K-th negative from the I-th, against every such asset.

``python bench/profile_gate.py leaks``; ``python bench/profile_gate.py neg 0 3``; rows go to
``bench/results/profile_gate-*.jsonl`` (null: an axis the part does not fix; inf: no scale and
height lay its profile inside the original's).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
WORK = ROOT / "bench" / "results" / "leaks"

from pipeline import threads  # noqa: E402  (one BLAS/OpenMP thread, before NumPy loads)

threads.pin()

import numpy as np  # noqa: E402

from pipeline import features  # noqa: E402
from pipeline.io.pointcloud import read_points  # noqa: E402
from pipeline.kernels import registration, resampling, revolution  # noqa: E402
from pipeline.nearest import NearestTree  # noqa: E402


def symmetric_assets():
    """{asset key: (spacing, (m, 2) profile about its axis, tree over it)} of the assets with a near-symmetry axis."""
    import pyarrow.parquet as pq

    out = {}
    for row in pq.read_table(WORK / "catalog.parquet").to_pylist():
        points = read_points(WORK / row["path"]).points
        if registration.symmetry_axes(points):
            anchor, direction, _ = revolution.revolution_axis(points, resampling.estimate_normals(points))
            whole = revolution.profile(points, anchor, direction)
            out[row["asset_key"]] = (float(np.median(resampling.nearest_spacing(points))), whole, NearestTree(whole))
    return out


def axis_costs(part, asset, most=1500):
    """Best profile match of ``part`` about each of its candidate axes, in the asset's spacings (as revolution_poses takes them)."""
    spacing, whole, tree = asset
    hint = features.scale_hint(features.dense_part(part), spacing)
    if hint is None:
        return []
    step = max(1, len(part) // most)
    sub, normals = part[::step], resampling.estimate_normals(part)[::step]
    out = []
    for anchor, direction, cost in revolution.revolution_axes(sub, normals, count=2):
        if not np.isfinite(cost):
            out.append(None)
            continue
        found = revolution.match_profile(revolution.profile(sub, anchor, direction), whole, hint, spacing,
                                         whole_tree=tree)
        out.append(found[0][0] / spacing if found else float("inf"))
    return out


def main(mode, first="0", every="1"):
    truth = json.loads((WORK / "truth.json").read_text())
    assets = symmetric_assets()
    print("assets with a near-symmetry axis:", sorted(assets), flush=True)
    if mode == "leaks":
        names = sorted(n for n, v in truth.items() if v[0] == "leak" and v[1] in assets)
    else:
        names = sorted(n for n, v in truth.items() if v[0] != "leak")[int(first)::int(every)]
    with open(WORK.parent / f"profile_gate-{mode}{first if mode != 'leaks' else ''}.jsonl", "w") as out:
        for name in names:
            part = read_points(WORK / "suspects" / f"{name}.ply").points
            for key in ([truth[name][1]] if mode == "leaks" else sorted(assets)):
                out.write(json.dumps(dict(name=name, truth=truth[name], asset=key,
                                          costs=axis_costs(part, assets[key]))) + "\n")
                out.flush()


if __name__ == "__main__":
    main(*sys.argv[1:])
