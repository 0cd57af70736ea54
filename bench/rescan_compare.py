"""Same verdicts before and after a change: a subset of the leak benchmark scanned by two trees.

``python bench/rescan_compare.py issue`` (run from the *old* tree) issues the leak
benchmark into ``bench/results/leaks`` (see ``bench/leaks.py``) and picks the
subset: every attack's leaks in turn up to ``N_LEAKS`` and every kind of negative
in turn up to ``N_NEGATIVES``, copied into ``leaks/compare/suspects``.
``python bench/rescan_compare.py scan NAME [FOLDER]`` scans the subset (or another
folder of ``leaks/compare``) with the tree it runs from into ``leaks/compare/NAME``
(``RESCAN_SCAN_SETS=key=value,...`` sets ``scan`` keys, e.g. the cascade's gates).  ``python bench/rescan_compare.py diff A B``
prints every suspect whose verdict, asset or recipient differs, and the counts.
``python bench/rescan_compare.py tally A [B]`` gives worker seconds per stage (median and 95th
percentile) for leaks and for negatives, and with B the same beside it and how many scores are equal.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

N_LEAKS, N_NEGATIVES = 60, 20
WORK = ROOT / "bench" / "results" / "leaks"


def _round_robin(groups, n):
    out, queues = [], [list(v) for _, v in sorted(groups.items())]
    while len(out) < n and any(queues):
        for q in queues:
            if q and len(out) < n:
                out.append(q.pop(0))
    return out


def issue():
    import leaks

    _, truth, _, t_issue = leaks._issue(WORK)
    by_attack, by_kind = {}, {}
    for name, (kind, _, _, attack) in sorted(truth.items()):
        (by_attack.setdefault(attack, []) if kind == "leak" else by_kind.setdefault(kind, [])).append(name)
    chosen = _round_robin(by_attack, N_LEAKS) + _round_robin(by_kind, N_NEGATIVES)
    folder = WORK / "compare" / "suspects"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for name in chosen:
        shutil.copy2(WORK / "suspects" / f"{name}.ply", folder / f"{name}.ply")
    print(f"issued in {t_issue:.0f} s; {len(chosen)} suspects chosen into {folder}")


def scan(name, subset="suspects"):
    import leaks
    from pipeline.orchestrate.scan import run_scan

    cfg = leaks._config(WORK, WORK / "manifests", WORK / "marked", "bench")
    cfg["dask"]["n_workers"] = int(os.environ.get("RESCAN_WORKERS", "1"))
    for item in filter(None, os.environ.get("RESCAN_SCAN_SETS", "").split(",")):
        key, value = item.split("=")              # e.g. RESCAN_SCAN_SETS=deep_votes=0.05,quick_shape=0.12
        cfg["scan"][key] = None if value == "null" else float(value)
    cfg["scan"]["suspects"], cfg["scan"]["out"] = str(WORK / "compare" / subset), str(WORK / "compare" / name)
    t0 = time.perf_counter()
    status = run_scan(cfg, leaks.SECRET)
    print(f"scanned into {cfg['scan']['out']}: exit status {status}, {time.perf_counter() - t0:.0f} s")


def diff(a, b):
    import leaks

    truth = json.loads((WORK / "truth.json").read_text())
    ra, rb = (leaks._results(WORK / "compare" / x) for x in (a, b))
    keys = ("verdict", "candidate_asset", "recipient")
    differ = [n for n in sorted(ra) if tuple(ra[n].get(k) for k in keys) != tuple(rb.get(n, {}).get(k) for k in keys)]
    right = Counter((truth[n][0] == "leak") and (rb[n]["verdict"], rb[n]["candidate_asset"], rb[n]["recipient"])
                    == ("match", truth[n][1], truth[n][2]) for n in rb)
    print(f"{len(ra)} and {len(rb)} suspects; {len(differ)} differ in verdict, asset or recipient")
    for n in differ:
        print(" ", n, truth[n], [ra[n].get(k) for k in keys], [rb.get(n, {}).get(k) for k in keys])
    print("verdicts", a, dict(Counter(r["verdict"] for r in ra.values())), b, dict(Counter(r["verdict"] for r in rb.values())))
    print("leaks named right in", b, right[True], "of", sum(truth[n][0] == "leak" for n in rb))


STAGES = ("candidates", "quick_registration", "deep_registration", "detection")


def _seconds(row):
    """Worker seconds of one suspect by stage, and in all (candidates + registration + detection)."""
    out = {s: float(row.get(f"seconds_{s}") or 0.0) for s in STAGES}
    out["total"] = sum(float(row.get(f"seconds_{s}") or 0.0) for s in ("candidates", "registration", "detection"))
    return out


def tally(*names):
    import numpy as np
    import leaks

    truth = json.loads((WORK / "truth.json").read_text())
    scans = [leaks._results(WORK / "compare" / x) for x in names]
    for group in ("leak", "negative"):
        rows = [n for n in sorted(scans[0]) if (truth[n][0] == "leak") == (group == "leak")]
        print(f"{group}s ({len(rows)}), worker s median / 95th percentile:")
        for stage in (*STAGES, "total"):
            cells = []
            for scan_ in scans:
                x = np.array([_seconds(scan_[n])[stage] for n in rows if n in scan_])
                cells.append(f"{np.median(x):7.1f} / {np.percentile(x, 95):7.1f}" if len(x) else "-")
            print(f"  {stage:20s}", "   ".join(cells))
    if len(scans) == 2:
        a, b = scans
        both = [n for n in a if n in b]
        equal = sum(np.array_equal([a[n]["score"]], [b[n]["score"]], equal_nan=True) for n in both)
        worst = max((abs(a[n]["score"] - b[n]["score"]) for n in both if a[n]["score"] == a[n]["score"]), default=0.0)
        print(f"{equal} of {len(both)} scores equal in every digit (largest difference {worst:.3g}); "
              f"recipients counted equal in {sum(a[n]['n_checked'] == b[n]['n_checked'] for n in both)}")


if __name__ == "__main__":
    {"issue": issue, "scan": scan, "diff": diff, "tally": tally}[sys.argv[1]](*sys.argv[2:])
