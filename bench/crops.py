"""Fingerprints in 10 % crops at the paper's distance, with and without clusters covering the asset (issue 39).

``python bench/run.py fingerprint-crops`` (about 20 minutes on one core).  For
each scan of at least 15,000 points below, two embeddings at the same
distance to the surface:

- ``seeds``: the default configuration with ``cover: false`` (5 clusters of
  4,000 points grown from seeds, beta 0.00115 along the normals: the paper's
  distance);
- ``cover``: the default (clusters of 4,000 tile the whole asset, alpha
  scaled by sqrt(5 / clusters planned): the same distance).

A copy to one of 1,000 recipients is cropped to 10 % of its points by a plane
at 10 random directions (seeds 0-9), rotated, rescaled and shuffled, and
attributed with the default detection (``evaluate.fingerprint_trial``).
Rows go to ``bench/results/crops/rows.jsonl`` (resumable); the summary is
printed and written to ``summary.md`` there (the threshold column: the highest, since
it counts every pose the mark was read at).  ``python bench/crops.py cover`` runs only the
default configuration; ``python bench/crops.py 0.05 0.02``
crops to those fractions instead (the smallest piece that still names its
recipient); ``python bench/crops.py distance`` prints both configurations' MRMS
over the paper's embedding; ``python bench/crops.py sparse`` checks the birdbath's
sparse whole copies (similarity + removal to 13.9 %, seeds 0-7).
"""

from __future__ import annotations

import json
import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("POINTMARK_TEST_DATA", ROOT.parent / "shared" / "data"))
WORK = ROOT / "bench" / "results" / "crops"
MODELS = ["bunny_zipper_faceref_34834", "bunny_rangescan_bun000_40256", "nikolov_birdbath_18793",
          "nikolov_blackvase_17337"]          # every scan of at least 15,000 points but the LiDAR tile
SEEDS = range(10)
RECIPIENTS = 1000
FRACTION = 0.1
SECRET = b"fingerprint-crops-bench-secret-01"


def _reference(path, points, params):
    """The trials' handle (:func:`evaluate.prepare_bases`) and the reference it keeps, loaded and verified."""
    from pipeline.orchestrate import evaluate
    from pipeline.orchestrate.reference import load_reference

    basis = evaluate._basis_params(params, params.n_coefficients)
    handle = evaluate.prepare_bases(path, basis, WORK / "bases")
    store, key, _, digests = handle
    return handle, load_reference(points, basis, store, key, json.loads(digests))


def _mrms(ref, points, params, material):
    """MRMS (fraction of the diagonal) of one fingerprinted copy, and the share of points in a cluster."""
    from pipeline.kernels import fingerprint
    from pipeline.watermark import distortion, fingerprint_displacement, fingerprint_length

    length = fingerprint_length(len(ref.specs), params)
    chips = fingerprint.signs(fingerprint.chip_bank(material, "mrms", ["r"], length)[0], length)[0]
    centred = points - ref.centre
    moved = centred.copy()
    for spec, d in zip(ref.specs, fingerprint_displacement(ref, chips, params, centred)):
        moved[spec.members] += d
    covered = len(np.unique(np.concatenate([s.members for s in ref.specs]))) / len(points)
    return distortion(centred, moved)["mrms_rel_diag"], covered


def _configs(path, points, default, material, names=("seeds", "cover")):
    """{name: (params, handle, beta, mrms, covered)}: clusters grown from seeds, and the default covering ones.

    The default's clusters cover the asset at alpha * sqrt(n_clusters / clusters planned)
    (``cover_amplitude: paper``): the seeds embedding's distance to the surface.  ``beta`` is the
    ratio each cluster is marked at (the configured one times :func:`watermark.budget_share`).
    """
    from pipeline.watermark import band_for, budget_share

    out = {}
    for name, params in (("seeds", replace(default, cover=False)), ("cover", default)):
        if name not in names:
            continue
        params = band_for(params, points)                 # the asset's band, as a catalogue run marks it
        handle, ref = _reference(path, points, params)
        beta = params.beta * budget_share(params, len(ref.specs))
        out[name] = (params, handle, beta, *_mrms(ref, points, params, material))
    return out


DISTANCE_MODELS = [*MODELS, "kitten_12623", "nikolov_owl_12442", "pcl_tum_rabbit_10429"]


def distance(copies=3):
    """MRMS of the default (covering) and of clusters from seeds over the paper's embedding.

    The paper's: beta 0.002 in x, y and z, 5 clusters from seeds, consecutive chips; the mean over
    ``copies`` recipients' copies, on every scan of at least 10,000 points but the LiDAR tiles.
    """
    from pipeline import config
    from pipeline.io.pointcloud import read_points
    from pipeline.kernels import keys
    from pipeline.watermark import band_for

    default = config.watermark_params(config.load_config(None))
    paper = replace(default, cover=False, beta=0.002, displacement="xyz", chip_layout="consecutive",
                    code="repetition", band_noise=None)
    materials = [keys.derive_key_material(SECRET, f"distance-{i}") for i in range(copies)]
    for model in DISTANCE_MODELS:
        path = DATA / "models" / f"{model}.ply"
        points = read_points(path).points
        mean = {}
        for name, params in (("paper", paper), ("seeds", replace(default, cover=False)), ("cover", default)):
            params = band_for(params, points)
            _, ref = _reference(path, points, params)
            mean[name] = (np.mean([_mrms(ref, points, params, m)[0] for m in materials]), len(ref.specs))
        print(f"{model}: MRMS over the paper's, covering {mean['cover'][0] / mean['paper'][0]:.3f} "
              f"({mean['cover'][1]} clusters), seeds {mean['seeds'][0] / mean['paper'][0]:.3f}", flush=True)


def crops_bench(fractions=(FRACTION,), names=("seeds", "cover")):
    from pipeline import config
    from pipeline.io.pointcloud import read_points
    from pipeline.kernels import keys
    from pipeline.orchestrate import evaluate

    WORK.mkdir(parents=True, exist_ok=True)
    rows_path = WORK / "rows.jsonl"
    done = {(r["model"], r["config"], _fraction(r), r["seed"]) for r in map(json.loads, rows_path.open())} \
        if rows_path.exists() else set()
    cfg = config.load_config(None)
    default, detect = config.watermark_params(cfg), config.detect_params(cfg)
    material = keys.derive_key_material(SECRET, "crops")
    for model in MODELS:
        path = DATA / "models" / f"{model}.ply"
        points = read_points(path).points
        for name, (params, handle, beta, mrms, covered) in _configs(path, points, default, material, names).items():
            print(f"{model} {name}: beta {beta:.6f}, MRMS {100 * mrms:.4f} % of the diagonal, "
                  f"{100 * covered:.0f} % of the points in a cluster", flush=True)
            for fraction in fractions:
                for seed in SEEDS:
                    if (model, name, fraction, seed) in done:
                        continue
                    row = evaluate.fingerprint_trial(path, handle, params, detect,
                                                     f"crop:{fraction}+random_similarity", "single", seed,
                                                     material, RECIPIENTS)
                    row.update(config=name, beta=beta, mrms_rel_diag=mrms, covered=covered,
                               fraction=fraction)
                    with rows_path.open("a") as f:
                        f.write(json.dumps(row) + "\n")
                    print(f"  crop {fraction}, seed {seed}: leaker score {row['min_colluder_score']:.2f} "
                          f"(threshold {row['threshold']:.2f}, {row['n_poses']} poses read), "
                          f"innocents accused {row['accused_innocents']}, "
                          f"{row['seconds_detect']:.0f} s", flush=True)
    summary()


def sparse(model="nikolov_birdbath_18793", seeds=range(8), chain="similarity+removal:0.139"):
    """A near solid of revolution's sparse whole copies, default configuration: one line per seed."""
    from pipeline import config
    from pipeline.io.pointcloud import read_points
    from pipeline.kernels import keys
    from pipeline.orchestrate import evaluate

    cfg = config.load_config(None)
    params, detect = config.watermark_params(cfg), config.detect_params(cfg)
    path = DATA / "models" / f"{model}.ply"
    handle, _ = _reference(path, read_points(path).points, params)
    material = keys.derive_key_material(SECRET, "crops")
    for seed in seeds:
        row = evaluate.fingerprint_trial(path, handle, params, detect, chain, "single", seed, material, RECIPIENTS)
        print(f"{model} {chain} seed {seed}: leaker score {row['min_colluder_score']:.2f} (threshold "
              f"{row['threshold']:.2f}, {row['n_poses']} poses read), best innocent {row['max_innocent_score']:.2f}, "
              f"innocents accused {row['accused_innocents']}, {row['seconds_detect']:.0f} s", flush=True)


def _fraction(row):
    return row.get("fraction", FRACTION)       # rows written before fractions were recorded: 10 % crops


def summary():
    rows = [json.loads(line) for line in (WORK / "rows.jsonl").open()]
    lines = ["| model | config | beta | MRMS % diag | points in a cluster | crop | leaker named "
             "| leaker scores (min, median) | threshold | poses read (median) | innocents accused |",
             "|---|---|---:|---:|---:|---:|---:|---|---:|---:|---:|"]
    for model in MODELS:
        for name in ("seeds", "cover"):
            for fraction in sorted({_fraction(r) for r in rows}, reverse=True):
                sub = [r for r in rows if r["model"] == model and r["config"] == name and _fraction(r) == fraction]
                if not sub:
                    continue
                s = np.array([r["min_colluder_score"] for r in sub])
                named = sum(r["accused_colluders"] == 1 for r in sub)
                lines.append(f"| {model} | {name} | {sub[0]['beta']:.6f} | {100 * sub[0]['mrms_rel_diag']:.4f} | "
                             f"{100 * sub[0]['covered']:.0f} % | {100 * fraction:g} % | {named}/{len(sub)} | "
                             f"{s.min():.2f}, {np.median(s):.2f} | {max(r['threshold'] for r in sub):.2f} | "
                             f"{np.median([r.get('n_poses', 1) for r in sub]):g} | "
                             f"{sum(r['accused_innocents'] for r in sub)} |")
    text = "\n".join(lines)
    (WORK / "summary.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    if sys.argv[1:] == ["summary"]:
        summary()
    elif sys.argv[1:] == ["distance"]:
        distance()
    elif sys.argv[1:] == ["sparse"]:
        sparse()
    else:
        args = sys.argv[1:]
        names = tuple(a for a in args if a in ("seeds", "cover")) or ("seeds", "cover")
        crops_bench(tuple(float(a) for a in args if a not in names) or (FRACTION,), names)
