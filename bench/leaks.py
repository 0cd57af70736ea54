"""Leak-scan benchmark (issue 13): real and procedural assets, attacked leaks, negatives, catalogue growth.

``python bench/run.py leaks`` (several hours on 2 cores; not part of the
default ``make bench``).  Writes ``bench/results/leaks/summary.md``.

Catalogue: every real scan of ``../shared/data/models`` except the 110,000-point
Autzen LiDAR tile (large scenes are issue 15), linked, never copied, plus
procedural shapes, among them near-identical pairs (a shape and the same
shape bent by 1 % of its size; the bunny's four scans are near-identical
too).  Five recipients per asset, ``cluster_size`` 2,400 (the smallest scans
have 1,889 to 4,494 points).

Suspects: every asset's copy to one recipient (in turn) under each of the
seven attacks below, shuffled.  Negatives: unmarked originals (rotated,
rescaled), copies issued under another key, and unrelated procedural shapes.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("POINTMARK_TEST_DATA", ROOT.parent / "shared" / "data"))

ATTACKS = ["crop:0.5+random_similarity+noise:0.3%", "crop:0.3+random_similarity", "random_similarity+clutter:3",
           "outliers:0.5", "noise:0.5%", "resample:half", "removal:0.1"]
RECIPIENTS = [f"r{i}" for i in range(1, 6)]
SECRET = b"leak-benchmark-secret-0123456789"
OTHER_SECRET = b"leak-benchmark-other-key-987654321"


def _bend(points, amount=0.01):
    """The same shape bent by ``amount`` of its largest side (a near-identical asset)."""
    size = float((points.max(axis=0) - points.min(axis=0)).max())
    x = (points[:, 0] - points[:, 0].min()) / size
    out = points.copy()
    out[:, 1] += amount * size * np.sin(np.pi * x)
    return out


def _procedural(n_shapes, seed0, n_points=6000):
    from pipeline.demo import SHAPES, procedural_shape

    kinds = sorted(SHAPES)
    return {f"{kinds[i % len(kinds)]}-{seed0 + i:03d}": procedural_shape(kinds[i % len(kinds)], n_points,
                                                                        seed=seed0 + i) * 20
            for i in range(n_shapes)}


def build_catalogue(work):
    """Assets folder (links to the real scans, procedural PLY files) and its catalogue file."""
    from pipeline.io.catalog import catalogue_record, discover_assets, write_catalogue
    from pipeline.io.pointcloud import write_array

    assets = work / "assets"
    assets.mkdir(parents=True, exist_ok=True)
    shapes = _procedural(14, 0)
    for name in sorted(shapes)[:4]:
        shapes[f"{name}-bent"] = _bend(shapes[name])
    for name, points in shapes.items():
        write_array(assets, name, points, "ply")
    # the real scans are catalogued where they are (never copied; a link out of a folder is not read)
    real = [a for a in discover_assets(DATA / "models", default_recipients=RECIPIENTS)
            if a.key != "lidar_autzen_trim_110000"]
    rows = [catalogue_record(a) for a in real + discover_assets(assets, default_recipients=RECIPIENTS)]
    bad = [r for r in rows if r["status"] != "ok"]
    if bad:
        raise SystemExit(f"unusable assets: {[(r['asset_key'], r['error']) for r in bad]}")
    write_catalogue(rows, work / "catalog.parquet")
    return rows


def _config(work, manifests, out, key_id):
    from pipeline import config

    return config.load_config(None, [
        f"catalog.source={work / 'catalog.parquet'}", f"recipients=[{', '.join(RECIPIENTS)}]", f"key.id={key_id}",
        f"output.dir={out}", f"output.manifests={manifests}", f"output.bases={work / 'bases'}", "cluster_size=2400",
        # the marking every published figure of this benchmark used (the defaults before 0.3)
        "beta=0.002", "displacement=xyz", "chip_layout=consecutive", "code=repetition",
        f"scan.suspects={work / 'suspects'}", f"scan.catalogue={work / 'catalog.parquet'}",
        f"scan.manifests={work / 'manifests'}", f"scan.out={work / 'scan'}",
        "dask.progress=none", "dask.n_workers=2"])


def _chain(text, n):
    from pipeline import surface

    steps = []
    for part in text.split("+"):
        if part == "resample:half":
            steps.append(("resample", float(max(n // 2, 1000))))
        else:
            steps.append(surface.parse_attack(part))
    return steps + [("shuffle", None)]


def _redraw(work, name, asset, recipient, attack):
    """Leak ``name`` drawn again from its issued copy with seed ``[2026, k]`` (k its number).

    Returns
    -------
    drawn : (m, 3) float
    points : (n, 3) float, the issued copy
    """
    from pipeline import surface
    from pipeline.io.pointcloud import read_points

    points = read_points(work / "marked" / recipient / f"{asset}.ply").points
    rng = np.random.default_rng([2026, int(name.split("-")[1])])
    return surface.apply_chain(points, _chain(attack, len(points)), rng), points


def _results(folder, key="name"):
    """A scan's rows by suspect file name (or ``key="sha"``: by its sha256), the latest scan of each kept."""
    from pipeline.orchestrate.scan import read_scan

    rows = sorted(read_scan(folder), key=lambda r: r["scanned_at"])
    return {(Path(r["suspect_path"]).stem if key == "name" else r["suspect_sha256"]): r for r in rows}


def _found(r):
    """Whether a scan row had the leaked asset to check: among its candidates, or an exact re-save."""
    return (r["verdict"] == "match" and not r.get("candidates")), list(r.get("candidates") or [])


def write_suspects(work, rows, other_rows):
    """Attacked leaks and negatives; returns {suspect name: (kind, asset, recipient, attack)}."""
    from pipeline import surface
    from pipeline.io.pointcloud import read_points, write_array

    rng = np.random.default_rng(2026)
    folder = work / "suspects"
    truth = {}
    issued = {(r["asset_key"], r["recipient"]): r for r in rows if r["status"] == "ok"}
    assets = sorted({a for a, _ in issued})
    k = 0
    for a_i, asset in enumerate(assets):
        for t_i, attack in enumerate(ATTACKS):
            recipient = RECIPIENTS[(a_i + t_i) % len(RECIPIENTS)]
            points = read_points(issued[(asset, recipient)]["output_path"]).points
            name = f"leak-{k:03d}"
            write_array(folder, name, surface.apply_chain(points, _chain(attack, len(points)), rng), "ply")
            truth[name] = ("leak", asset, recipient, attack)
            k += 1
    originals = {r["asset_key"]: r["source_path"] for r in rows if r["status"] == "ok"}
    for i, asset in enumerate(assets):
        points = read_points(originals[asset]).points
        write_array(folder, f"unmarked-{i:03d}", surface.apply_chain(
            points, [("random_similarity", None), ("shuffle", None)], rng), "ply")
        truth[f"unmarked-{i:03d}"] = ("unmarked original", asset, None, "random_similarity")
    for i, r in enumerate(other_rows):
        points = read_points(r["output_path"]).points
        write_array(folder, f"otherkey-{i:03d}", surface.apply_chain(
            points, [("random_similarity", None), ("shuffle", None)], rng), "ply")
        truth[f"otherkey-{i:03d}"] = ("copy under another key", r["asset_key"], None, "random_similarity")
    for i, (name, points) in enumerate(sorted(_procedural(20, 500).items())):
        write_array(folder, f"unrelated-{i:03d}", surface.apply_chain(
            points, [("random_similarity", None), ("shuffle", None)], rng), "ply")
        truth[f"unrelated-{i:03d}"] = ("unrelated shape", None, None, "random_similarity")
    (work / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def growth(work, rows, truth, n_large=300, n_queries=20):
    """Candidate search per suspect with the catalogue and with ``n_large`` assets, exact and through a faiss IVF.

    Both searches use the same index (same descriptors and background prior);
    ``right`` counts queries whose leaked asset is among the top 3.
    """
    from pipeline.features import build_index
    from pipeline.io.pointcloud import read_points

    clouds = {r["asset_key"]: read_points(work / r["path"]).points for r in rows if r["status"] == "ok"}
    extra = _procedural(n_large - len(clouds), 1000)
    queries = sorted((work / "suspects").glob("leak-*.ply"))[:: max(1, 217 // n_queries)][:n_queries]
    suspects = [(read_points(q).points, truth[q.stem][1]) for q in queries]
    out = {}
    for label, cat in (("catalogue", clouds), ("grown", {**clouds, **extra})):
        t0 = time.perf_counter()
        index = build_index(cat, ivf=False)
        built = time.perf_counter() - t0
        t0 = time.perf_counter()
        ivf = index.with_ivf()
        trained = time.perf_counter() - t0
        for search, variant in (("exact", index), ("faiss IVF", ivf)):
            t0 = time.perf_counter()
            right = sum(asset in [k for k, _ in variant.rank(points, top_k=3)] for points, asset in suspects)
            out[f"{label}, {search}"] = {
                "assets": len(cat), "index_rows": len(index.features), "build_seconds": built,
                "train_seconds": trained if search != "exact" else 0.0,
                "rank_seconds_per_suspect": (time.perf_counter() - t0) / len(suspects),
                "right_in_top_3": f"{right}/{len(suspects)}"}
    return out


def leaks_bench(resume=None):
    """Issue, attack, scan and summarise; ``resume`` (or ``POINTMARK_BENCH_RESUME=1``) keeps the issued
    copies, suspects and scan results of an interrupted run and scans only the suspects not yet scanned."""
    from pipeline.orchestrate.scan import read_scan, run_scan

    work = ROOT / "bench" / "results" / "leaks"
    if not DATA.is_dir():
        raise SystemExit(f"{DATA}: the shared data folder is missing (set POINTMARK_TEST_DATA)")
    resume = os.environ.get("POINTMARK_BENCH_RESUME") == "1" if resume is None else resume
    if resume and (work / "truth.json").is_file():
        catalogue = [r for r in _read_catalogue(work)]
        truth = {k: tuple(v) for k, v in json.loads((work / "truth.json").read_text()).items()}
        cfg, t_issue = _config(work, work / "manifests", work / "marked", "bench"), float("nan")
    else:
        catalogue, truth, cfg, t_issue = _issue(work)
    before = len(read_scan(work / "scan")) if resume and (work / "scan").is_dir() else 0
    t0 = time.perf_counter()
    status = run_scan(cfg, SECRET, force=not resume)
    wall = time.perf_counter() - t0
    # rows keyed by file name: an interrupted run may have scanned a suspect from another folder
    results = _results(work / "scan")
    summary = _summarise(truth, results, wall, status, len(catalogue), t_issue)
    summary["scanned_this_run"] = len(read_scan(work / "scan")) - before
    summary["growth"] = growth(work, catalogue, truth)
    _write(work, summary)


def resample_bench(check=False):
    """The resampled leaks of an issued benchmark drawn again (seed ``[2026, k]`` for leak k) and scanned.

    Needs ``bench/results/leaks`` from a run of :func:`leaks_bench`.  With
    ``check``, nothing is written or scanned: each leak is drawn from its
    seed again and the share of its points found within 1e-5 of the size in
    the file on disk is printed (the resample attack's reproducibility).
    """
    from scipy.spatial import cKDTree

    from pipeline.io.pointcloud import read_points, write_array
    from pipeline.orchestrate.scan import run_scan

    work = ROOT / "bench" / "results" / "leaks"
    truth = json.loads((work / "truth.json").read_text())
    for name, (_, asset, recipient, attack) in truth.items():
        if attack != "resample:half":
            continue
        drawn, points = _redraw(work, name, asset, recipient, attack)
        if check:
            d, _ = cKDTree(read_points(work / "suspects" / f"{name}.ply").points).query(drawn)
            print(f"{name} {asset}: {np.mean(d < 1e-5 * np.ptp(points, axis=0).max()):.4f} of the points again")
        else:
            write_array(work / "suspects", name, drawn, "ply", keep_existing=False)
    if not check:
        t0 = time.perf_counter()
        status = run_scan(_config(work, work / "manifests", work / "marked", "bench"), SECRET)
        print(f"scan exit status {status} in {time.perf_counter() - t0:.0f} s; results in {work / 'scan'}")


def trim_bench():
    """Each whole-copy leak checked against its true asset with and without the trimmed fit.

    Needs ``bench/results/leaks`` from a run of :func:`leaks_bench`.  The same
    registration and detection path as the scan (``detect_from_ledger`` with
    the asset named), ``detection.outlier_trim`` null and the config's value;
    writes ``bench/results/leaks/trim.json`` and prints each attack's scores.
    """
    import dataclasses

    from pipeline import config
    from pipeline.orchestrate.detect import detect_from_ledger

    work = ROOT / "bench" / "results" / "leaks"
    truth = json.loads((work / "truth.json").read_text())
    params = config.detect_params(_config(work, work / "manifests", work / "marked", "bench"))
    variants = {"kept": dataclasses.replace(params, outlier_trim=None), "trimmed": params}
    rows = []
    for name, (kind, asset, recipient, attack) in sorted(truth.items()):
        if kind != "leak" or attack not in ("outliers:0.5", "noise:0.5%", "resample:half", "removal:0.1"):
            continue
        row = {"suspect": name, "asset": asset, "recipient": recipient, "attack": attack}
        for label, dp in variants.items():
            r = detect_from_ledger(work / "suspects" / f"{name}.ply", work / "manifests", SECRET, dp, asset=asset,
                                   store=work / "bases")
            named = [a.get("recipient") for a in r.get("accused") or []]
            score = r.get("best_score")
            row[label] = {"verdict": r["verdict"], "score": float("nan") if score is None else score,
                          "threshold": r["threshold"],
                          "right": named == [recipient]}
        rows.append(row)
        print(name, asset, attack, *(f"{k} {row[k]['score']:.2f} {row[k]['verdict']}" for k in variants), flush=True)
    (work / "trim.json").write_text(json.dumps(rows, indent=1))
    for attack in sorted({r["attack"] for r in rows}):
        sel = [r for r in rows if r["attack"] == attack]
        ratio = np.array([r["trimmed"]["score"] / r["kept"]["score"] for r in sel])
        print(f"{attack}: {len(sel)} leaks; right recipient kept {sum(r['kept']['right'] for r in sel)}, "
              f"trimmed {sum(r['trimmed']['right'] for r in sel)}; median score kept "
              f"{np.median([r['kept']['score'] for r in sel]):.2f}, trimmed "
              f"{np.median([r['trimmed']['score'] for r in sel]):.2f}; trimmed/kept {ratio.min():.2f} to "
              f"{ratio.max():.2f} (median {np.median(ratio):.2f})")


PART_ATTACKS = ATTACKS[:3]   # crops and scenes: the suspect is part of the asset, or the asset part of it


def parts_bench():
    """The part and scene leaks of an issued benchmark drawn again where their files are missing.

    Needs ``bench/results/leaks`` from a run of :func:`leaks_bench`.  Leak k
    is drawn from its issued copy with seed ``[2026, k]`` (as
    :func:`resample_bench` draws); a leak whose file exists is kept.
    """
    from pipeline.io.pointcloud import write_array

    work = ROOT / "bench" / "results" / "leaks"
    truth = json.loads((work / "truth.json").read_text())
    drawn = 0
    for name, (_, asset, recipient, attack) in truth.items():
        if attack not in PART_ATTACKS or (work / "suspects" / f"{name}.ply").exists():
            continue
        write_array(work / "suspects", name, _redraw(work, name, asset, recipient, attack)[0], "ply")
        drawn += 1
    print(f"{drawn} leaks drawn into {work / 'suspects'}")


POSE_LEAKS = ("leak-050", "leak-119", "leak-120", "leak-196", "leak-197", "leak-203", "leak-210", "leak-211")


def poses_bench(names=POSE_LEAKS):
    """How far the registration lays crop leaks from the pose of their known attack, in spacings of the original.

    Each leak (its chain a crop first, as in :data:`PART_ATTACKS`) is drawn
    again from its seed as :func:`_redraw` draws it, without the shuffle, so
    the kept points of the issued copy are known; the true pose is their
    Procrustes fit.  Registered by detection's own registration of the
    checked-out tree (``watermark.register``, with the original's normals).
    """
    from scipy.spatial import cKDTree

    from pipeline import config, surface, watermark
    from pipeline.io.pointcloud import read_points
    from pipeline.kernels import attacks, registration, resampling

    work = ROOT / "bench" / "results" / "leaks"
    truth = json.loads((work / "truth.json").read_text())
    for name in names:
        _, asset, recipient, attack = truth[name]
        points = read_points(work / "marked" / recipient / f"{asset}.ply").points
        original = read_points(work / "assets" / f"{asset}.ply").points
        chain = _chain(attack, len(points))[:-1]                       # no shuffle: rows stay matched
        rng = np.random.default_rng([2026, int(name.split("-")[1])])
        normal, offset = attacks.crop_plane(points, chain[0][1], rng)
        kept = points[points @ normal >= offset]
        drawn = surface.apply_chain(kept, chain[1:], rng)
        true = registration.umeyama(drawn, kept)
        spacing = float(np.median(resampling.nearest_spacing(original)))
        t0 = time.perf_counter()
        found = watermark.register(drawn, original, spacing, config.DetectParams(registration="robust"),
                                    cKDTree(original),
                                    resampling.estimate_normals(original))
        off = np.linalg.norm(registration.apply(found, drawn) - registration.apply(true, drawn), axis=1) / spacing
        print(f"{name} {asset} {attack}: median {np.median(off):.2f}, most {off.max():.2f} spacings from the "
              f"true pose; {time.perf_counter() - t0:.0f} s", flush=True)


def rescan_bench():
    """Every leak of an issued benchmark scanned afresh in one run, today's config, into ``leaks/rescan``.

    Needs ``bench/results/leaks`` from a run of :func:`leaks_bench` (and
    :func:`parts_bench` where part leaks are missing).  The leaks are copied
    into ``rescan/suspects``; earlier results there are removed first unless
    ``POINTMARK_BENCH_RESUME=1`` resumes an interrupted run.  Negatives are
    not scanned (:func:`negatives_bench` scans them).  Writes
    ``rescan/summary.json`` and prints each attack's counts.
    """
    truth, results, s = _rescan("rescan", lambda kind: kind == "leak")
    s["misses"] = [(n, a, attack, results[n]["verdict"], results[n].get("candidate_asset"),
                    results[n].get("recipient"), results[n].get("score"), results[n].get("threshold"))
                   for n, (_, a, rec, attack) in sorted(truth.items()) if n in results
                   and (results[n]["verdict"], results[n].get("candidate_asset"), results[n].get("recipient"))
                   != ("match", a, rec)]
    (ROOT / "bench" / "results" / "leaks" / "rescan" / "summary.json").write_text(json.dumps(s, indent=1, default=str))
    tot = Counter()
    for attack, c in sorted(s["per_attack"].items()):
        tot.update(c)
        print(f"{attack}: {dict(c)}")
    print(f"all: {dict(tot)}; failed {len(s['failed'])}; exit status {s['exit_status']}; "
          f"{s['wall_seconds']:.0f} s on 2 workers; worker seconds per suspect: "
          + ", ".join(f"{k} {v / max(len(results), 1):.1f}" for k, v in s["stage_seconds"].items()))
    for m in s["misses"]:
        print("missed:", *m)


def negatives_bench():
    """The negatives of an issued benchmark scanned afresh with today's config, into ``leaks/negatives``.

    Unmarked originals, unrelated shapes and copies under another key: none
    may be a match.  Same folders, config and resume rule as
    :func:`rescan_bench`.  Writes ``negatives/summary.json`` and prints the
    false matches, the checks made and the best score against its threshold.
    """
    truth, results, s = _rescan("negatives", lambda kind: kind != "leak")
    rows = [results[n] for n in truth if n in results and results[n]["verdict"] != "failed"]
    s["best"] = max(((r["score"], r["threshold"], Path(r["suspect_path"]).stem) for r in rows
                     if r.get("score") is not None), default=None)
    limits = [r["threshold"] for r in rows if r.get("threshold") is not None]
    s["thresholds"] = [min(limits), max(limits)] if limits else None
    (ROOT / "bench" / "results" / "leaks" / "negatives" / "summary.json").write_text(
        json.dumps(s, indent=1, default=str))
    print(f"{len(rows)} negatives scanned ({s['negatives']}); {s['negative_asset_checks']} suspect-asset checks, "
          f"{s['negative_recipient_checks']} recipient scores; false matches {s['false_matches']}; "
          f"failed {len(s['failed'])}; best score {s['best']}; thresholds {s['thresholds']}; "
          f"exit status {s['exit_status']}; {s['wall_seconds']:.0f} s on 2 workers; worker seconds per suspect: "
          + ", ".join(f"{k} {v / max(len(rows), 1):.1f}" for k, v in s["stage_seconds"].items()))


def _rescan(sub, keep):
    """Scan the issued suspects whose kind ``keep`` accepts afresh into ``leaks/<sub>``; (truth, results, summary)."""
    import filecmp

    from pipeline.orchestrate.scan import run_scan

    work = ROOT / "bench" / "results" / "leaks"
    out = work / sub
    truth = {n: tuple(v) for n, v in json.loads((work / "truth.json").read_text()).items()
             if keep(v[0]) and (work / "suspects" / f"{n}.ply").exists()}
    if os.environ.get("POINTMARK_BENCH_RESUME") != "1":
        shutil.rmtree(out / "scan", ignore_errors=True)
    (out / "suspects").mkdir(parents=True, exist_ok=True)
    for name in truth:
        src, dst = work / "suspects" / f"{name}.ply", out / "suspects" / f"{name}.ply"
        if not dst.exists() or not filecmp.cmp(src, dst, shallow=False):
            shutil.copy2(src, dst)
    cfg = _config(work, work / "manifests", work / "marked", "bench")
    cfg["scan"]["suspects"], cfg["scan"]["out"] = str(out / "suspects"), str(out / "scan")
    t0 = time.perf_counter()
    status = run_scan(cfg, SECRET)
    wall = time.perf_counter() - t0
    results = _results(out / "scan")
    return truth, results, _summarise(truth, results, wall, status, len(_read_catalogue(work)), float("nan"))


def _triage_one(args):
    from pipeline.orchestrate.candidates import triage

    return triage(*args)


def candidates_bench():
    """The scan's candidate search alone for every suspect on disk, against the candidates its scan recorded.

    Needs ``bench/results/leaks`` from a run of :func:`leaks_bench`.  Each
    suspect is ranked as the scan ranks it (``triage``, with the index of
    the current format, built if missing) on 2 spawned processes, and its
    candidates taken as the scan takes them.  Writes
    ``bench/results/leaks/candidates.json`` and prints, per attack, how
    often the leaked asset is a candidate now and was in the recorded scan,
    and the negatives' candidate counts (their asset checks).
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from pipeline.orchestrate.candidates import candidates as _candidates
    from pipeline.orchestrate.scan import _ranked_by, _reference

    work = ROOT / "bench" / "results" / "leaks"
    truth = json.loads((work / "truth.json").read_text())
    cfg = _config(work, work / "manifests", work / "marked", "bench")
    index_path, descriptors = _ranked_by(_reference(cfg, SECRET), work / "scan")
    recorded = _results(work / "scan", key="sha")     # by content: a leak drawn again was not scanned there
    names = sorted(n for n in truth if (work / "suspects" / f"{n}.ply").exists())
    t0 = time.perf_counter()
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        infos = list(pool.map(_triage_one, [(str(work / "suspects" / f"{n}.ply"), descriptors, index_path)
                                            for n in names]))
    wall = time.perf_counter() - t0
    rows, view = [], set(descriptors)
    for name, info in zip(names, infos):
        kind, asset, _, attack = truth[name]
        picked = _candidates(info, view, cfg["scan"]["top_k"], cfg["scan"]["shape_margin"])
        old = recorded.get(info["sha256"])
        exact, checked = _found(old) if old is not None else (False, [])
        rows.append({"suspect": name, "kind": kind, "asset": asset, "attack": attack, "candidates": picked,
                     "shape_rank": info["ranking"].index(asset) if asset in info["ranking"] else None,
                     "vote_rank": info["index_ranking"].index(asset) if asset in info["index_ranking"] else None,
                     "recorded": None if old is None else bool(exact or asset in checked),
                     "recorded_checks": None if old is None else len(checked), "seconds": info["seconds"],
                     "ranking": info["ranking"], "distances": info["distances"],
                     "index_ranking": info["index_ranking"]})
    (work / "candidates.json").write_text(json.dumps(rows, indent=1))
    print(f"{len(rows)} suspects ranked in {wall:.0f} s on 2 processes "
          f"({np.mean([r['seconds'] for r in rows]):.1f} s each)")
    for attack in sorted({r["attack"] for r in rows if r["kind"] == "leak"}):
        sel = [r for r in rows if r["kind"] == "leak" and r["attack"] == attack]
        was = [r for r in sel if r["recorded"] is not None]
        old = sum(r["recorded"] for r in was)
        now = [r for r in sel if r["asset"] in r["candidates"]]
        print(f"{attack}: {len(sel)} leaks, asset a candidate {len(now)}; recorded scan {old} of {len(was)}; "
              f"missed now: {[(r['suspect'], r['asset'], r['shape_rank'], r['vote_rank']) for r in sel if r not in now]}")
    neg = [r for r in rows if r["kind"] != "leak"]
    if neg:
        print(f"negatives: {len(neg)}, asset checks {sum(len(r['candidates']) for r in neg)} "
              f"(recorded scan {sum(r['recorded_checks'] for r in neg if r['recorded_checks'] is not None)})")
    leaks = [r for r in rows if r["kind"] == "leak"]
    for k in (3, 4, 5, 6):      # what scan.top_k buys: leaks with their asset to check, checks per innocent
        found = sum(r["asset"] in _candidates(r, view, k, cfg["scan"]["shape_margin"]) for r in leaks)
        checks = np.mean([len(_candidates(r, view, k, cfg["scan"]["shape_margin"])) for r in neg]) if neg else 0.0
        print(f"top_k {k}: leaked asset a candidate for {found} of {len(leaks)}; {checks:.2f} asset checks "
              f"per negative")


def _read_catalogue(work):
    import pyarrow.parquet as pq

    return pq.read_table(work / "catalog.parquet").to_pylist()


def _issue(work):
    """A fresh catalogue, issued copies (and copies under another key) and attacked suspects."""
    from pipeline.orchestrate.progress import Progress
    from pipeline.orchestrate.run import plan_job, run_job

    for sub in ("scan", "suspects"):
        shutil.rmtree(work / sub, ignore_errors=True)
    (work / "truth.json").unlink(missing_ok=True)    # a resume must not pair an old truth with new suspects
    t0 = time.perf_counter()
    catalogue = build_catalogue(work)
    cfg = _config(work, work / "manifests", work / "marked", "bench")
    job = plan_job(cfg, SECRET)
    run_job(job, cfg, progress=Progress())
    rows = job.ledger.rows()
    # copies of ten assets under another key, in a ledger the scan never sees
    other_cfg = _config(work, work / "other-manifests", work / "other-marked", "other")
    other_cfg["recipients"] = ["x1"]
    other_job = plan_job(other_cfg, OTHER_SECRET)
    run_job(other_job, other_cfg, progress=Progress())
    other_rows = [r for r in other_job.ledger.rows() if r["status"] == "ok"][::3][:10]
    t_issue = time.perf_counter() - t0
    truth = write_suspects(work, rows, other_rows)
    return catalogue, truth, cfg, t_issue


def _summarise(truth, results, wall, status, n_assets, t_issue):
    per_attack = {}
    negatives = Counter()
    neg_checks = neg_recipients = false_matches = 0
    failed = []
    for name, (kind, asset, recipient, attack) in truth.items():
        r = results.get(name)
        if r is None or r["verdict"] == "failed":
            failed.append((name, None if r is None else r.get("error")))
            continue
        if kind == "leak":
            cell = per_attack.setdefault(attack, Counter())
            cell["suspects"] += 1
            exact, picked = _found(r)
            cell["candidate"] += bool(exact or asset in picked)
            cell["right"] += r["verdict"] == "match" and (r["candidate_asset"], r["recipient"]) == (asset, recipient)
            cell["wrong"] += r["verdict"] == "match" and (r["candidate_asset"], r["recipient"]) != (asset, recipient)
            cell["inconclusive"] += r["verdict"] == "inconclusive"
        else:
            negatives[kind] += 1
            false_matches += r["verdict"] == "match"
            negatives[f"{kind}: inconclusive"] += r["verdict"] == "inconclusive"
            neg_checks += len(r.get("candidates") or [])
            neg_recipients += r.get("n_checked") or 0
    stages = Counter()
    for r in results.values():
        stages["candidates"] += r.get("seconds_candidates") or 0
        stages["registration"] += r.get("seconds_registration") or 0
        stages["detection"] += r.get("seconds_detection") or 0
    return {"assets": n_assets, "suspects": len(truth), "wall_seconds": wall, "issue_seconds": t_issue,
            "exit_status": status, "per_attack": {k: dict(v) for k, v in per_attack.items()},
            "negatives": dict(negatives), "negative_asset_checks": neg_checks,
            "negative_recipient_checks": neg_recipients, "false_matches": false_matches,
            "failed": failed, "stage_seconds": dict(stages)}


def _write(work, s):
    lines = [f"# Leak-scan benchmark: {s['suspects']} suspects, {s['assets']} assets x {len(RECIPIENTS)} recipients",
             "", f"Scan wall time {s['wall_seconds']:.0f} s on 2 workers for the {s['scanned_this_run']} suspects "
             f"scanned in this run ({s['wall_seconds'] / max(s['scanned_this_run'], 1):.1f} s per suspect); "
             f"exit status {s['exit_status']}.", "",
             "| attack | leaks | right asset among candidates | right recipient named | wrong recipient named "
             "| inconclusive |", "|---|---|---|---|---|---|"]
    tot = Counter()
    for attack, c in s["per_attack"].items():
        tot.update(c)
        lines.append(f"| {attack} | {c['suspects']} | {c['candidate']} | {c['right']} | {c['wrong']} "
                     f"| {c['inconclusive']} |")
    lines.append(f"| all | {tot['suspects']} | {tot['candidate']} ({100 * tot['candidate'] / max(tot['suspects'], 1):.1f} %) "
                 f"| {tot['right']} ({100 * tot['right'] / max(tot['suspects'], 1):.1f} %) | {tot['wrong']} "
                 f"| {tot['inconclusive']} |")
    lines += ["", f"Negatives: {s['negatives']}; {s['negative_asset_checks']} suspect-asset checks, "
              f"{s['negative_recipient_checks']} recipient scores; false matches: {s['false_matches']}.",
              f"Failed suspects: {len(s['failed'])} {s['failed'][:5]}", ""]
    total = sum(s["stage_seconds"].values()) or 1.0
    lines.append("Worker seconds by stage: " + ", ".join(
        f"{k} {v:.0f} s ({100 * v / total:.0f} %)" for k, v in s["stage_seconds"].items()))
    g = s["growth"]
    lines += ["", "Candidate search as the catalogue grows (index built once per catalogue version; "
              "rank per suspect; right = leaked asset in the top 3):"]
    for label, v in g.items():
        lines.append(f"- {label}: {v['assets']} assets ({v['index_rows']} descriptors), build "
                     f"{v['build_seconds']:.0f} s (+{v['train_seconds']:.0f} s cells), rank "
                     f"{v['rank_seconds_per_suspect']:.2f} s per suspect, right {v['right_in_top_3']}")
    text = "\n".join(lines) + "\n"
    (work / "summary.md").write_text(text)
    (work / "summary.json").write_text(json.dumps(s, indent=1, default=str))
    print(text)
