"""Leak-detection scans: which asset, and which recipient, a suspect file came from.

Per suspect: (1) an exact sha256 match against issued outputs attributes at
once; (2) otherwise the top-K catalogue assets by D2 shape descriptor are
candidates; (3) each candidate's original is registered and the watermark
estimated once, then decoded with every key id issued for that asset, and
the decoded payload matched to the nearest issued payload.  The parameters
come from the embedding manifest rows, not from the scan config.

Exit status of ``pointmark scan``: 0 no match, 1 at least one match,
2 bad config, 3 some suspects failed to process.
"""

from __future__ import annotations

import json
import sys
import time
from collections import defaultdict
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pyarrow as pa

from . import __version__, config as config_mod
from .evaluate import _cache_name, load_bases, prepare_bases
from .io.catalog import discover_assets, read_catalogue
from .io.manifest import EMBED_SCHEMA, read_dataset, read_rows, write_rows
from .io.pointcloud import read_points, sha256_file
from .kernels import keys, modulation
from .kernels.descriptor import d2_descriptor, descriptor_distance
from .watermark import WatermarkParams, decode, estimate_differences

__all__ = ["SCAN_SCHEMA", "run_scan", "params_from_row"]

SCAN_SCHEMA = pa.schema([
    ("schema_version", pa.int16()),
    ("suspect_path", pa.string()),
    ("suspect_sha256", pa.string()),
    ("n_points", pa.int64()),
    ("candidate_asset", pa.string()),
    ("candidate_rank", pa.int32()),
    ("descriptor_distance", pa.float64()),
    ("best", pa.bool_()),
    ("key_id", pa.string()),
    ("registration_fitness", pa.float64()),
    ("registration_residual_rel_diag", pa.float64()),
    ("registration_scale", pa.float64()),
    ("decoded_payload", pa.string()),
    ("recipient", pa.string()),
    ("issued_payload", pa.string()),
    ("bit_errors", pa.int32()),
    ("score", pa.float64()),
    ("p_value", pa.float64()),
    ("p_value_payload", pa.float64()),
    ("verdict", pa.string()),
    ("seconds_candidates", pa.float64()),
    ("seconds_registration", pa.float64()),
    ("seconds_detection", pa.float64()),
    ("status", pa.string()),
    ("error", pa.string()),
    ("tool_version", pa.string()),
    ("scanned_at", pa.timestamp("ms", tz="UTC")),
])

_PARAM_FIELDS = ("n_bits", "chip_rate", "beta", "valence", "n_clusters", "cluster_size", "on_touch",
                 "cover", "chip_layout", "first_coefficient", "crc_bits")


def params_from_row(row):
    """WatermarkParams as recorded in an embedding manifest row."""
    seeds = json.loads(row["seeds_json"]) if row.get("seeds_json") else None
    seeds = None if seeds is None else tuple(tuple(s) if isinstance(s, list) else s for s in seeds)
    # manifests written before the normal-direction option hold the paper's xyz
    displacement = row.get("displacement") or "xyz"
    return WatermarkParams(**{k: row[k] for k in _PARAM_FIELDS}, seeds=seeds, displacement=displacement)


def triage(suspect_path, descriptors, issued_by_sha, top_k):
    """Read a suspect, look for an exact copy, rank candidate assets by descriptor."""
    t0 = time.perf_counter()
    points = read_points(suspect_path).points
    sha = sha256_file(suspect_path)
    exact = issued_by_sha.get(sha)
    keys_ = list(descriptors)
    dist = descriptor_distance(d2_descriptor(points - points.mean(axis=0)),
                               np.array([descriptors[k] for k in keys_]))
    order = np.argsort(np.atleast_1d(dist), kind="stable")[:top_k]
    candidates = [(keys_[i], float(np.atleast_1d(dist)[i])) for i in order]
    return {"path": str(suspect_path), "sha256": sha, "n_points": len(points), "exact": exact,
            "candidates": candidates, "seconds": time.perf_counter() - t0}


def check_candidate(suspect_path, original_path, cache_path, issued, materials, detect_params, max_bit_errors):
    """Detect against one candidate original for every key id issued for it; best row."""
    params = params_from_row(issued[0])
    suspect = read_points(suspect_path).points
    original = read_points(original_path).points
    centre, _, specs, bases = load_bases(cache_path, params.n_coefficients)
    estimate = estimate_differences(suspect - centre, original - centre, specs, bases, detect_params,
                                    params.displacement)
    t0 = time.perf_counter()
    best = None
    for key_id in sorted({r["key_id"] for r in issued}):
        result = decode(estimate, specs, materials[key_id], params, detect_params)
        z = np.asarray(result["bit_scores"])
        for row in (r for r in issued if r["key_id"] == key_id):
            want = modulation.hex_to_bits(row["payload"], params.n_bits)
            errors = int((np.asarray(result["bits"]) != want).sum())
            cand = {"key_id": key_id, "decoded_payload": result["message"], "p_value": result["p_value"],
                    "p_value_payload": modulation.p_value_payload(z, want), "bit_errors": errors,
                    "issued_payload": row["payload"], "recipient": row["recipient"],
                    "score": float(z @ (2.0 * want - 1.0) / np.sqrt(len(z)))}
            if best is None or (cand["bit_errors"], cand["p_value"]) < (best["bit_errors"], best["p_value"]):
                best = cand
    reg = estimate["registration"]
    present = best["p_value"] < detect_params.p_threshold
    if present and best["bit_errors"] <= max_bit_errors:
        verdict = "match"
    elif present or best["p_value_payload"] < detect_params.p_threshold:
        verdict = "inconclusive"
    else:
        verdict = "no match"
    if verdict != "match":
        best["recipient"] = None
    return {**best, "verdict": verdict, "registration_fitness": reg["fitness"],
            "registration_residual_rel_diag": reg["residual_rel_diag"], "registration_scale": reg["scale"],
            "seconds_registration": estimate["seconds_registration"],
            "seconds_detection": estimate["seconds_estimate"] + time.perf_counter() - t0}


def _load_reference(cfg):
    sc = cfg["scan"]
    for name in ("suspects", "catalogue"):
        if not sc[name]:
            raise config_mod.ConfigError(f"config: scan.{name}: required for a scan")
    catalogue = [r for r in read_catalogue(sc["catalogue"]) if r["status"] == "ok"]
    base = Path(sc["catalogue"]).resolve().parent
    originals = {r["asset_key"]: (Path(r["path"]) if Path(r["path"]).is_absolute() else base / r["path"])
                 for r in catalogue}
    descriptors = {r["asset_key"]: r["descriptor"] for r in catalogue}
    issued = read_dataset(sc["manifests"] or cfg["output"]["manifests"], EMBED_SCHEMA).to_pylist()
    issued = [r for r in issued if r["status"] == "ok"]
    by_asset = defaultdict(list)
    for r in issued:
        by_asset[r["asset_key"]].append(r)
    by_sha = {r["output_sha256"]: r for r in issued}
    return originals, descriptors, by_asset, by_sha


def _out_path(folder, sha):
    return Path(folder) / f"{sha[:32]}.parquet"


def run_scan(cfg, secret, *, force=False):
    """``pointmark scan``: returns the exit status."""
    from distributed import as_completed

    from .orchestrate.run import start_client

    sc = cfg["scan"]
    originals, descriptors, by_asset, by_sha = _load_reference(cfg)
    fingerprint = keys.fingerprint(secret)
    key_ids = {r["key_id"] for rows in by_asset.values() for r in rows if r["key_fingerprint"] == fingerprint}
    materials = {k: keys.derive_key_material(secret, k) for k in key_ids}
    suspects = [a.path for a in discover_assets(sc["suspects"])]
    detect_params = config_mod.detect_params(cfg)
    out = Path(sc["out"])
    cache = out / "bases"
    cache.mkdir(parents=True, exist_ok=True)
    done_shas = {p.stem for p in out.glob("*.parquet")} if not force else set()
    t0 = time.perf_counter()
    client, cluster = start_client(cfg)
    counts = {"match": 0, "no match": 0, "inconclusive": 0, "failed": 0, "skipped": 0}
    try:
        triages = {client.submit(triage, str(p), descriptors, by_sha, sc["top_k"], pure=False): p
                   for p in suspects}
        prepared = {}
        pending = as_completed(list(triages))
        waiting = {}
        for fut in pending:
            if fut in triages:
                path = triages.pop(fut)
                if fut.status != "finished":
                    _write(out, None, [_failed(path, fut.exception())])
                    counts["failed"] += 1
                    continue
                info = fut.result()
                if info["sha256"][:32] in done_shas:
                    counts["skipped"] += 1
                    continue
                if info["exact"] is not None:
                    row = info["exact"]
                    _write(out, info, [{**_base(info), "candidate_asset": row["asset_key"], "candidate_rank": 0,
                                        "best": True, "key_id": row["key_id"], "recipient": row["recipient"],
                                        "decoded_payload": row["payload"], "issued_payload": row["payload"],
                                        "bit_errors": 0, "p_value": 0.0, "verdict": "match",
                                        "status": "ok"}])
                    counts["match"] += 1
                    continue
                subs = []
                for rank, (asset, dist) in enumerate(info["candidates"]):
                    issued = [r for r in by_asset.get(asset, []) if r["key_id"] in materials]
                    if not issued:
                        continue
                    params = params_from_row(issued[0])
                    if asset not in prepared:
                        prepared[asset] = client.submit(prepare_bases, str(originals[asset]), params,
                                                        str(cache / _cache_name(originals[asset], params,
                                                                                params.n_coefficients)),
                                                        pure=False)
                    sub = client.submit(check_candidate, info["path"], str(originals[asset]), prepared[asset],
                                        issued, materials, detect_params, sc["max_bit_errors"], pure=False)
                    subs.append(sub)
                    waiting[sub] = (info, asset, rank, dist)
                    pending.add(sub)
                info["open"] = len(subs)
                info["rows"] = []
                if not subs:
                    _write(out, info, [{**_base(info), "verdict": "no match", "status": "ok"}])
                    counts["no match"] += 1
            else:
                info, asset, rank, dist = waiting.pop(fut)
                row = {**_base(info), "candidate_asset": asset, "candidate_rank": rank,
                       "descriptor_distance": dist}
                if fut.status == "finished":
                    row.update(fut.result(), status="ok")
                else:
                    row.update(status="failed", error=str(fut.exception()), verdict="no match")
                info["rows"].append(row)
                info["open"] -= 1
                if info["open"] == 0:
                    verdict = _finish(out, info)
                    counts[verdict] += 1
                    print(f"[pointmark] scan: {info['path']}: {verdict}", file=sys.stderr, flush=True)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    print(f"scanned {len(suspects)} suspects in {time.perf_counter() - t0:.0f}s: {counts['match']} match, "
          f"{counts['inconclusive']} inconclusive, {counts['no match']} no match, {counts['failed']} failed, "
          f"{counts['skipped']} already scanned; results in {out}")
    if counts["failed"]:
        return 3
    return 1 if counts["match"] else 0


def _base(info):
    return {"suspect_path": info["path"], "suspect_sha256": info["sha256"], "n_points": info["n_points"],
            "seconds_candidates": info["seconds"], "tool_version": __version__}


def _failed(path, exc):
    return {"suspect_path": str(path), "status": "failed", "error": str(exc), "verdict": "no match",
            "tool_version": __version__}


_RANK = {"match": 0, "inconclusive": 1, "no match": 2}


def _finish(out, info):
    rows = info["rows"]
    best = min(rows, key=lambda r: (_RANK[r.get("verdict", "no match")], r.get("p_value") or 1.0))
    for r in rows:
        r["best"] = r is best
    _write(out, info, rows)
    return best.get("verdict", "no match")


def _write(out, info, rows):
    now = datetime.now(timezone.utc).replace(microsecond=0)
    name = info["sha256"] if info else f"failed-{abs(hash(rows[0]['suspect_path'])):x}"
    write_rows(_out_path(out, name), [{**r, "scanned_at": now} for r in rows], SCAN_SCHEMA)


def read_scan(folder):
    """All detection manifests of a scan folder, as rows."""
    rows = []
    for path in sorted(Path(folder).glob("*.parquet")):
        rows.extend(read_rows(path))
    return rows
