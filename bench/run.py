"""pointmark benchmarks: ``make bench`` (or ``python bench/run.py [spectral] [catalog] [scan] [fingerprint] [issue] [leaks]``).

Every figure is a ratio of two timings taken side by side in this one run,
since shared machines are noisy; each timing is the best of a few repeats.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def best_of(func, repeat=3):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        func()
        times.append(time.perf_counter() - t0)
    return min(times)


def spectral_bench():
    """Spectral basis (sparse shift-invert Lanczos) against dense numpy.linalg.eigh."""
    from pipeline.demo import procedural_shape
    from pipeline.kernels import graph
    from pipeline.kernels.spectral import spectral_basis

    points = procedural_shape("blob", 4000, seed=1)
    radius = graph.valence_radius(points, 12)
    adjacency, _ = graph.connect_components(points, graph.radius_graph(points, radius))
    k = graph.laplacian(adjacency)
    dense = k.toarray()
    t_sparse = best_of(lambda: spectral_basis(k, 320))
    t_dense = best_of(lambda: np.linalg.eigh(dense), repeat=2)
    print("spectral basis, n = 4,000, 320 vectors (N_n = 12)")
    print(f"  pointmark spectral_basis : {t_sparse:8.2f} s")
    print(f"  numpy.linalg.eigh (dense): {t_dense:8.2f} s")
    print(f"  speed-up                 : {t_dense / t_sparse:8.1f} x")


def catalog_bench(n_assets=8, n_points=35000):
    """Catalogue job: plain serial loop vs Dask with 1 and 2 workers, same assets."""
    import shutil

    from pipeline import config
    from pipeline.demo import procedural_shape
    from pipeline.io.pointcloud import write_array
    from pipeline.orchestrate.progress import Progress
    from pipeline.orchestrate.run import plan_job, run_job

    work = ROOT / "bench" / "results" / "catalog"
    kinds = ["blob", "torus", "shell", "terrain"]
    for i in range(n_assets):
        write_array(work / "assets", f"asset-{i}", procedural_shape(kinds[i % 4], n_points, seed=i) * 50, "ply")
    secret = b"benchmark-secret"

    def run(name, serial=False, workers=1):
        shutil.rmtree(work / name, ignore_errors=True)
        cfg = config.load_config(None, [f"catalog.source={work / 'assets'}", "recipients=[r1, r2]",
                                        f"output.dir={work / name / 'marked'}", "key.id=bench",
                                        f"output.manifests={work / name / 'manifests'}",
                                        f"dask.n_workers={workers}", "dask.progress=none"])
        job = plan_job(cfg, secret)
        t0 = time.perf_counter()
        counts = run_job(job, cfg, serial=serial, progress=Progress())
        assert counts["ok"] == n_assets, counts
        return time.perf_counter() - t0

    # interleaved repeats, best of each, so drifts of a shared machine hit all three alike
    t_serial = t_one = t_two = float("inf")
    for _ in range(2):
        t_serial = min(t_serial, run("serial", serial=True))
        t_one = min(t_one, run("dask1", workers=1))
        t_two = min(t_two, run("dask2", workers=2))
    print(f"catalogue job, {n_assets} assets x {n_points:,} points, 2 recipients, 5 clusters of 4,000 "
          f"(best of 2, interleaved; Dask times include starting and closing the LocalCluster)")
    print(f"  serial loop (1 process)  : {t_serial:8.1f} s")
    print(f"  Dask LocalCluster, 1 wkr : {t_one:8.1f} s   ({100 * (t_one / t_serial - 1):+.1f} % vs serial)")
    print(f"  Dask LocalCluster, 2 wkrs: {t_two:8.1f} s   (speed-up {t_one / t_two:.2f} x over 1 worker)")


def scan_bench(n_assets=50, n_suspects=100, n_points=5000):
    """Leak scan: 100 attacked suspects against a 50-asset catalogue; time per suspect and its shares."""
    import shutil

    from pipeline import config
    from pipeline.demo import SHAPES, procedural_shape
    from pipeline.io.catalog import catalogue_record, discover_assets, write_catalogue
    from pipeline.io.pointcloud import read_points, write_array
    from pipeline.kernels import attacks
    from pipeline.orchestrate.progress import Progress
    from pipeline.orchestrate.run import plan_job, run_job
    from pipeline.orchestrate.scan import read_scan, run_scan

    work = ROOT / "bench" / "results" / "scan"
    shutil.rmtree(work / "scan", ignore_errors=True)
    kinds = sorted(SHAPES)
    for i in range(n_assets):
        write_array(work / "assets", f"asset-{i:02d}", procedural_shape(kinds[i % 4], n_points, seed=i) * 20, "ply")
    rows = [catalogue_record(a) for a in discover_assets(work / "assets", default_recipients=["r1", "r2"])]
    write_catalogue(rows, work / "catalog.parquet")
    cfg = config.load_config(None, [
        f"catalog.source={work / 'catalog.parquet'}", "recipients=[r1, r2]", "key.id=bench",
        f"output.dir={work / 'marked'}", f"output.manifests={work / 'manifests'}",
        "n_clusters=2", "cluster_size=2000", f"scan.suspects={work / 'suspects'}",
        f"scan.catalogue={work / 'catalog.parquet'}", f"scan.out={work / 'scan'}", "dask.progress=none"])
    secret = b"benchmark-secret"
    run_job(plan_job(cfg, secret), cfg, progress=Progress())
    rng = np.random.default_rng(0)
    chains = [[("random_similarity", None)], [("noise", 0.005)], [("removal", 0.5)], [("crop", 0.7)]]
    for k in range(n_suspects):
        src = work / "marked" / f"r{1 + k % 2}" / f"asset-{k % n_assets:02d}.ply"
        pts = attacks.apply_chain(read_points(src).points, chains[k % 4] + [("shuffle", None)], rng)
        write_array(work / "suspects", f"suspect-{k:03d}", pts, "ply")
    t0 = time.perf_counter()
    run_scan(cfg, secret)
    wall = time.perf_counter() - t0
    found = read_scan(work / "scan")
    best = found
    right = sum(r["verdict"] == "match" and r["candidate_asset"] == f"asset-{int(Path(r['suspect_path']).stem[-3:]) % n_assets:02d}"
                for r in best)
    cand = sum(r["seconds_candidates"] or 0 for r in best)
    reg = sum(r["seconds_registration"] or 0 for r in found)
    det = sum(r["seconds_detection"] or 0 for r in found)
    total = cand + reg + det
    print(f"leak scan, {n_suspects} suspects (similarity, noise 0.5 %, removal 50 %, crop 70 %) "
          f"against {n_assets} assets x 2 recipients, top-3 candidates, 2 workers")
    print(f"  wall time               : {wall:8.1f} s  ({wall / n_suspects:.2f} s per suspect)")
    print(f"  attributed correctly    : {right}/{n_suspects}")
    print(f"  worker time per suspect : {total / n_suspects:8.2f} s: candidate search {100 * cand / total:.1f} %, "
          f"registration {100 * reg / total:.1f} %, detection {100 * det / total:.1f} %")


def fingerprint_bench():
    """Scoring every issued recipient of one asset: 1,000 / 10,000 / 100,000 recipients."""
    from pipeline.kernels import fingerprint

    length = 5 * 3 * 320          # the default embedding: 5 clusters x 3 axes x 320 coefficients
    y = np.random.default_rng(0).normal(size=length)
    material = b"bench-material-0123456789abcdef!"
    print(f"fingerprint scoring, {length} chips per recipient, one suspect")
    for n in (1000, 10000, 100000):
        names = [f"recipient-{i:06d}" for i in range(n)]
        t_bank = best_of(lambda: fingerprint.chip_bank(material, "asset/g1", names, length), repeat=2)
        bank = fingerprint.chip_bank(material, "asset/g1", names, length)
        t_score = best_of(lambda: fingerprint.scores(y, bank))
        print(f"  {n:>7,} recipients: derive fingerprints {t_bank:6.3f} s, score {t_score:6.3f} s, "
              f"together {t_bank + t_score:6.3f} s ({1e6 * (t_bank + t_score) / n:.1f} us per recipient)")


def _issue_run(work, recipients):
    """One serial catalogue run in a child process; (seconds, peak RSS in MB)."""
    import json
    import subprocess

    code = f"""
import json, resource, sys, time
sys.path.insert(0, {str(ROOT)!r})
from pipeline import config
from pipeline.orchestrate.progress import Progress
from pipeline.orchestrate.run import plan_job, run_job
cfg = config.load_config({str(work / 'issue.yaml')!r}, ["recipients=" + json.dumps({recipients!r})])
t0 = time.perf_counter()
job = plan_job(cfg, b"bench-secret-0123456789")
counts = run_job(job, cfg, serial=True, progress=Progress())
assert counts["failed"] == 0, counts
print(json.dumps([time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024]))
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def issue_bench(n_copies=1000):
    """Issuing copies of the bunny: the first copy, then each further one (bases from the store)."""
    import shutil

    import yaml

    bunny = ROOT.parent / "shared" / "data" / "models" / "bunny_zipper_faceref_34834.ply"
    work = ROOT / "bench" / "results" / "issue"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    cfg = yaml.safe_load((ROOT / "configs" / "default.yaml").read_text())
    cfg.update({"catalog": {"source": str(bunny)}, "key": {"id": "bench"},
                "output": {"dir": str(work / "marked"), "manifests": str(work / "ledger")}})
    (work / "issue.yaml").write_text(yaml.safe_dump(cfg))
    names = [f"recipient-{i:04d}" for i in range(n_copies)]
    first, rss_first = _issue_run(work, names[:1])
    ten, rss_ten = _issue_run(work, names[:11])
    rest, rss_rest = _issue_run(work, names)
    per_copy = rest / (n_copies - 11)
    print("issuing copies of the bunny (34,834 points, configs/default.yaml), serial, one process per run")
    print(f"  first copy (clusters, 5 bases, write): {first:8.2f} s, peak RSS {rss_first:6.0f} MB")
    print(f"  10 more copies                       : {ten:8.2f} s, peak RSS {rss_ten:6.0f} MB")
    print(f"  {n_copies - 11} more copies                      : {rest:8.2f} s, peak RSS {rss_rest:6.0f} MB")
    print(f"  per further copy                     : {per_copy:8.3f} s = {100 * per_copy / first:.1f} % of the first")
    shutil.rmtree(work / "marked", ignore_errors=True)


def leaks_bench():
    """Leak scan over real scans and procedural shapes (issue 13; several hours): see bench/leaks.py."""
    sys.path.insert(0, str(ROOT / "bench"))
    from leaks import leaks_bench as run

    run()


BENCHES = {"spectral": spectral_bench, "catalog": catalog_bench, "scan": scan_bench,
           "fingerprint": fingerprint_bench, "issue": issue_bench, "leaks": leaks_bench}
DEFAULT = ["spectral", "catalog", "scan", "fingerprint", "issue"]   # "leaks" runs when named


def main(argv):
    # one BLAS thread everywhere, as on the workers, so the comparisons are fair
    import os

    pinned = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    if any(os.environ.get(k) != v for k, v in pinned.items()):
        os.execve(sys.executable, [sys.executable, __file__, *argv], {**os.environ, **pinned})
    names = argv or DEFAULT
    for name in names:
        BENCHES[name]()
        print()


if __name__ == "__main__":
    main(sys.argv[1:])
