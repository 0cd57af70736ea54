"""Robustness evaluation: models x attacks x parameter sets x methods x seeds, on Dask.

One Parquet row per trial; then a report folder (PNG plots, Markdown summary).
The trials call the engine's own embed and detect functions; the spectral
bases of a model are computed once per cluster parameters, cached as a
``.npz`` file whose path the trials receive.
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .. import config as config_mod
from ..io.pointcloud import atomic_write_bytes, read_points, units_of
from ..kernels import fingerprint, keys, modulation
from ..surface import apply_chain, parse_attack
from ..watermark import (band_applies, band_for, decode_poses, distortion, embed_with_bases, estimate_differences,
                         fingerprint_displacement, fingerprint_length, fingerprint_observations)
from .reference import build_reference, load_reference

__all__ = ["run_evaluation", "parse_chain", "trial", "prepare_bases", "load_bases", "fingerprint_trial",
           "parse_case"]

MESSAGE = "5ca1ab1e"
_CLUSTER_KEYS = ("valence", "n_clusters", "cluster_size", "seeds", "on_touch", "cover")


def parse_chain(text):
    """'similarity+removal:0.139' -> [('similarity', None), ('removal', 0.139)]; 'none' -> []."""
    if text in ("none", ""):
        return []
    return [parse_attack(step) for step in text.split("+")]


def method_params(method, params, detect_params):
    """(WatermarkParams, DetectParams) of an evaluation method.

    ``paper``: the paper's embedding (xyz displacement, consecutive chips, repetition),
    covariance registration and nearest-point resampling; ``robust``: the
    config as given; ``robust-xyz``: the config's detection on the paper's
    embedding.
    """
    if method == "robust":
        return params, detect_params
    paper_embedding = replace(params, displacement="xyz", chip_layout="consecutive", amplitude="model",
                              max_displacement=None, code="repetition")
    if method == "paper":
        return paper_embedding, replace(detect_params, registration="paper", correspondence="paper")
    return paper_embedding, detect_params


def _basis_params(params, n_coefficients):
    """Parameters whose reference holds ``n_coefficients`` vectors (one basis serves every c and m)."""
    return replace(params, chip_rate=1, n_bits=n_coefficients, crc_bits=0, first_coefficient=0, code="repetition")


def prepare_bases(model_path, params, store):
    """Clusters and bases of a model built into the basis store.

    Returns
    -------
    tuple
        The handle: (store folder, entry key, basis parameters' coefficient
        count, digests JSON), which :func:`load_bases` and the trials verify.
    """
    from ..io.basis_store import BasisStore
    from ..io.pointcloud import sha256_file

    key = BasisStore(store).key(sha256_file(model_path), params)
    ref = build_reference(read_points(model_path).points, params, store, key, detection=True)
    return str(store), key, int(params.n_coefficients), json.dumps(ref.digests(), sort_keys=True)


def load_bases(handle, points, params):
    """Frame and clusters of :func:`prepare_bases`: (centre (3,), phi, specs, bases (n_c, K)), verified."""
    ref = _stored_reference(tuple(handle), points, params)
    return ref.centre, ref.phi, ref.specs, ref.bases


def _message_bits(params):
    digits = (params.n_bits + 3) // 4
    value = int(MESSAGE, 16) & ((1 << params.n_bits) - 1)
    return modulation.hex_to_bits(format(value, f"0{digits}x"), params.n_bits)


def trial(model_path, cache_path, params, detect_params, chain_text, method, seed, material):
    """Embed, attack, detect once; one result row.  ``simplify`` uses the model's own faces."""
    t0 = time.perf_counter()
    cloud = read_points(model_path)
    points = cloud.points
    ref = _stored_reference(tuple(cache_path), points, params)
    centre, phi, specs, bases = ref.centre, ref.phi, ref.specs, ref.bases
    bits = _message_bits(params)
    params, dparams = method_params(method, params, detect_params)
    marked = embed_with_bases(points - centre, specs, bases, material, bits, params, phi) + centre
    t1 = time.perf_counter()
    chain = parse_chain(chain_text)
    attacked = apply_chain(marked, chain + [("shuffle", None)], rng=seed, faces=cloud.faces())
    t2 = time.perf_counter()
    estimate = estimate_differences(attacked - centre, points - centre, specs, bases, dparams,
                                    params, every_pose=True, **ref.detection_aids())
    result = decode_poses(estimate, specs, material, params, dparams)
    errors = int((np.asarray(result["bits"]) != bits).sum())
    dist = _distortion_of(points, marked, (str(model_path), tuple(cache_path), params, material))
    return {
        "model": Path(model_path).stem, "attack": chain_text, "strength": _strength(chain),
        "method": method, "seed": int(seed), "beta": params.beta, "chip_rate": params.chip_rate,
        "n_bits": params.n_bits, "n_clusters": len(specs), "n_suspect": int(len(attacked)),
        "bit_errors": errors, "ber": errors / params.n_bits, "detected": result["detected"],
        "p_value": result["p_value"], "min_abs_score": float(np.min(np.abs(result["bit_scores"]))),
        "registration_fitness": result["registration"]["fitness"],
        "displacement": params.displacement,
        **dist, "code": params.code, "chip_layout": params.chip_layout,
        "message_error": bool(errors > 0),
        "seconds_embed": t1 - t0, "seconds_attack": t2 - t1, "seconds_detect": time.perf_counter() - t2,
    }


_DISTORTIONS = {}


def _distortion_of(points, marked, key):
    """Distortion of a marked copy, once per worker: every attack and seed of a cell shares the copy.

    ``key`` (model, handle, embedding parameters, key material) decides the copy.
    """
    if key not in _DISTORTIONS:
        if len(_DISTORTIONS) >= 64:
            _DISTORTIONS.clear()
        _DISTORTIONS[key] = distortion(points, marked)
    return _DISTORTIONS[key]


def _stored_reference(handle, points, params):
    """The Reference of a prepared handle, verified, bases cut to ``params``' coefficients, with detection aids.

    Cached per worker process by the handle (whose entry key is a hash of the
    model's bytes and the cluster parameters) and the parameters: the trials
    of one model share it.
    """
    key = (handle, params)
    if key not in _REFERENCES:
        if len(_REFERENCES) >= 16:
            _REFERENCES.clear()
        store, entry, basis_k, digests = handle
        whole = load_reference(points, _basis_params(params, basis_k), store, entry, json.loads(digests),
                               source="the evaluation's prepared bases", detection=True)
        _REFERENCES[key] = whole.cut(params.n_coefficients)
    return _REFERENCES[key]


_REFERENCES = {}


def parse_case(text):
    """'single' -> ('average', 1); 'average:3'; 'interleave:2'; 'unmarked' and 'other-key' -> 0 colluders."""
    kind, _, count = text.partition(":")
    if kind == "single":
        return "average", 1
    if kind in ("unmarked", "other-key"):
        return kind, 0
    if kind not in ("average", "interleave") or not count.isdigit() or int(count) < 1:
        raise ValueError(f"collusion case {text!r}: use single, average:K, interleave:K, unmarked or other-key")
    return kind, int(count)


def fingerprint_trial(model_path, handle, params, detect_params, chain_text, case, seed, material, n_recipients):
    """Issue fingerprinted copies, let colluders combine them, attack, attribute; one row.

    The suspect is the average of the colluders' copies (``average:K``), or
    each point taken from one colluder's copy at random (``interleave:K``),
    then the attack chain, then a shuffle.  ``unmarked`` checks the original
    and ``other-key`` a copy under another key: every recipient is innocent.
    """
    t0 = time.perf_counter()
    cloud = read_points(model_path)
    points = cloud.points
    ref = _stored_reference(tuple(handle), points, params)
    kind, k = parse_case(case)
    rng = np.random.default_rng(seed)
    names = [f"recipient-{i:05d}" for i in range(n_recipients)]
    length = fingerprint_length(len(ref.specs), params)
    label = f"{Path(model_path).stem}/g1"
    bank = fingerprint.chip_bank(material, label, names, length)
    colluders = np.sort(rng.choice(n_recipients, size=k, replace=False)) if k else np.zeros(0, dtype=int)
    centred = points - ref.centre

    def copy(chips):
        moved = centred.copy()
        for spec, d in zip(ref.specs, fingerprint_displacement(ref, chips, params, centred)):
            moved[spec.members] += d
        return moved

    if kind == "unmarked":
        suspect = centred
    elif kind == "other-key":
        other = fingerprint.chip_bank(keys.derive_key_material(b"evaluation-other-key-0001", "other"), label,
                                      names[:1], length)
        suspect = copy(fingerprint.signs(other, length)[0])
    else:
        copies = np.stack([copy(fingerprint.signs(bank[j], length)[0]) for j in colluders])
        suspect = copies.mean(axis=0) if kind == "average" else copies[rng.integers(k, size=len(points)),
                                                                         np.arange(len(points))]
    # the distance to the surface of one recipient's copy (copies differ only in their chips)
    dist = _distortion_of(centred, copy(fingerprint.signs(bank[0], length)[0]),
                          ("fingerprint", str(model_path), tuple(handle), params, material))
    t1 = time.perf_counter()
    attacked = apply_chain(suspect + ref.centre, parse_chain(chain_text) + [("shuffle", None)], rng=seed,
                           faces=cloud.faces())
    est = estimate_differences(attacked - ref.centre, centred, ref.specs, ref.bases, detect_params,
                               params, every_pose=True, **ref.detection_aids())
    s, _, table = fingerprint.scores_over_poses(fingerprint_observations(est, ref.specs, params), bank)
    n_checked = n_recipients * len(table)      # every pose read tests every recipient
    accused, _ = fingerprint.accuse(s, n_checked, detect_params.epsilon)
    innocent = np.setdiff1d(np.arange(n_recipients), colluders)
    guilty = set(colluders.tolist())
    return {
        "model": Path(model_path).stem, "case": case, "colluders": int(k), "attack": chain_text, "seed": int(seed),
        "n_recipients": n_recipients, "epsilon": detect_params.epsilon, "beta": params.beta,
        "mrms_rel_diag": dist["mrms_rel_diag"], "msdm": dist["msdm"],
        "threshold": fingerprint.threshold(n_checked, detect_params.epsilon), "n_poses": len(table),
        "accused_colluders": int(sum(a in guilty for a in accused.tolist())),
        "accused_innocents": int(sum(a not in guilty for a in accused.tolist())),
        "min_colluder_score": float(s[colluders].min()) if k else float("nan"),
        "max_innocent_score": float(s[innocent].max()),
        "innocent_checks": int(len(innocent)),
        **{f"innocents_over_{t}": int((s[innocent] >= t).sum()) for t in (2, 3, 4)},
        "registration_fitness": est["registration"]["fitness"], "n_suspect": int(len(attacked)),
        "seconds_copies": t1 - t0, "seconds_detect": time.perf_counter() - t1,
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
    ref = _stored_reference(tuple(cache_path), points, params)
    centre, phi, specs, bases = ref.centre, ref.phi, ref.specs, ref.bases
    bits = _message_bits(params)
    suspects = {"unmarked original": points}
    if marked_too:
        suspects["marked with another key"] = embed_with_bases(points - centre, specs, bases, material, bits,
                                                               params, phi) + centre
    rows = []
    for label, suspect in suspects.items():
        estimate = estimate_differences(suspect - centre, points - centre, specs, bases, detect_params,
                                        params, every_pose=True, **ref.detection_aids())
        for k in range(n_keys):
            wrong = keys.derive_key_material(b"evaluation-wrong-keys", f"wrong-{k}")
            res = decode_poses(estimate, specs, wrong, params, detect_params)
            rows.append({"model": Path(model_path).stem, "suspect": label, "key": k, "p_value": res["p_value"]})
        if label == "unmarked original":
            res = decode_poses(estimate, specs, material, params, detect_params)
            rows.append({"model": Path(model_path).stem, "suspect": "unmarked original, right key",
                         "key": -1, "p_value": res["p_value"]})
    return rows


def _prep_key(model, params):
    return json.dumps({"m": str(model), **{k: getattr(params, k) for k in _CLUSTER_KEYS}}, sort_keys=True,
                      default=str)


def _cells(cfg, collusion):
    """(experiment, model, params, chain, repetitions) of the message or of the fingerprint experiments."""
    ev = cfg["evaluate"]
    originals = {}
    for exp in ev["experiments"]:
        if bool(exp.get("collusion")) != collusion:
            continue
        for model in exp["models"]:
            for overrides in exp.get("parameters") or [{}]:
                params = config_mod.watermark_params({"watermark": {**cfg["watermark"], **overrides}},
                                                     units_of(model))    # survey data: the rule embed uses
                if band_applies(params) and model not in originals:
                    originals[model] = read_points(model).points
                params = band_for(params, originals.get(model))     # the band follows the model's sampling
                try:                    # fail before any work, not in every trial
                    config_mod.check_code(params)
                except ValueError as exc:
                    raise config_mod.ConfigError(f"evaluate.experiments {exp['name']}: {exc}") from None
                for chain in exp["attacks"]:
                    parse_chain(chain)  # fail early on a typo
                    yield exp, model, params, chain, exp.get("repetitions", ev["repetitions"])


def plan_trials(cfg):
    """Expand the message experiments into (experiment, model, params, chain, method, seed) tuples."""
    return [(exp["name"], model, params, chain, method, 1000 * rep + 17)
            for exp, model, params, chain, reps in _cells(cfg, collusion=False)
            for method in exp.get("methods") or cfg["evaluate"]["methods"] for rep in range(reps)]


def plan_fingerprint_trials(cfg):
    """Experiments with a ``collusion`` list: (experiment, model, params, chain, case, seed, recipients)."""
    return [(exp["name"], model, params, chain, case, 1000 * rep + 29, exp.get("recipients", 1000))
            for exp, model, params, chain, reps in _cells(cfg, collusion=True)
            for case in exp["collusion"] if parse_case(case) for rep in range(reps)]


def run_evaluation(cfg, secret):
    """``pointmark evaluate``: run the grid, write results.parquet, plots and summary.md."""
    from distributed import as_completed

    from .run import start_client
    from ..report import write_report

    ev = cfg["evaluate"]
    out = Path(ev["out"])
    cache = Path(cfg["output"]["bases"] or out / "bases")
    cache.mkdir(parents=True, exist_ok=True)
    material = keys.derive_key_material(secret, cfg["key"]["id"] or "evaluation")
    detect_params = config_mod.detect_params(cfg)
    trials = plan_trials(cfg)
    fp_trials = plan_fingerprint_trials(cfg)
    need = {}
    for _, model, params, *_ in trials + fp_trials:
        name = _prep_key(model, params)
        need[name] = max(need.get(name, (0, model, params))[0], params.n_coefficients), model, params
    t0 = time.perf_counter()
    client, cluster = start_client(cfg)
    try:
        # absolute paths: a worker of an existing cluster has its own working directory
        prep = {name: client.submit(prepare_bases, os.path.abspath(src), _basis_params(params, k),
                                    os.path.abspath(cache), pure=False)
                for name, (k, src, params) in need.items()}
        futures = {}
        for exp, model, params, chain, method, seed in trials:
            fut = client.submit(trial, os.path.abspath(model), prep[_prep_key(model, params)], params, detect_params,
                                chain, method, seed, material, pure=False)
            futures[fut] = exp
        for exp, model, params, chain, case, seed, n_recipients in fp_trials:
            fut = client.submit(fingerprint_trial, os.path.abspath(model), prep[_prep_key(model, params)], params,
                                detect_params, chain, case, seed, material, n_recipients, pure=False)
            futures[fut] = exp
        fp_futures = []
        if ev["false_positive_keys"]:
            seen = set()
            for _, model, params, *_ in trials:
                if model not in seen and "/meshes/" not in model:
                    seen.add(model)
                    fp_futures.append(client.submit(false_positives, os.path.abspath(model),
                                                    prep[_prep_key(model, params)], params, detect_params,
                                                    material, ev["false_positive_keys"], pure=False))
        rows, fingerprint_rows, errors, done, total = [], [], [], 0, len(futures)
        for fut in as_completed(list(futures)):
            exp = futures.pop(fut)          # released: a lost worker does not recompute collected trials
            if fut.status != "finished":    # a crashed trial (e.g. a native library fault) is reported, not fatal
                errors.append(f"{exp}: {type(fut.exception()).__name__}: {fut.exception()}")
                print(f"[pointmark] evaluate: trial failed: {errors[-1]}", file=sys.stderr, flush=True)
                continue
            row = fut.result()
            row["experiment"] = exp
            (fingerprint_rows if "case" in row else rows).append(row)
            done += 1
            if done % 25 == 0 or done == total:       # (futures shrinks as trials are collected)
                print(f"[pointmark] evaluate: {done}/{total} trials, "
                      f"{time.perf_counter() - t0:.0f}s", file=sys.stderr, flush=True)
        fp_rows = [r for f in fp_futures for r in f.result()]
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    _write_table(out / "results.parquet", rows)
    _write_table(out / "false_positives.parquet", fp_rows)
    _write_table(out / "fingerprints.parquet", fingerprint_rows)
    write_report(out, rows, fp_rows, detect_params.p_threshold, time.perf_counter() - t0, fingerprint_rows)
    print(f"wrote {out / 'results.parquet'} ({len(rows)} trials), {out / 'fingerprints.parquet'} "
          f"({len(fingerprint_rows)} trials), {out / 'summary.md'} and plots in {time.perf_counter() - t0:.0f}s"
          + (f"; {len(errors)} trials failed" if errors else ""))
    return 1 if errors else 0


def _write_table(path, rows):
    import io

    buf = io.BytesIO()
    pq.write_table(pa.Table.from_pylist(rows), buf)
    atomic_write_bytes(path, buf.getvalue())
