"""The search screen (:func:`pipeline.features.search_screen`) on the leak benchmark: what it stops (issue 38).

``python bench/coarse_screen.py measure [N_PROCS]`` takes the issued leak
benchmark (``bench/results/leaks``).  Checks: every leak against its own
asset, and every negative against each candidate the scan's cascade may take
deep (triage through the catalogue index a scan of the benchmark built, then
:func:`pipeline.orchestrate.candidates.cascade` at the default gates, without
what :func:`~pipeline.orchestrate.candidates.after_whole` would stop: more
checks than a scan makes).  For each check the quick registration steps run
first (``deep=False``); where they leave it undecided the screen runs, as the
registration would run it before the rotation search (which a scan runs
only where the global step left the part loose: so a leak the screen stops
here may never meet it there).  One JSON line per check goes to
``bench/results/leaks/coarse/measure-<settings>.jsonl`` (resumable).

``python bench/coarse_screen.py summary`` prints the leaks it stops (its
miss rate, at most), its least margin per attack, the innocent checks it
stops, and its seconds.  ``COARSE_SET=rotations=1000,poses=48`` sets the
registration effort it is given; ``COARSE_ONLY=leak-001,unrelated`` measures
only the suspects whose names start so.
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
OUT = WORK / "coarse"
SETTINGS = {"rotations": 1000, "poses": 48, "v": 3}


def _settings():
    out = dict(SETTINGS)
    for part in filter(None, os.environ.get("COARSE_SET", "").split(",")):
        k, v = part.split("=")
        out[k] = int(v)
    return out


def _catalogue():
    import pyarrow.parquet as pq

    rows = [r for r in pq.read_table(WORK / "catalog.parquet").to_pylist() if r["status"] == "ok"]
    return {r["asset_key"]: (Path(r["path"]) if Path(r["path"]).is_absolute() else WORK / r["path"]) for r in rows}


def coarse(suspect, original, spacing, tree, normals, settings):
    """:func:`pipeline.features.search_screen` as a scan runs it: passed, seconds, each pose it refined."""
    from pipeline import features

    t0 = time.perf_counter()
    seen = []
    passed = features.search_screen(suspect, original, spacing=spacing, rotations=settings["rotations"],
                                    poses=settings["poses"], normals=normals, seen=seen)
    return {"passed": passed, "total_s": time.perf_counter() - t0, "seen": seen}


def _one(args):
    name, truth, paths, index_path, settings = args
    import numpy as np

    from pipeline import config, watermark
    from pipeline.io.pointcloud import read_points
    from pipeline.kernels import resampling
    from pipeline.nearest import NearestTree
    from pipeline.orchestrate.candidates import candidates, cascade, triage

    path = WORK / "suspects" / f"{name}.ply"
    kind, asset = truth[0], truth[1]
    suspect = read_points(path).points
    if kind == "leak":
        checks = [asset]
    else:
        info = triage(str(path), {k: None for k in paths}, index_path, twin_shape=0.03)
        picked = candidates(info, set(paths), 5, 1.6)
        stages = cascade(info, picked, 0.03, 0.06, None)
        checks = [a for a in picked if stages[a] == "deep"]
    rows = []
    for a in checks:
        original = read_points(paths[a]).points
        original = original - original.mean(axis=0)
        spacing = float(np.median(resampling.nearest_spacing(original)))
        normals = resampling.estimate_normals(original)
        tree = NearestTree(original)
        row = {"name": name, "kind": kind, "asset": asset, "attack": truth[3], "check": a, "own": a == asset}
        t0 = time.perf_counter()
        try:
            watermark.register(suspect, original, spacing, config.DetectParams(), tree, normals, deep=False)
            row["quick"] = True
        except watermark.Undecided:
            row["quick"] = False
        row["quick_s"] = time.perf_counter() - t0
        if not row["quick"]:
            row.update(coarse(suspect, original, spacing, tree, normals, settings))
        rows.append(row)
    return name, rows


def measure(n_procs="1"):
    import multiprocessing as mp

    OUT.mkdir(parents=True, exist_ok=True)
    truth = json.loads((WORK / "truth.json").read_text())
    paths = _catalogue()
    index_path = next((WORK / "compare").glob("*/state/index-v8-*.npz"))
    settings = _settings()
    tag = "-".join(f"{k}{v}" for k, v in sorted(settings.items()))
    log = OUT / f"measure-{tag}.jsonl"
    done = {json.loads(line)["name"] for line in log.read_text().splitlines()} if log.exists() else set()
    only = os.environ.get("COARSE_ONLY")
    names = sorted(n for n in truth if not only or any(n.startswith(p) for p in only.split(",")))
    # negatives and leaks interleaved, so that a partial run is a fair sample of both
    leaks = [n for n in names if truth[n][0] == "leak"]
    negs = [n for n in names if truth[n][0] != "leak"]
    order = [n for pair in zip(leaks[::2], negs) for n in pair] + leaks[::2][len(negs):] + leaks[1::2] \
        + negs[len(leaks[::2]):]
    todo = [(n, truth[n], paths, index_path, settings) for n in order if n not in done]
    print(f"{len(todo)} suspects to measure into {log}", flush=True)
    with mp.get_context("spawn").Pool(int(n_procs)) as pool, log.open("a") as fh:
        for k, (name, rows) in enumerate(pool.imap_unordered(_one, todo)):
            for row in rows:
                fh.write(json.dumps({**row, "name": name}) + "\n")
            fh.flush()
            deep = [r for r in rows if not r["quick"]]
            print(f"{k + 1}/{len(todo)} {name}: {len(rows)} checks, {len(deep)} coarse, "
                  + ", ".join(f"{r['check']} {r['passed']} {r['total_s']:.1f}s" for r in deep), flush=True)


def summary(tag="poses48-rotations1000-v3"):
    """The screen's decisions: leaks it would stop (its miss rate), innocent checks it stops, its cost."""
    import numpy as np

    from pipeline.features import SCREEN_EXCESS, SCREEN_NEAR

    rows = [json.loads(line) for line in (OUT / f"measure-{tag}.jsonl").read_text().splitlines()]
    leaks = [r for r in rows if r["kind"] == "leak"]
    screened = [r for r in leaks if not r["quick"]]
    innocent = [r for r in rows if r["kind"] != "leak" and not r["quick"] and not r["own"]]
    lost = [(r["name"], r["attack"], r["check"]) for r in screened if not r["passed"]]
    print(f"{len({r['name'] for r in leaks})} leaks measured; {len(screened)} past the quick steps, screened: "
          f"{len(screened) - len(lost)} passed, lost {lost}")
    by_attack = {}
    for r in screened:
        by_attack.setdefault(r["attack"], []).append(r)
    for attack, rs in sorted(by_attack.items()):
        margin = [max(max(n - SCREEN_NEAR, (SCREEN_EXCESS - e) / 4.0) for n, e in r["seen"]) for r in rs if r["seen"]]
        print(f"  {attack}: {len(rs)} screened, {sum(r['passed'] for r in rs)} passed; least margin "
              f"{min(margin):.3f} (near - {SCREEN_NEAR}, or ({SCREEN_EXCESS} - excess) / 4)")
    stopped = [r for r in innocent if not r["passed"]]
    print(f"innocent checks past the quick steps: {len(innocent)} of {len({r['name'] for r in innocent})} "
          f"negatives; stopped {len(stopped)} ({len(stopped) / max(len(innocent), 1):.0%})")
    for group, rs in (("leaks", screened), ("innocent, passed", [r for r in innocent if r["passed"]]),
                      ("innocent, stopped", stopped)):
        if rs:
            t = [r["total_s"] for r in rs]
            print(f"  {group}: {len(rs)} screens, median {np.median(t):.2f} s, p95 {np.percentile(t, 95):.2f} s")
    passed = sorted({r["check"] for r in innocent if r["passed"]})
    print("assets an innocent check passed on:", passed)


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    {"measure": measure, "summary": summary}[sys.argv[1]](*sys.argv[2:])
