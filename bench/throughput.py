"""Scan throughput (issue 38): a nightly crawl's mix of suspects against catalogues of 100 and 300 assets.

``python bench/run.py scan-throughput`` (hours at full size).  ``THROUGHPUT_ASSETS``
(comma-separated catalogue sizes, default ``100,300``), ``THROUGHPUT_SUSPECTS``
(default 1,000) and ``THROUGHPUT_WORKERS`` (default 2) size it.

Catalogue: the real scans of ``../shared/data/models`` but the Autzen LiDAR tile
and three held out (fandisk, spot, fertility: unrelated real scans), filled up
with procedural shapes (``pipeline.demo``, 6,000 points).  Two recipients per
asset, the default configuration (what a new user runs).  Suspects: 10 % leaks
(a recipient's copy under the leak benchmark's attacks, in turn) and 90 %
innocents, in turn: unrelated real scans (held out, each cropped to 50-100 %),
unrelated procedural shapes (other seeds), unmarked originals and copies issued
under another key, each under a random similarity and shuffled.

The scan runs on a LocalCluster started here and given to ``pointmark scan``
by address, so that the workers' peak resident memory can be read afterwards.
Per catalogue size it writes ``bench/results/throughput/<N>/summary.json`` and
prints worker seconds per stage (candidate search, quick and deep
registration, detection, their sum) as median and 95th percentile for
innocent suspects and for leaks, verdicts against the truth, the share of
suspects the cascade stopped a candidate of, and the workers' peak memory.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("POINTMARK_TEST_DATA", ROOT.parent / "shared" / "data"))
WORK = ROOT / "bench" / "results" / "throughput"
HELD_OUT = ("fandisk_cad_6475", "spot_cow_2930", "fertility_4494")
RECIPIENTS = ["r1", "r2"]
SECRET = b"throughput-benchmark-secret-01234567"
OTHER_SECRET = b"throughput-benchmark-other-key-7654321"
INNOCENTS = ("unrelated real scan", "unrelated shape", "unmarked original", "copy under another key")
STAGES = ("seconds_candidates", "seconds_quick_registration", "seconds_deep_registration", "seconds_detection")


def _peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _config(work, n_workers, address=None, manifests="manifests", out="marked", key_id="bench"):
    from pipeline import config

    sets = [f"catalog.source={work / 'catalog.parquet'}", f"recipients=[{', '.join(RECIPIENTS)}]",
            f"key.id={key_id}", f"output.dir={work / out}", f"output.manifests={work / manifests}",
            f"output.bases={work / 'bases'}", f"scan.suspects={work / 'suspects'}",
            f"scan.catalogue={work / 'catalog.parquet'}", f"scan.manifests={work / 'manifests'}",
            f"scan.out={work / 'scan'}", "dask.progress=none", f"dask.n_workers={n_workers}"]
    if address:
        sets.append(f"dask.address={address}")
    return config.load_config(None, sets)


def build_catalogue(work, n_assets):
    """``n_assets`` assets: the real scans not held out, then procedural shapes; its catalogue file."""
    from leaks import _procedural
    from pipeline.io.catalog import catalogue_record, discover_assets, write_catalogue
    from pipeline.io.pointcloud import write_array

    real = [a for a in discover_assets(DATA / "models", default_recipients=RECIPIENTS)
            if a.key != "lidar_autzen_trim_110000" and a.key not in HELD_OUT][:n_assets]
    assets = work / "assets"
    assets.mkdir(parents=True, exist_ok=True)
    for name, points in _procedural(n_assets - len(real), 0).items():
        if not (assets / f"{name}.ply").exists():
            write_array(assets, name, points, "ply")
    rows = [catalogue_record(a) for a in real + discover_assets(assets, default_recipients=RECIPIENTS)]
    bad = [r for r in rows if r["status"] != "ok"]
    if bad:
        raise SystemExit(f"unusable assets: {[(r['asset_key'], r['error']) for r in bad]}")
    write_catalogue(rows, work / "catalog.parquet")
    return rows


def issue(work, n_workers):
    """Every asset's copies, and one copy of ten assets under another key (a ledger the scan never sees)."""
    from pipeline.orchestrate.progress import Progress
    from pipeline.orchestrate.run import plan_job, run_job

    cfg = _config(work, n_workers)
    job = plan_job(cfg, SECRET)
    run_job(job, cfg, progress=Progress())
    other = _config(work, n_workers, manifests="other-manifests", out="other-marked", key_id="other")
    other["recipients"] = ["x1"]
    other_job = plan_job(other, OTHER_SECRET)
    run_job(other_job, other, progress=Progress())
    ok = [r for r in job.ledger.rows() if r["status"] == "ok"]
    return ok, [r for r in other_job.ledger.rows() if r["status"] == "ok"][::7][:10]


def write_suspects(work, rows, other_rows, n_suspects):
    """10 % leaks and 90 % innocents in turn; returns {name: (kind, asset, recipient, attack)}."""
    from leaks import ATTACKS, _chain, _procedural
    from pipeline import surface
    from pipeline.io.pointcloud import read_points, write_array

    rng = np.random.default_rng(2026)
    folder = work / "suspects"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    copies = sorted(rows, key=lambda r: (r["asset_key"], r["recipient"]))
    originals = sorted({r["asset_key"]: r["source_path"] for r in rows}.items())
    held = [read_points(DATA / "models" / f"{k}.ply").points for k in HELD_OUT]
    n_leaks = max(1, round(0.1 * n_suspects))
    shapes = iter(_procedural(n_suspects // len(INNOCENTS) + 1, 5000).values())
    truth = {}
    for i in range(n_suspects):
        name = f"s{i:04d}"
        similar = [("random_similarity", None), ("shuffle", None)]
        if i % 10 == 0 and i // 10 < n_leaks:                  # leaks spread through the crawl
            k = i // 10
            row = copies[(k * 7919) % len(copies)]
            attack = ATTACKS[k % len(ATTACKS)]
            points = read_points(row["output_path"]).points
            drawn = surface.apply_chain(points, _chain(attack, len(points)), rng)
            truth[name] = ("leak", row["asset_key"], row["recipient"], attack)
        else:
            kind = INNOCENTS[i % len(INNOCENTS)]
            if kind == "unrelated real scan":
                steps = [("crop", float(rng.uniform(0.5, 1.0)))] + similar
                drawn, asset = surface.apply_chain(held[i % len(held)], steps, rng), None
            elif kind == "unrelated shape":
                drawn, asset = surface.apply_chain(next(shapes), similar, rng), None
            elif kind == "unmarked original":
                asset, path = originals[(i * 31) % len(originals)]
                drawn = surface.apply_chain(read_points(path).points, similar, rng)
            else:
                row = other_rows[i % len(other_rows)]
                asset = row["asset_key"]
                drawn = surface.apply_chain(read_points(row["output_path"]).points, similar, rng)
            truth[name] = (kind, asset, None, "random_similarity")
        write_array(folder, name, drawn, "ply")
    (work / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def scan(work, n_workers):
    """``pointmark scan`` of the suspects on a LocalCluster given by address; (wall s, peak MB per worker)."""
    from pipeline.orchestrate.run import start_client
    from pipeline.orchestrate.scan import run_scan

    shutil.rmtree(work / "scan", ignore_errors=True)
    client, cluster = start_client(_config(work, n_workers))
    try:
        t0 = time.perf_counter()
        status = run_scan(_config(work, n_workers, address=cluster.scheduler_address), SECRET)
        wall = time.perf_counter() - t0
        peaks = sorted(client.run(_peak_rss_mb).values())
    finally:
        client.close()
        cluster.close()
    return wall, peaks, status


def _quantiles(values):
    v = np.asarray(values, dtype=np.float64)
    return {"n": int(len(v)), "median": float(np.median(v)) if len(v) else None,
            "p95": float(np.percentile(v, 95)) if len(v) else None}


def summarise(work, truth, wall, peaks, status, n_assets, t_issue):
    from leaks import _results

    results = _results(work / "scan")
    table, verdicts = {}, Counter()
    for group in ("innocent", "leak"):
        names = [n for n, t in truth.items() if (t[0] == "leak") == (group == "leak") and n in results]
        per = {s: [results[n].get(s) or 0.0 for n in names] for s in STAGES}
        per["total"] = [sum(per[s][i] for s in STAGES) for i in range(len(names))]
        table[group] = {s: _quantiles(v) for s, v in per.items()}
        table[group]["cascade_stopped_some"] = sum(bool(results[n].get("n_stopped")) for n in names)
    for name, (kind, asset, recipient, _) in truth.items():
        r = results.get(name)
        if r is None:
            verdicts[f"{kind}: not scanned"] += 1
        elif r["verdict"] == "failed":
            verdicts[f"{kind}: failed"] += 1
        elif kind == "leak":
            right = r["verdict"] == "match" and (r["candidate_asset"], r["recipient"]) == (asset, recipient)
            verdicts["leak: right recipient" if right else f"leak: {r['verdict']}"
                     + (" (wrong)" if r["verdict"] == "match" else "")] += 1
        else:
            verdicts[f"{kind}: {r['verdict']}"] += 1
    summary = {"assets": n_assets, "suspects": len(truth), "workers": len(peaks), "scan_wall_seconds": wall,
               "issue_seconds": t_issue, "exit_status": status, "worker_peak_rss_mb": peaks,
               "stages": table, "verdicts": dict(sorted(verdicts.items()))}
    (work / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def _print(s):
    print(f"\n{s['assets']} assets, {s['suspects']} suspects, {s['workers']} workers: scan wall "
          f"{s['scan_wall_seconds']:.0f} s ({s['scan_wall_seconds'] / max(s['suspects'], 1):.1f} s per suspect), "
          f"issue {s['issue_seconds']:.0f} s, exit status {s['exit_status']}, worker peak RSS "
          f"{', '.join(f'{p:.0f}' for p in s['worker_peak_rss_mb'])} MB")
    print("| suspects | stage | n | median s | 95th percentile s |\n|---|---|---:|---:|---:|")
    for group, stages in s["stages"].items():
        for stage, q in stages.items():
            if isinstance(q, dict) and q["n"]:
                print(f"| {group} | {stage.replace('seconds_', '')} | {q['n']} | {q['median']:.2f} | {q['p95']:.2f} |")
        print(f"| {group} | cascade stopped a candidate | {stages['cascade_stopped_some']} | | |")
    for k, v in s["verdicts"].items():
        print(f"  {k}: {v}")


def throughput_bench():
    sys.path.insert(0, str(ROOT / "bench"))
    n_workers = int(os.environ.get("THROUGHPUT_WORKERS", "2"))
    n_suspects = int(os.environ.get("THROUGHPUT_SUSPECTS", "1000"))
    for n_assets in (int(n) for n in os.environ.get("THROUGHPUT_ASSETS", "100,300").split(",")):
        work = WORK / str(n_assets)
        work.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        build_catalogue(work, n_assets)
        rows, other_rows = issue(work, n_workers)
        t_issue = time.perf_counter() - t0
        truth = write_suspects(work, rows, other_rows, n_suspects)
        wall, peaks, status = scan(work, n_workers)
        _print(summarise(work, truth, wall, peaks, status, n_assets, t_issue))


if __name__ == "__main__":
    for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_v, "1")
    throughput_bench()
