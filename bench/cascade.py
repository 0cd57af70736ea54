"""Calibrating the scan's cascade on the leak benchmark (issue 38).

``python bench/cascade.py measure [N_PROCS]`` runs the scan's cheap stages on
every suspect of the issued leak benchmark (``bench/results/leaks``, see
``bench/leaks.py``): on each leak, the quick registration steps
(:func:`pipeline.watermark.register` with ``deep=False``) against its own
asset; where they leave it undecided, and on every negative, the triage
(descriptor votes over the catalogue index, the candidates).  One JSON line
per suspect goes to ``bench/results/leaks/cascade/measure.jsonl`` (resumable).

``python bench/cascade.py summary [DEEP_VOTES DEEP_SHAPE QUICK_SHAPE]`` prints
the leaks whose asset the quick steps settle, per attack; for the rest, the vote
share of their asset; the shape distances of every leak's asset; and at the
three gates (:func:`pipeline.orchestrate.candidates.cascade`), the leaks they
would lose (the miss rate they add: a settled leak's votes are not measured, so
it counts as passing only by its shape) and the candidates an innocent suspect
still registers, and may take deep.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

ROOT = Path(__file__).resolve().parents[1]
WORK = ROOT / "bench" / "results" / "leaks"
OUT = WORK / "cascade"


def _catalogue():
    import pyarrow.parquet as pq

    rows = [r for r in pq.read_table(WORK / "catalog.parquet").to_pylist() if r["status"] == "ok"]
    base = WORK
    return {r["asset_key"]: (Path(r["path"]) if Path(r["path"]).is_absolute() else base / r["path"]) for r in rows}


def _index(paths):
    from pipeline.orchestrate.candidates import build_index

    return build_index(OUT, "bench", {k: str(v) for k, v in paths.items()})


def _quick(suspect, original_path):
    """(decided, seconds) of the quick registration steps of ``suspect`` on one original."""
    import numpy as np
    from scipy.spatial import cKDTree

    from pipeline import config, watermark
    from pipeline.io.pointcloud import read_points
    from pipeline.kernels import resampling

    original = read_points(original_path).points
    t0 = time.perf_counter()
    spacing = float(np.median(resampling.nearest_spacing(original)))
    normals = resampling.estimate_normals(original)
    try:
        watermark.register(suspect, original, spacing, config.DetectParams(), cKDTree(original), normals,
                           deep=False)
        decided = True
    except watermark.Undecided:
        decided = False
    return decided, time.perf_counter() - t0


def _one(args):
    """One suspect's cheap stages: the quick steps on a leak's own asset, the triage where they leave it open."""
    name, truth, paths, index_path = args
    from pipeline.io.pointcloud import read_points
    from pipeline.orchestrate.candidates import candidates, load_index, triage

    path = WORK / "suspects" / f"{name}.ply"
    kind, asset = truth[0], truth[1]
    row = {"name": name, "kind": kind, "asset": asset, "attack": truth[3], "quick": {}}
    if kind == "leak":
        points = read_points(path).points
        row["quick"][asset] = _quick(points, paths[asset])
        if row["quick"][asset][0]:          # settled without the gate: its shape distances only
            t0 = time.perf_counter()
            index = load_index(index_path)
            row["shape"] = dict(zip(index.keys, map(float, index.shape_distances(points))))
            row["seconds_shape"] = time.perf_counter() - t0
            return row
    info = triage(str(path), {k: None for k in paths}, index_path)
    return {**row, "seconds_triage": info["seconds"], "candidates": candidates(info, set(paths), 5, 1.6),
            "votes": dict(zip(info["index_ranking"], info["index_votes"])),
            "shape": dict(zip(info["ranking"], info["distances"]))}


def measure(n_procs="1"):
    import multiprocessing as mp

    OUT.mkdir(parents=True, exist_ok=True)
    truth = json.loads((WORK / "truth.json").read_text())
    paths = _catalogue()
    index_path = _index(paths)
    log = OUT / "measure.jsonl"
    done = {json.loads(line)["name"] for line in log.read_text().splitlines()} if log.exists() else set()
    # leaks and negatives interleaved, so that a partial run is a fair sample of both
    leaks = sorted(n for n in truth if truth[n][0] == "leak")
    negs = sorted(n for n in truth if truth[n][0] != "leak")
    order, step = [], max(1, len(leaks) // max(len(negs), 1))
    for i, n in enumerate(negs):
        order += leaks[i * step:(i + 1) * step] + [n]
    order += leaks[len(negs) * step:]
    todo = [(n, truth[n], paths, index_path) for n in order if n not in done]
    if os.environ.get("CASCADE_REVERSE") == "1":        # a second process from the other end
        todo.reverse()
    if os.environ.get("CASCADE_LEAKS_ONLY") == "1":     # what the gates' miss rate needs, first
        todo = [t for t in todo if t[1][0] == "leak"]
    with mp.get_context("spawn").Pool(int(n_procs)) as pool, log.open("a") as fh:
        for k, row in enumerate(pool.imap(_one, todo)):
            fh.write(json.dumps(row) + "\n")
            fh.flush()
            print(f"{k + 1}/{len(todo)} {row['name']} {row['kind']}: triage {row.get('seconds_triage', 0):.1f} s, "
                  f"quick {sum(s for _, s in row['quick'].values()):.1f} s", flush=True)


def summary(*gates):
    """The gates' miss rate on the leaks and the checks they leave an innocent, at ``gates``."""
    import numpy as np

    rows = list({r["name"]: r for r in map(json.loads, (OUT / "measure.jsonl").read_text().splitlines())}.values())
    leaks = [r for r in rows if r["kind"] == "leak"]
    negs = [r for r in rows if r["kind"] != "leak"]
    undecided = [r for r in leaks if not r["quick"][r["asset"]][0]]
    print(f"{len(leaks)} leaks, {len(negs)} negatives measured; the quick steps settle {len(leaks) - len(undecided)} "
          f"leaks, leave {len(undecided)} to the gate")
    by_attack = {}
    for r in leaks:
        by_attack.setdefault(r["attack"], [0, 0])[r in undecided] += 1
    for attack, (settled, left) in sorted(by_attack.items()):
        print(f"  {attack}: {settled} settled, {left} to the gate")
    gated = sorted((r["votes"].get(r["asset"], float("inf")), r["name"], r["attack"]) for r in undecided)
    print("vote shares of their assets, lowest first:", [(round(v, 4), n, a) for v, n, a in gated[:15]])
    far = sorted(((r["shape"].get(r["asset"], 0.0), r["name"], r["attack"]) for r in leaks), reverse=True)
    print("shape distances of the leaks' assets, farthest first:", [(round(d, 4), n, a) for d, n, a in far[:12]])
    not_cand = [r["name"] for r in undecided if r["asset"] not in r["candidates"]]
    print("of them, the asset not a candidate:", not_cand)
    top = sorted(((max((r["votes"].get(a, 0.0) for a in r["candidates"]), default=0.0), r["name"]) for r in negs),
                 reverse=True)
    print("negatives' highest candidate vote share, highest first:", [(round(v, 4), n) for v, n in top[:15]])
    for group, rs in (("leaks", leaks), ("negatives", negs)):
        quick = [s for r in rs for _, s in r["quick"].values()]
        tri = [r["seconds_triage"] for r in rs if "seconds_triage" in r]
        if quick:
            print(f"{group}: quick steps on the asset median {np.median(quick):.1f} s, p95 {np.percentile(quick, 95):.1f} s")
        if tri:
            print(f"{group}: triage median {np.median(tri):.1f} s, p95 {np.percentile(tri, 95):.1f} s")
    if gates:
        gates = tuple(map(float, gates))
        lost = [(r["name"], r["attack"]) for r in leaks if _stage(r, r["asset"], gates) is None
                or (r in undecided and _stage(r, r["asset"], gates) != "deep")]
        stages = [[_stage(r, a, gates) for a in r["candidates"]] for r in negs]
        quick = [sum(s is not None for s in st) for st in stages]
        deep = [sum(s == "deep" for s in st) for st in stages]
        print(f"deep_votes, deep_shape, quick_shape {gates}: leaks lost {len(lost)} of {len(leaks)} {lost}; per "
              f"negative, candidates registered median {np.median(quick):.0f} (most {max(quick)}), of them "
              f"allowed deep median {np.median(deep):.0f} (p95 {np.percentile(deep, 95):.0f}, most {max(deep)}), "
              f"of {np.median([len(r['candidates']) for r in negs]):.0f} candidates")


def _stage(row, asset, gates):
    from pipeline.orchestrate.candidates import cascade

    votes, shape = row.get("votes", {}), row.get("shape", {})
    info = {"index_ranking": list(votes), "index_votes": list(votes.values()),
            "ranking": list(shape), "distances": list(shape.values())}
    if asset not in votes:            # a leak the quick steps settled: its votes were not measured
        info["index_ranking"].append(asset)
        info["index_votes"].append(float("-inf"))
    return cascade(info, [asset], *gates)[asset]


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    {"measure": measure, "summary": summary}[sys.argv[1]](*sys.argv[2:])
