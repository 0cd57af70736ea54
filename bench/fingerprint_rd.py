"""One report from several runs of ``configs/evaluate-fingerprint-rd.yaml`` (issue 39).

``python bench/fingerprint_rd.py OUT [MORE ...]`` reads each folder's
``results.parquet`` and ``fingerprints.parquet`` (the message rows give the
paper's distance per model; each model's paper-distance row is kept once) and
writes the evaluation report of all of them into ``OUT/combined``: summary.md
and ``fingerprint_rate_distortion_<model>.png``.  The sweep ran in two parts
(three models at three betas, then two more betas on the owl with
``--only``), each a plain ``pointmark evaluate``.
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline import threads  # noqa: E402  (one BLAS/OpenMP thread, before NumPy loads)

threads.pin()

import pyarrow.parquet as pq  # noqa: E402


def main(folders):
    from pipeline.report import write_report

    rows, fingerprints, seen = [], [], set()
    for folder in map(Path, folders):
        for r in pq.read_table(folder / "results.parquet").to_pylist():
            if (r["experiment"], r["model"], r["beta"], r["seed"]) not in seen:
                seen.add((r["experiment"], r["model"], r["beta"], r["seed"]))
                rows.append(r)
        fingerprints += pq.read_table(folder / "fingerprints.parquet").to_pylist()
    out = Path(folders[0]) / "combined"
    out.mkdir(exist_ok=True)
    print(write_report(out, rows, [], 1e-6, 0.0, fingerprints))


if __name__ == "__main__":
    main(sys.argv[1:])
