"""The exact candidate search of small catalogues (``features.nearest_exact``) against a full partition.

``python bench/exact_search.py chunks``: one chunk of 1,024 suspect descriptors against 20,000
index rows (``features.IVF_MIN``, the most a catalogue searched exactly holds), k = 8, best of 3:
clean rows, one NaN row, every row zero (all similarities equal, the worst case).  The same rows
and similarities as the full partition are asserted for the clean chunk.

``python bench/exact_search.py triage SCAN_FOLDER``: the candidate search (``candidates.triage``,
warm index) of every suspect of a scan's folder (a folder holding ``suspects/`` and
``scan/state/index-*.npz``, such as the world ``tests/test_scan.py`` builds under pytest's
``--basetemp``), seconds each, its first three in both rankings and their votes, as JSON.  Run it
from two trees and compare.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline import threads  # noqa: E402  (one BLAS/OpenMP thread, before NumPy loads)

threads.pin()

import numpy as np  # noqa: E402

from pipeline import features  # noqa: E402


def full_partition(queries, rows, k):
    """The search as it was: ``np.argpartition`` over every row, then the k sorted."""
    sim = queries @ rows.T
    top = np.argpartition(-sim, k - 1, axis=1)[:, :k]
    val = np.take_along_axis(sim, top, axis=1)
    order = np.argsort(-val, axis=1, kind="stable")
    return np.take_along_axis(top, order, axis=1), np.take_along_axis(val, order, axis=1)


def chunks(n_rows=20_000, n_queries=1024, k=8):
    rng = np.random.default_rng(0)
    rows = rng.normal(size=(n_rows, 33)).astype(np.float32)
    rows /= np.linalg.norm(rows, axis=1, keepdims=True)
    cases = {"clean": rows[rng.choice(n_rows, n_queries)] + np.float32(0.01),
             "one NaN row": np.vstack([rows[:n_queries - 1], np.full((1, 33), np.nan, np.float32)]),
             "every row zero": np.zeros((n_queries, 33), np.float32)}
    for name, queries in cases.items():
        times = {"full partition": [], "nearest_exact": []}
        with np.errstate(invalid="ignore"):
            if name == "clean":
                want, got = full_partition(queries, rows, k), features.nearest_exact(queries, rows, k)
                assert np.array_equal(want[0], got[0]) and np.array_equal(want[1], got[1])
            for _ in range(3):
                for label, search in (("full partition", full_partition), ("nearest_exact", features.nearest_exact)):
                    t = time.perf_counter()
                    search(queries, rows, k)
                    times[label].append(time.perf_counter() - t)
        print(f"{name}: " + ", ".join(f"{label} {min(t):.3f} s" for label, t in times.items()))


def triage(folder):
    from pipeline.orchestrate import candidates

    folder = Path(folder)
    index = sorted((folder / "scan" / "state").glob("index-*.npz"))[0]
    out = {}
    for suspect in sorted((folder / "suspects").glob("*.ply")):
        candidates.triage(suspect, {}, index)                  # the index loaded once, as a scan's worker has it
        t = time.perf_counter()
        info = candidates.triage(suspect, {}, index)
        out[suspect.name] = {"seconds": round(time.perf_counter() - t, 2), "index_ranking": info["index_ranking"][:3],
                             "index_votes": [round(v, 6) for v in info["index_votes"][:3]],
                             "ranking": info["ranking"][:3]}
    print(json.dumps(out, indent=1))
    print(f"total {sum(v['seconds'] for v in out.values()):.2f} s", file=sys.stderr)


if __name__ == "__main__":
    {"chunks": chunks, "triage": triage}[sys.argv[1]](*sys.argv[2:])
