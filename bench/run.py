"""pointmark benchmarks: ``make bench`` (or ``python bench/run.py [spectral] [catalog] [scan] [fingerprint] [issue] [cli] [leaks] [leaks-resample] [leaks-resample-check] [leaks-trim] [leaks-parts] [leaks-rescan] [leaks-candidates] [leaks-poses] [leaks-negatives] [tile] [gltf] [fingerprint-crops] [scan-throughput]``).

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
    """Issuing copies of the bunny: the first copy, then each further one (bases from the store).

    The default (clusters covering the bunny) and ``cover: false`` (the paper's 5 clusters from
    seeds) side by side, with the cost per marked point.
    """
    import shutil

    import yaml

    bunny = ROOT.parent / "shared" / "data" / "models" / "bunny_zipper_faceref_34834.ply"
    names = [f"recipient-{i:04d}" for i in range(n_copies)]
    print("issuing copies of the bunny (34,834 points, configs/default.yaml), serial, one process per run")
    for label, cover in (("covering (default)", True), ("from seeds (cover false)", False)):
        work = ROOT / "bench" / "results" / "issue"
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        cfg = yaml.safe_load((ROOT / "configs" / "default.yaml").read_text())
        cfg["watermark"]["cover"] = cover
        cfg.update({"catalog": {"source": str(bunny)}, "key": {"id": "bench"},
                    "output": {"dir": str(work / "marked"), "manifests": str(work / "ledger")}})
        (work / "issue.yaml").write_text(yaml.safe_dump(cfg))
        first, rss_first = _issue_run(work, names[:1])
        ten, rss_ten = _issue_run(work, names[:11])
        rest, rss_rest = _issue_run(work, names)
        per_copy = rest / (n_copies - 11)
        marked = _marked_points(cfg, bunny)
        print(f"clusters {label}: {marked:,} points in a cluster")
        print(f"  first copy (clusters, bases, write): {first:8.2f} s, peak RSS {rss_first:6.0f} MB, "
              f"{1e6 * first / marked:.0f} us per marked point")
        print(f"  10 more copies                     : {ten:8.2f} s, peak RSS {rss_ten:6.0f} MB")
        print(f"  {n_copies - 11} more copies                    : {rest:8.2f} s, peak RSS {rss_rest:6.0f} MB")
        print(f"  per further copy                   : {per_copy:8.3f} s = {100 * per_copy / first:.1f} % of the "
              f"first, {1e6 * per_copy / marked:.1f} us per marked point")
        shutil.rmtree(work / "marked", ignore_errors=True)


def _marked_points(cfg, path):
    """Points in a cluster of one asset under a config dict."""
    from pipeline import config
    from pipeline.io.pointcloud import read_points
    from pipeline.watermark import frame_of, plan_clusters

    points = read_points(path).points
    specs = plan_clusters(points - frame_of(points).centre, config.watermark_params(cfg))
    return len(np.unique(np.concatenate([s.members for s in specs])))


PREVIOUS = "14b375f"   # the release before issue 15: no thread pinning in the CLI, no basis store


def _cli(tree, args, cores=None):
    """Seconds of one ``pointmark`` command run from ``tree`` (a checkout), optionally on given cores."""
    import os
    import subprocess

    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}   # as a user runs it
    env.update(PYTHONPATH=str(tree), POINTMARK_SECRET="bench-secret-0123456789abcdef")
    cmd = [sys.executable, "-m", "pipeline.cli", *map(str, args)]
    if cores:
        cmd = ["taskset", "-c", cores, *cmd]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode not in (0, 1):
        raise RuntimeError(f"{' '.join(cmd)}: exit {done.returncode}: {done.stderr[-2000:]}")
    return time.perf_counter() - t0


def cli_bench(repeat=2):
    """embed and detect of the bunny through the CLI, this tree against the previous release (issue 15).

    Both run the previous release's configs/default.yaml (the same run), as
    a user runs them (no thread variables set), pinned to one core by
    taskset, interleaved, best of ``repeat``.  Then detection with the
    original's bases in the store (``detect --ledger`` after ``run``), and
    four concurrent detections on both cores against one alone.
    """
    import shutil
    import subprocess

    import yaml

    bunny = ROOT.parent / "shared" / "data" / "models" / "bunny_zipper_faceref_34834.ply"
    work = ROOT / "bench" / "results" / "cli"
    previous = work / "previous"
    if not (previous / "pipeline").exists():
        shutil.rmtree(previous, ignore_errors=True)
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", str(previous), PREVIOUS],
                       check=True, capture_output=True)
    for sub in ("marked", "ledger"):
        shutil.rmtree(work / sub, ignore_errors=True)
    (work / "marked").mkdir(parents=True)
    cfg = work / "config.yaml"
    cfg.write_bytes(subprocess.run(["git", "-C", str(ROOT), "show", f"{PREVIOUS}:configs/default.yaml"],
                                   check=True, capture_output=True).stdout)
    message = "5ca1ab1e"
    times = {}

    def timed(name, tree, args, cores="0"):
        times[name] = min(times.get(name, float("inf")), _cli(tree, args, cores))

    for _ in range(repeat):
        for label, tree in (("previous", previous), ("current", ROOT)):
            out = work / "marked" / f"{label}.ply"
            timed(f"{label} embed", tree, ["embed", bunny, out, "--key-id", "bench", "--message", message,
                                           "--config", cfg])
            timed(f"{label} detect", tree, ["detect", out, "--original", bunny, "--key-id", "bench",
                                            "--expect", message, "--config", cfg])
    # a one-asset catalogue run fills the basis store; detection then reads the bases
    run_cfg = yaml.safe_load(cfg.read_text())
    run_cfg.update({"catalog": {"source": str(bunny)}, "recipients": ["r1"], "key": {"id": "bench"},
                    "output": {"dir": str(work / "marked" / "run"), "manifests": str(work / "ledger")}})
    (work / "run.yaml").write_text(yaml.safe_dump(run_cfg))
    _cli(ROOT, ["run", work / "run.yaml", "--serial"])
    issued = next((work / "marked" / "run").rglob("*.ply"))
    for _ in range(repeat):
        timed("current detect, bases in the store", ROOT, ["detect", issued, "--ledger", work / "ledger"])
    # four detections at once on both cores, against one alone
    import concurrent.futures as cf

    args = ["detect", work / "marked" / "current.ply", "--original", bunny, "--key-id", "bench", "--config", cfg]
    one = _cli(ROOT, args)
    with cf.ThreadPoolExecutor(4) as pool:
        t0 = time.perf_counter()
        list(pool.map(lambda _: _cli(ROOT, args), range(4)))
        four = time.perf_counter() - t0
    print(f"CLI on the bunny (34,834 points), the previous release ({PREVIOUS}) against this tree, "
          f"its configs/default.yaml, one core (taskset), best of {repeat}, interleaved")
    for name, value in times.items():
        print(f"  {name:38s}: {value:7.2f} s")
    for step in ("embed", "detect"):
        print(f"  {step} speed-up, cold              : {times[f'previous {step}'] / times[f'current {step}']:7.2f} x")
    print(f"  detect speed-up, bases in the store  : "
          f"{times['previous detect'] / times['current detect, bases in the store']:7.2f} x")
    print(f"  one detection alone (2 cores)        : {one:7.2f} s")
    print(f"  four concurrent detections (2 cores) : {four:7.2f} s = {four / one:.2f} x one")


def leaks_bench():
    """Leak scan over real scans and procedural shapes (issue 13; several hours): see bench/leaks.py."""
    sys.path.insert(0, str(ROOT / "bench"))
    from leaks import leaks_bench as run

    run()


def _leaks(name, doc, **kwargs):
    """A bench entry that runs ``bench/leaks.py``'s ``name`` on an issued leak benchmark."""
    def run():
        sys.path.insert(0, str(ROOT / "bench"))
        import leaks

        getattr(leaks, name)(**kwargs)

    run.__doc__ = doc
    return run


resample_bench = _leaks("resample_bench", "The leak benchmark's resampled leaks drawn again and scanned.")
resample_check = _leaks("resample_bench", "The resampled leaks drawn again and compared with the files.", check=True)
trim_bench = _leaks("trim_bench", "The whole-copy leaks against their true asset, fit trimmed and not (~22 min).")
parts_bench = _leaks("parts_bench", "The part and scene leaks drawn again where their files are missing.")
rescan_bench = _leaks("rescan_bench", "Every leak scanned afresh in one run (~1.5 h on 2 cores).")
candidates_bench = _leaks("candidates_bench", "The candidate search alone for every suspect (~15 min).")
poses_bench = _leaks("poses_bench", "Distance of crop leaks' registrations from their known pose (~3 min).")
negatives_bench = _leaks("negatives_bench", "Every negative scanned afresh in one run (~1.5 h on 2 cores).")


def gltf_bench():
    """GLB copies leaked through glTF Transform and trimesh, scanned (issue 40; ~10 min): see bench/gltf.py."""
    sys.path.insert(0, str(ROOT / "bench"))
    from gltf import main as run

    run(ROOT / "bench" / "results" / "gltf")


def crops_bench():
    """Fingerprints in 10 % crops at the paper's distance, clusters from seeds or covering (issue 39; ~20 min)."""
    sys.path.insert(0, str(ROOT / "bench"))
    from crops import crops_bench as run

    run()


def throughput_bench():
    """A nightly crawl's mix (90 % innocent) scanned against 100 and 300 assets (issue 38; hours): bench/throughput.py."""
    sys.path.insert(0, str(ROOT / "bench"))
    from throughput import throughput_bench as run

    run()


def tile_bench():
    """Embedding 1- and 10-million-point LAZ tiles (issue 15; about 45 minutes): see bench/tile.py."""
    sys.path.insert(0, str(ROOT / "bench"))
    from tile import tile_bench as run

    run()


BENCHES = {"spectral": spectral_bench, "catalog": catalog_bench, "scan": scan_bench,
           "fingerprint": fingerprint_bench, "issue": issue_bench, "cli": cli_bench, "leaks": leaks_bench,
           "tile": tile_bench, "leaks-resample": resample_bench, "leaks-resample-check": resample_check,
           "leaks-trim": trim_bench, "leaks-parts": parts_bench, "leaks-rescan": rescan_bench,
           "leaks-candidates": candidates_bench, "leaks-poses": poses_bench,
           "leaks-negatives": negatives_bench, "gltf": gltf_bench,
           "fingerprint-crops": crops_bench, "scan-throughput": throughput_bench}
DEFAULT = ["spectral", "catalog", "scan", "fingerprint", "issue", "cli"]   # the others run when named


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
