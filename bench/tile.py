"""Large LiDAR tiles (issue 15): embed a generated 1- and 10-million-point LAZ tile, side by side.

``python bench/run.py tile`` (about 45 minutes on 2 cores).  Each tile is
terrain at the same density (10 points per square metre, 1 mm scale,
point format 3 with intensity, returns, classification, GPS time and
colour), watermarked with ``configs/survey.yaml`` and ``tile_points`` on a
Dask LocalCluster of 2 spawned workers, one recipient.  Reported: wall time
per million points and the peak resident memory of each worker.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
WORK = ROOT / "bench" / "results" / "tile"
DENSITY = 10.0            # points per square metre
TILE_POINTS = 64_000      # points per planning cell
CHUNK = 1_000_000         # points generated and written at a time


def terrain_height(x, y):
    """Smooth hills and ridges (metres), a function of position only: any tile size, same relief."""
    return (6.0 * np.sin(x / 47.0) * np.cos(y / 61.0) + 2.5 * np.sin((x + 2 * y) / 23.0)
            + 0.8 * np.cos(x / 7.3) * np.sin(y / 9.1))


def generate_tile(path, n_points, seed=0):
    """Write a LAZ tile of ``n_points`` terrain points, chunk by chunk (bounded memory).

    Parameters
    ----------
    path : Path
    n_points : int
    seed : int
    """
    import laspy

    side = float(np.sqrt(n_points / DENSITY))
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([637_000.0, 851_000.0, 0.0])
    rng = np.random.default_rng(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    pending = path.with_name(f".{path.name}.pending.laz")     # an interrupted run leaves no tile
    with laspy.open(str(pending), mode="w", header=header) as writer:
        for a in range(0, n_points, CHUNK):
            m = min(CHUNK, n_points - a)
            x, y = rng.uniform(0, side, m), rng.uniform(0, side, m)
            record = laspy.ScaleAwarePointRecord.zeros(m, header=header)
            record.x, record.y = header.offsets[0] + x, header.offsets[1] + y
            record.z = 100.0 + terrain_height(x, y) + rng.normal(0, 0.02, m)
            record.intensity = rng.integers(0, 4096, m)
            record.return_number = np.ones(m, np.uint8)
            record.number_of_returns = np.ones(m, np.uint8)
            record.classification = np.full(m, 2, np.uint8)
            record.gps_time = 3.0e5 + a + np.arange(m) * 1e-4
            record.red, record.green, record.blue = (rng.integers(0, 65536, m) for _ in range(3))
            writer.write_points(record)
    pending.replace(path)


def _peak_rss_mb():
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def embed_tile(tile, name, client):
    """One catalogue run on ``tile`` through the given cluster; (seconds, ledger row)."""
    from pipeline import config
    from pipeline.io.ledger import Ledger
    from pipeline.orchestrate.progress import Progress
    from pipeline.orchestrate.run import plan_job, run_job

    out = WORK / name
    shutil.rmtree(out, ignore_errors=True)
    cfg = config.load_config(ROOT / "configs" / "survey.yaml", [
        f"catalog.source={tile}", "recipients=[r1]", f"output.dir={out / 'marked'}",
        f"output.manifests={out / 'ledger'}", "key.id=bench", f"watermark.tile_points={TILE_POINTS}",
        f"dask.address={client.scheduler_info()['address']}", "dask.progress=none"])
    t0 = time.perf_counter()
    job = plan_job(cfg, b"tile-benchmark-secret")
    counts = run_job(job, cfg, progress=Progress())
    seconds = time.perf_counter() - t0
    rows = Ledger(out / "ledger").rows(status=None)
    assert counts["ok"] == 1, (counts, [r["error"] for r in rows])
    return seconds, rows[-1]


def tile_bench(sizes=(1_000_000, 10_000_000)):
    """Embed tiles of the given sizes on one LocalCluster of 2 workers; time per million points, peak memory."""
    import dask
    from distributed import Client, LocalCluster

    from pipeline.orchestrate.run import WORKER_ENV

    tiles = {}
    for n in sizes:
        tiles[n] = WORK / f"tile-{n // 1_000_000}M.laz"
        if not tiles[n].is_file():
            generate_tile(tiles[n], n, seed=n)
    dask.config.set({"distributed.worker.multiprocessing-method": "spawn",
                     "distributed.nanny.pre-spawn-environ": WORKER_ENV,
                     "distributed.worker.profile.enabled": False})
    results = {}
    for n in sizes:          # a fresh cluster per tile: each worker's peak is that tile's
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                          memory_limit="8GiB") as cluster, Client(cluster) as client:
            seconds, row = embed_tile(tiles[n], f"run-{n // 1_000_000}M", client)
            peaks = sorted(client.run(_peak_rss_mb).values())
        results[n] = {"points": n, "seconds": seconds, "seconds_per_million": seconds / (n / 1e6),
                      "worker_peak_rss_mb": peaks, "clusters": len(row["cluster_sizes"]),
                      "mrms_rel_diag": row["mrms_rel_diag"], "realized_ratio": row["realized_ratio"]}
        print(json.dumps(results[n]), flush=True)
    (WORK / "results.json").write_text(json.dumps(results, indent=1))
    base = results[sizes[0]]["seconds_per_million"]
    print(f"large LiDAR tiles (configs/survey.yaml, tile_points {TILE_POINTS:,}, 2 workers, 1 recipient)")
    for n in sizes:
        r = results[n]
        print(f"  {n:>11,} points: {r['seconds']:8.1f} s, {r['seconds_per_million']:7.1f} s per million "
              f"({r['seconds_per_million'] / base:.2f} x the {sizes[0]:,}-point tile's), {r['clusters']} "
              f"clusters, worker peak RSS {', '.join(f'{p:.0f}' for p in r['worker_peak_rss_mb'])} MB")


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    tile_bench(tuple(int(a) for a in sys.argv[1:]) or (1_000_000, 10_000_000))
