"""Robustness evaluation: models x attacks x parameter sets x methods x seeds, on Dask.

One Parquet row per trial; then a report folder (PNG plots, Markdown summary).
The trials call the engine's own embed and detect functions; the spectral
bases of a model are computed once per cluster parameters, cached as a
``.npz`` file whose path the trials receive.
"""

from __future__ import annotations

import hashlib
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from . import config as config_mod
from .io.pointcloud import atomic_write_bytes, read_points
from .kernels import keys, modulation
from .surface import apply_chain, parse_attack
from .watermark import (ClusterSpec, DetectParams, cluster_basis, decode, distortion, embed_with_bases,
                        estimate_differences, frame_of, plan_clusters)

__all__ = ["run_evaluation", "parse_chain", "trial", "prepare_bases", "load_bases"]

MESSAGE = "5ca1ab1e"
_CLUSTER_KEYS = ("valence", "n_clusters", "cluster_size", "seeds", "on_touch", "cover")


def parse_chain(text):
    """'similarity+removal:0.139' -> [('similarity', None), ('removal', 0.139)]; 'none' -> []."""
    if text in ("none", ""):
        return []
    return [parse_attack(step) for step in text.split("+")]


def method_params(method, params, detect_params):
    """(WatermarkParams, DetectParams) of an evaluation method.

    ``paper``: the paper's embedding (xyz displacement, consecutive chips),
    covariance registration and nearest-point resampling; ``robust``: the
    config as given; ``robust-xyz``: the config's detection on the paper's
    embedding.
    """
    if method == "robust":
        return params, detect_params
    paper_embedding = replace(params, displacement="xyz", chip_layout="consecutive")
    if method == "paper":
        return paper_embedding, replace(detect_params, registration="paper", correspondence="paper")
    return paper_embedding, detect_params


def prepare_bases(model_path, params, cache_path):
    """Clusters and bases of a model, saved to ``cache_path`` (.npz); returns the path."""
    cache_path = Path(cache_path)
    if cache_path.exists():
        return str(cache_path)
    points = read_points(model_path).points
    frame = frame_of(points)
    centred = points - frame.centre
    specs = plan_clusters(centred, params)
    arrays = {"centre": frame.centre, "phi": np.array(frame.phi)}
    for s in specs:
        arrays[f"members_{s.index}"] = s.members
        arrays[f"seed_{s.index}"] = np.array(s.seed_index)
        arrays[f"basis_{s.index}"] = cluster_basis(centred[s.members], params)[1]
    import io

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(cache_path, buf.getvalue())
    return str(cache_path)


def load_bases(cache_path, n_coefficients):
    """Frame and clusters saved by ``prepare_bases``: (centre (3,), phi, specs, bases (n_c, K))."""
    data = np.load(cache_path)
    n = len([k for k in data.files if k.startswith("members_")])
    specs = [ClusterSpec(i, int(data[f"seed_{i}"]), 0, data[f"members_{i}"]) for i in range(n)]
    bases = [data[f"basis_{i}"][:, :n_coefficients] for i in range(n)]
    return data["centre"], float(data["phi"]), specs, bases


def _message_bits(params):
    digits = (params.n_bits + 3) // 4
    value = int(MESSAGE, 16) & ((1 << params.n_bits) - 1)
    return modulation.hex_to_bits(format(value, f"0{digits}x"), params.n_bits)


def trial(model_path, cache_path, params, detect_params, chain_text, method, seed, material):
    """Embed, attack, detect once; one result row.  ``simplify`` uses the model's own faces."""
    t0 = time.perf_counter()
    cloud = read_points(model_path)
    points = cloud.points
    centre, phi, specs, bases = load_bases(cache_path, params.n_coefficients)
    bits = _message_bits(params)
    params, dparams = method_params(method, params, detect_params)
    marked = embed_with_bases(points - centre, specs, bases, material, bits, params, phi) + centre
    t1 = time.perf_counter()
    chain = parse_chain(chain_text)
    attacked = apply_chain(marked, chain + [("shuffle", None)], rng=seed, faces=cloud.faces())
    t2 = time.perf_counter()
    estimate = estimate_differences(attacked - centre, points - centre, specs, bases, dparams,
                                    params.displacement)
    result = decode(estimate, specs, material, params, dparams)
    errors = int((np.asarray(result["bits"]) != bits).sum())
    dist = distortion(points, marked)
    return {
        "model": Path(model_path).stem, "attack": chain_text, "strength": _strength(chain),
        "method": method, "seed": int(seed), "beta": params.beta, "chip_rate": params.chip_rate,
        "n_bits": params.n_bits, "n_clusters": len(specs), "n_suspect": int(len(attacked)),
        "bit_errors": errors, "ber": errors / params.n_bits, "detected": result["detected"],
        "p_value": result["p_value"], "min_abs_score": float(np.min(np.abs(result["bit_scores"]))),
        "registration_fitness": result["registration"]["fitness"],
        "displacement": params.displacement, "rmse_rel_diag": dist["rmse_rel_diag"],
        "hausdorff_rel_diag": dist["hausdorff_rel_diag"], "surface_rmse_rel_diag": dist["surface_rmse_rel_diag"],
        "seconds_embed": t1 - t0, "seconds_attack": t2 - t1, "seconds_detect": time.perf_counter() - t2,
    }


def _strength(chain):
    values = [s for _, s in chain if s is not None]
    return float(values[-1]) if values else float("nan")


def false_positives(model_path, cache_path, params, detect_params, material, n_keys, marked_too=True):
    """p-values of wrong keys on the unmarked original and on a marked copy.

    The coefficient differences do not depend on the key, so they are
    estimated once per suspect and decoded with every wrong key.
    """
    points = read_points(model_path).points
    centre, phi, specs, bases = load_bases(cache_path, params.n_coefficients)
    bits = _message_bits(params)
    suspects = {"unmarked original": points}
    if marked_too:
        suspects["marked with another key"] = embed_with_bases(points - centre, specs, bases, material, bits,
                                                               params, phi) + centre
    rows = []
    for label, suspect in suspects.items():
        estimate = estimate_differences(suspect - centre, points - centre, specs, bases, detect_params,
                                        params.displacement)
        for k in range(n_keys):
            wrong = keys.derive_key_material(b"evaluation-wrong-keys", f"wrong-{k}")
            res = decode(estimate, specs, wrong, params, detect_params)
            rows.append({"model": Path(model_path).stem, "suspect": label, "key": k, "p_value": res["p_value"]})
        if label == "unmarked original":
            res = decode(estimate, specs, material, params, detect_params)
            rows.append({"model": Path(model_path).stem, "suspect": "unmarked original, right key",
                         "key": -1, "p_value": res["p_value"]})
    return rows


def _cache_name(model_path, params, n_coefficients):
    text = json.dumps({"m": str(model_path), **{k: getattr(params, k) for k in _CLUSTER_KEYS},
                       "k": n_coefficients}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16] + ".npz"


def plan_trials(cfg):
    """Expand the experiments into (experiment, model, params, chain, method, seed) tuples."""
    ev = cfg["evaluate"]
    base = config_mod.watermark_params(cfg)
    out = []
    for exp in ev["experiments"]:
        reps = exp.get("repetitions", ev["repetitions"])
        for model in exp["models"]:
            for overrides in exp.get("parameters") or [{}]:
                params = replace(base, **overrides)
                for chain in exp["attacks"]:
                    parse_chain(chain)  # fail early on a typo
                    for method in exp.get("methods") or ev["methods"]:
                        for rep in range(reps):
                            out.append((exp["name"], model, params, chain, method, 1000 * rep + 17))
    return out


def run_evaluation(cfg, secret):
    """``pointmark evaluate``: run the grid, write results.parquet, plots and summary.md."""
    from distributed import as_completed

    from .orchestrate.run import start_client
    from .report import write_report

    ev = cfg["evaluate"]
    out = Path(ev["out"])
    cache = out / "bases"
    cache.mkdir(parents=True, exist_ok=True)
    material = keys.derive_key_material(secret, cfg["key"]["id"] or "evaluation")
    detect_params = config_mod.detect_params(cfg)
    trials = plan_trials(cfg)
    need = {}
    for _, model, params, *_ in trials:
        name = _cache_name(model, params, 0)
        need[name] = max(need.get(name, (0, model, params))[0], params.n_coefficients), model, params
    t0 = time.perf_counter()
    client, cluster = start_client(cfg)
    try:
        prep = {name: client.submit(prepare_bases, src, replace(params, chip_rate=1, n_bits=k, crc_bits=0,
                                                                first_coefficient=0),
                                    str(cache / name), pure=False)
                for name, (k, src, params) in need.items()}
        futures = {}
        for exp, model, params, chain, method, seed in trials:
            fut = client.submit(trial, model, prep[_cache_name(model, params, 0)], params, detect_params,
                                chain, method, seed, material, pure=False)
            futures[fut] = exp
        fp_futures = []
        if ev["false_positive_keys"]:
            seen = set()
            for _, model, params, *_ in trials:
                if model not in seen and "/meshes/" not in model:
                    seen.add(model)
                    fp_futures.append(client.submit(false_positives, model, prep[_cache_name(model, params, 0)],
                                                    params, detect_params, material, ev["false_positive_keys"],
                                                    pure=False))
        rows, done = [], 0
        for fut in as_completed(list(futures)):
            row = fut.result()
            row["experiment"] = futures[fut]
            rows.append(row)
            done += 1
            if done % 25 == 0 or done == len(futures):
                print(f"[pointmark] evaluate: {done}/{len(futures)} trials, "
                      f"{time.perf_counter() - t0:.0f}s", file=sys.stderr, flush=True)
        fp_rows = [r for f in fp_futures for r in f.result()]
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    _write_table(out / "results.parquet", rows)
    _write_table(out / "false_positives.parquet", fp_rows)
    write_report(out, rows, fp_rows, detect_params.p_threshold, time.perf_counter() - t0)
    print(f"wrote {out / 'results.parquet'} ({len(rows)} trials), {out / 'summary.md'} and plots "
          f"in {time.perf_counter() - t0:.0f}s")
    return 0


def _write_table(path, rows):
    import io

    buf = io.BytesIO()
    pq.write_table(pa.Table.from_pylist(rows), buf)
    atomic_write_bytes(path, buf.getvalue())
