"""Leak scans on Dask: which asset, and which recipient, suspect files came from.

Per suspect: (1) a suspect that is a catalogue original's own bytes is no
match; (2) an exact sha256 match with an issued copy attributes at once;
(3) otherwise the top-K catalogue assets by local-descriptor votes
(part-to-whole: crops, scenes) and the top-K by shape distribution (the
suspect whole, without outliers and object by object, against each asset
whole, cut and without outliers) are checked, alternately best-ranked first and until the
first match, through the one attribution
path (:mod:`pipeline.orchestrate.attribute`), each against every recipient
issued under the keys held; the verdict is corrected for every recipient of
every candidate planned.

Layout of ``scan.out``: ``results/`` (one Parquet file per suspect and
ledger/catalogue version, or ``.failed.parquet``), ``evidence/`` (a picture
per match), ``state/`` (what each version held, the feature index) and
``report.md``.

Each suspect ends as exactly one of match, inconclusive, no match or failed.
A failed suspect is counted, sets exit status 3 and is retried by the next
scan; a suspect is skipped only when it was scanned against the same ledger
and catalogue versions.  Otherwise an earlier suspect is checked only against
the ledger parts and catalogue assets added since (``scan.out/state`` records
what each version held), and the correction counts the recipients of every
scan of it.

Exit status: 0 no match, 1 at least one match, 2 bad config or secret,
3 some suspects failed.
"""

from __future__ import annotations

import functools
import hashlib
import json
import sys
import time
import zipfile
from collections import defaultdict
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pyarrow as pa

from .. import __version__, config as config_mod
from ..io.basis_store import find_file, write_file
from ..io.catalog import discover_assets, read_catalogue
from ..io.evidence import render_match, write_summary
from ..io.ledger import Ledger
from ..io.manifest import read_rows, write_rows
from ..io.pointcloud import InputError, atomic_write_bytes, read_points, sha256_file
from ..kernels.descriptor import d2_descriptor, descriptor_distance
from .attribute import check_asset, decide
from .detect import held_rows

__all__ = ["SCAN_SCHEMA", "run_scan", "read_scan", "render_evidence"]

SCAN_SCHEMA = pa.schema([
    ("schema_version", pa.int16()),
    ("suspect_path", pa.string()),
    ("suspect_sha256", pa.string()),
    ("n_points", pa.int64()),
    ("verdict", pa.string()),
    ("candidate_asset", pa.string()),
    ("candidates", pa.list_(pa.string())),
    ("recipient", pa.string()),
    ("key_id", pa.string()),
    ("generation", pa.int32()),
    ("accused_json", pa.string()),
    ("score", pa.float64()),
    ("p_value", pa.float64()),
    ("threshold", pa.float64()),
    ("margin", pa.float64()),
    ("n_checked", pa.int64()),
    ("registration_fitness", pa.float64()),
    ("registration_residual_rel_diag", pa.float64()),
    ("registration_scale", pa.float64()),
    ("registration_coverage", pa.float64()),
    ("registration_status", pa.string()),
    ("evidence_path", pa.string()),
    ("ledger_version", pa.string()),
    ("catalogue_version", pa.string()),
    ("seconds_candidates", pa.float64()),
    ("seconds_registration", pa.float64()),
    ("seconds_detection", pa.float64()),
    ("status", pa.string()),
    ("error", pa.string()),
    ("note", pa.string()),
    ("tool_version", pa.string()),
    ("scanned_at", pa.timestamp("ms", tz="UTC")),
])


@functools.lru_cache(maxsize=2)
def _index(path):
    from ..features import FeatureIndex

    return FeatureIndex.load(path)


def triage(suspect_path, descriptors, index_path):
    """Read a suspect, hash it, rank every catalogue asset two ways.

    ``ranking``: by shape distribution (D2), the suspect's views (it whole,
    without outliers, each separate object) against each asset's (whole,
    cut as a crop cuts it, and without outliers), right for whole copies,
    scenes, outliers and crops; ``index_ranking``: by votes of local descriptors (FPFH) over the
    catalogue index, right for parts of an asset and assets inside a scene.
    """
    t0 = time.perf_counter()
    points = read_points(suspect_path).points
    names = list(descriptors)
    shaped, index_ranking = {}, []
    if index_path:
        index = _index(index_path)
        shaped = dict(zip(index.keys, index.shape_distances(points)))
        index_ranking = [k for k, _ in index.rank(points, top_k=len(names))]
    # assets the index lacks (unreadable when it was built) keep the catalogue's whole-asset D2
    missing = [k for k in names if k not in shaped]
    if missing:
        whole = np.atleast_1d(descriptor_distance(d2_descriptor(points - points.mean(axis=0)),
                                                  np.array([descriptors[k] for k in missing])))
        shaped.update(zip(missing, whole))
    dist = np.array([shaped[k] for k in names])
    order = np.argsort(dist, kind="stable")
    return {"path": str(suspect_path), "sha256": sha256_file(suspect_path), "n_points": len(points),
            "ranking": [names[i] for i in order], "distances": [float(dist[i]) for i in order],
            "index_ranking": index_ranking, "seconds": time.perf_counter() - t0}


def _candidates(info, view, top_k, margin=1.6):
    """Candidates among the assets in view, alternating between the rankings (best of each first).

    The top-K of each ranking, and also, up to 2K from the shape ranking,
    the assets whose shape distance is within ``margin`` times the nearest
    in view (near-identical assets tie there).
    """
    by_votes = [a for a in info["index_ranking"] if a in view][:top_k]
    shaped = [(a, d) for a, d in zip(info["ranking"], info["distances"]) if a in view]
    by_shape = [a for i, (a, d) in enumerate(shaped)
                if i < top_k or (i < 2 * top_k and d <= margin * shaped[0][1])]
    pick = [a for pair in zip(by_shape, by_votes) for a in pair]
    pick += by_shape[len(by_votes):] + by_votes[len(by_shape):]
    return list(dict.fromkeys(pick))


INDEX_FORMAT = "v4"   # v2: inverted-file cells; v3: whole and cut shape views; v4: and the dense view


def _loads(index_path):
    try:
        _index(index_path)
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        return False
    return True


def _build_index(out, cat_version, catalogue_paths):
    """The catalogue's local-descriptor index, built once per catalogue version.

    Kept in ``out`` (a scan's folder, or the basis store for ``detect
    --ledger``), or in its stand-in when ``out`` cannot be written.
    """
    from ..features import build_index

    name = f"state/index-{INDEX_FORMAT}-{cat_version}.npz"
    found = [p for p in find_file(out, name) if _loads(p)]      # a damaged one is rebuilt
    if found or not catalogue_paths:
        return str(found[0]) if found else None
    clouds, missing = {}, []
    for key, file in sorted(catalogue_paths.items()):
        try:
            clouds[key] = read_points(file).points
        except InputError:
            missing.append(key)          # its checks fail (and are retried); D2 still ranks it
    if not clouds:
        return None
    index = build_index(clouds)
    if missing:                          # not saved: the next scan builds it whole
        return str(write_file(out, f"state/.index-{cat_version}-partial.npz", index.to_bytes()))
    return str(write_file(out, name, index.to_bytes()))


def _reference(cfg, secret):
    sc = cfg["scan"]
    for name in ("suspects", "catalogue"):
        if not sc[name]:
            raise config_mod.ConfigError(f"config: scan.{name}: required for a scan")
    ledger = Ledger(sc["manifests"] or cfg["output"]["manifests"])
    rows, materials = held_rows(ledger, secret)          # refuses a secret that opens nothing
    catalogue = [r for r in read_catalogue(sc["catalogue"]) if r["status"] == "ok"]
    cat_version = hashlib.sha256("\n".join(sorted(r["sha256"] for r in catalogue)).encode()).hexdigest()[:16]
    issued = defaultdict(list)
    for r in rows:
        issued[r["asset_key"]].append(r)
    originals = {r["sha256"] for r in catalogue} | {r["source_sha256"] for r in rows}
    # an issued copy with its original's bytes is no copy: it never attributes anything
    by_sha = {r["output_sha256"]: r for r in rows if r["output_sha256"] not in originals}
    descriptors = {r["asset_key"]: r["descriptor"] for r in catalogue if r["asset_key"] in issued}
    assets = {r["asset_key"]: r["sha256"] for r in catalogue}
    base = Path(sc["catalogue"]).resolve().parent
    paths = {r["asset_key"]: (Path(r["path"]) if Path(r["path"]).is_absolute() else base / r["path"])
             for r in catalogue if r["asset_key"] in issued}
    return ledger, materials, issued, by_sha, originals, descriptors, cat_version, assets, paths


def _result_path(out, sha, versions, failed=False):
    if failed:
        return Path(out) / "results" / f"{sha[:32]}.failed.parquet"
    return Path(out) / "results" / f"{sha[:32]}-{versions[0]}-{versions[1]}.parquet"


def run_scan(cfg, secret, *, force=False):
    """``pointmark scan``: returns the exit status."""
    from distributed import as_completed

    from .run import start_client

    sc = cfg["scan"]
    ledger, materials, issued, by_sha, originals, descriptors, cat_version, assets, paths = _reference(cfg, secret)
    versions = (ledger.version(), cat_version)
    suspects = [a.path for a in discover_assets(sc["suspects"])]
    detect_params = config_mod.detect_params(cfg)
    store = str(Path(cfg["output"]["bases"] or ledger.folder / "bases"))
    out = Path(sc["out"])
    out.mkdir(parents=True, exist_ok=True)
    state = _save_state(out, versions, [p.name for p in ledger.parts()], assets)
    index_path = _build_index(out, cat_version, paths)
    previous = {} if force else _previous(out)
    t0 = time.perf_counter()
    counts = {"match": 0, "no match": 0, "inconclusive": 0, "failed": 0, "skipped": 0}
    # suspects already scanned against these versions are skipped before any
    # work (hashing is cheap; ranking a suspect against the catalogue is not)
    done = {p for p in suspects if previous and _already(previous.get(_sha_or_none(p)), versions)}
    counts["skipped"] = len(done)
    client, cluster = start_client(cfg)
    try:
        triages = {client.submit(triage, str(p), descriptors, index_path, pure=False): p
                   for p in suspects if p not in done}
        pending = as_completed(list(triages))
        waiting = {}
        for fut in pending:
            if fut in triages:
                path = triages.pop(fut)
                if fut.status != "finished":
                    _record(out, versions, {"suspect_path": str(path)}, "failed", error=_text(fut.exception()))
                    counts["failed"] += 1
                    continue
                info = fut.result()
                prev = previous.get(info["sha256"])
                if _already(prev, versions):   # the same bytes twice in the folder
                    counts["skipped"] += 1
                    continue
                verdict = _quick(info, by_sha, originals, out, versions)
                if verdict:
                    counts[verdict] += 1
                    continue
                view = _scope(issued, prev, state, out)
                info["prev"] = prev
                info["candidates"] = _candidates(info, view, sc["top_k"], sc["shape_margin"])
                info["planned"] = planned_recipients([view[a] for a in info["candidates"]], materials)
                info["checks"], info["errors"] = [], []
                # candidates are checked best-ranked first and the search
                # stops at the first match: the threshold counts every
                # recipient of every candidate planned, so stopping early
                # adds no chance to accuse
                info["queue"] = [(view[a], [str(paths[a])] if a in paths else []) for a in info["candidates"]]
                if not _submit_next(client, info, materials, store, detect_params, waiting, pending):
                    counts[_finish(out, versions, info, detect_params.epsilon, store)] += 1
            else:
                info = waiting.pop(fut)
                if fut.status == "finished":
                    info["checks"].append(fut.result())
                else:
                    info["errors"].append(_text(fut.exception()))
                matched = decide(info["checks"], detect_params.epsilon, _prior(info), info["planned"])["accused"]
                if matched or not _submit_next(client, info, materials, store, detect_params, waiting, pending):
                    verdict = _finish(out, versions, info, detect_params.epsilon, store)
                    counts[verdict] += 1
                    print(f"[pointmark] scan: {info['path']}: {verdict}", file=sys.stderr, flush=True)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    summary = write_summary(read_scan(out), out / "report.md", detect_params.epsilon)
    print(f"scanned {len(suspects)} suspects in {time.perf_counter() - t0:.0f}s: {counts['match']} match, "
          f"{counts['inconclusive']} inconclusive, {counts['no match']} no match, {counts['failed']} failed, "
          f"{counts['skipped']} already scanned; results in {out}, evidence report {summary}")
    if counts["failed"]:
        return 3
    return 1 if counts["match"] else 0


def planned_recipients(candidate_rows, materials):
    """Recipients a suspect may be scored against: every (reference, key, generation, recipient) held.

    Parameters
    ----------
    candidate_rows : list of list of dict
        Issued ledger rows of each candidate asset.
    materials : dict key_id -> bytes

    Returns
    -------
    int
        An upper bound on what :func:`check_asset` scores for these candidates.
    """
    return sum(len({(r["reference_key"], r["key_id"], r["generation_id"], r["recipient"])
                    for r in rows if r["key_id"] in materials}) for rows in candidate_rows)


def _prior(info):
    return (info.get("prev") or {}).get("n_checked") or 0


def _sha_or_none(path):
    """The file's sha256, or None when it cannot be read (its triage then fails and is recorded)."""
    try:
        return sha256_file(path)
    except OSError:
        return None


def _already(prev, versions):
    """True when a suspect's last result was against these ledger and catalogue versions."""
    return prev is not None and (prev["ledger_version"], prev["catalogue_version"]) == versions


def _submit_next(client, info, materials, store, detect_params, waiting, pending):
    """Submit the suspect's next candidate check; False when none is left.

    Checks run before the triage of further suspects (higher priority), so
    verdicts come out while a large folder is still being ranked.
    """
    if not info["queue"]:
        return False
    rows, places = info["queue"].pop(0)
    fut = client.submit(check_asset, info["path"], rows, materials, store, detect_params, places=places,
                        pure=False, priority=1)
    waiting[fut] = info
    pending.add(fut)
    return True


def _text(exc):
    return str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"


def _quick(info, by_sha, originals, out, versions):
    """Verdicts that need no detection: an original's own bytes, an exact issued copy."""
    if info["sha256"] in originals:
        _record(out, versions, info, "no match", error="the suspect is a catalogue original's own bytes")
        return "no match"
    row = by_sha.get(info["sha256"])
    if row is None:
        return None
    _record(out, versions, info, "match", candidate_asset=row["asset_key"], recipient=row["recipient"],
            key_id=row["key_id"], generation=row["generation"], p_value=0.0,
            accused_json=json.dumps([{"recipient": row["recipient"], "asset_key": row["asset_key"],
                                      "exact_sha256": True}]))
    return "match"


def render_evidence(suspect_path, original_path, accused, store, path):
    """The evidence picture of one accusation (see :func:`pipeline.io.evidence.render_match`)."""
    from ..io.basis_store import BasisStore

    centre, _, _, members = BasisStore(store).load_meta(accused["reference_key"])
    title = (f"{Path(suspect_path).name}: issued copy of {accused['asset_key']} to {accused['recipient']} "
             f"(generation {accused['copies'][-1][0]}), score {accused['score']:.1f}, p = {accused['p_value']:.2g}, "
             f"margin {accused['margin']:.1f}")
    return render_match(read_points(original_path).points, read_points(suspect_path).points,
                        {**accused["registration"], "centre": centre}, members, accused["cluster_scores"], title, path)


def _finish(out, versions, info, epsilon, store):
    if info["errors"]:     # a check that raised is never "no match": retried next scan
        _record(out, versions, info, "failed", error="; ".join(info["errors"]))
        return "failed"
    prev = info.get("prev")
    result = decide(info["checks"], epsilon, _prior(info), info.get("planned", 0))
    if prev is not None and result["verdict"] != "match" and prev["verdict"] in ("match", "inconclusive"):
        # what was found before stands; the new copies and assets did not change it
        carried = {k: prev[k] for k in SCAN_SCHEMA.names if k in prev and k not in ("scanned_at", "ledger_version",
                                                                                     "catalogue_version")}
        _record(out, versions, info, prev["verdict"], **{k: v for k, v in carried.items() if k not in
                                                        ("suspect_path", "suspect_sha256", "n_points", "verdict",
                                                         "status", "tool_version", "schema_version", "note")},
                note=f"checked {result['n_checked'] - (prev.get('n_checked') or 0)} more recipients; "
                     f"the verdict of {prev['scanned_at']:%Y-%m-%d %H:%M} stands")
        return prev["verdict"]
    unchecked = [line for c in info["checks"] for line in c.get("unchecked", [])]
    if unchecked and result["verdict"] != "match":
        # copies whose original no file holds may be what this is: failed (retried), never "no match"
        _record(out, versions, info, "failed", error="; ".join(unchecked), n_checked=result["n_checked"])
        return "failed"
    top = result["accused"][0] if result["accused"] else None
    evidence = None
    if top is not None and top.get("cluster_scores") is not None:
        evidence = out / "evidence" / f"{info['sha256'][:32]}-{versions[0]}-{versions[1]}.png"
        render_evidence(info["path"], top["original_path"], top, store, evidence)
    regs = [g["registration"] for c in info["checks"] for g in c["groups"]]
    # the accused's registration, else the best one (most overlap) of any candidate
    reg = top["registration"] if top else max(regs, key=lambda r: min(r.get("fitness", 0), r.get("coverage", 0)),
                                              default={})
    status = None if not regs else ("registration failed" if all(r.get("failed") for r in regs) else "registered")
    seconds = [c["seconds"] for c in info["checks"]]
    _record(out, versions, info, result["verdict"],
            candidate_asset=top["asset_key"] if top else None, recipient=top["recipient"] if top else None,
            key_id=top["key_id"] if top else None, generation=top["copies"][-1][0] if top else None,
            accused_json=json.dumps([{k: a[k] for k in ("recipient", "asset_key", "key_id", "score", "p_value",
                                                        "margin", "copies")} for a in result["accused"]]),
            score=result["best_score"], p_value=result["p_value"], threshold=result["threshold"],
            margin=top["margin"] if top else None, n_checked=result["n_checked"],
            registration_fitness=reg.get("fitness"), registration_residual_rel_diag=reg.get("residual_rel_diag"),
            registration_scale=reg.get("scale"), registration_coverage=reg.get("coverage"),
            registration_status=status,
            seconds_registration=sum(s["registration"] for s in seconds),
            seconds_detection=sum(s["estimate"] + s["scoring"] for s in seconds),
            evidence_path=None if evidence is None else str(evidence))
    return result["verdict"]


def _save_state(out, versions, parts, assets):
    """Record which ledger parts and catalogue assets a version names (once, never rewritten)."""
    folder = Path(out) / "state"
    folder.mkdir(parents=True, exist_ok=True)
    for name, value in ((f"ledger-{versions[0]}.json", parts), (f"catalogue-{versions[1]}.json", assets)):
        path = folder / name
        if not path.exists():
            atomic_write_bytes(path, json.dumps(value, sort_keys=True).encode())
    return {"parts": set(parts), "assets": assets}


def _previous(out):
    """The latest finished (not failed) result of every suspect sha256 scanned into ``out``."""
    latest = {}
    for r in read_scan(out):
        if r["status"] == "ok" and r.get("suspect_sha256"):
            old = latest.get(r["suspect_sha256"])
            if old is None or r["scanned_at"] > old["scanned_at"]:
                latest[r["suspect_sha256"]] = r
    return latest


def _scope(issued, prev, state, out):
    """Issued rows a suspect must be checked against: all, or those added since its last scan."""
    if prev is None:
        return issued
    folder = Path(out) / "state"
    try:
        parts = set(json.loads((folder / f"ledger-{prev['ledger_version']}.json").read_text()))
        assets = json.loads((folder / f"catalogue-{prev['catalogue_version']}.json").read_text())
    except (OSError, ValueError):
        return issued                       # no record of what it saw: check everything again
    view = {}
    for asset, rows in issued.items():
        new_asset = assets.get(asset) != state["assets"].get(asset)
        keep = [r for r in rows if new_asset or r["ledger_part"] not in parts]
        if keep:
            view[asset] = keep
    return view


def _record(out, versions, info, verdict, **columns):
    """Write the suspect's result row.

    A failed suspect keeps one file, overwritten on retry; a finished result
    never overwrites another (a ``--force`` rescan against the same versions
    adds a file named by its time).
    """
    now = datetime.now(timezone.utc).replace(microsecond=0)
    sha = info.get("sha256") or hashlib.sha256(info["suspect_path"].encode()).hexdigest()
    row = {"suspect_path": info.get("path", info.get("suspect_path")), "suspect_sha256": info.get("sha256"),
           "n_points": info.get("n_points"), "candidates": info.get("candidates"),
           "seconds_candidates": info.get("seconds"), "verdict": verdict,
           "status": "failed" if verdict == "failed" else "ok", "ledger_version": versions[0],
           "catalogue_version": versions[1], "tool_version": __version__, "scanned_at": now, **columns}
    path = _result_path(out, sha, versions, failed=verdict == "failed")
    stamp, n = now.strftime("%Y%m%dT%H%M%S"), 0
    while verdict != "failed" and path.exists():
        n += 1
        path = path.with_name(f"{path.name.removesuffix('.parquet').split('@')[0]}@{stamp}-{n}.parquet")
    write_rows(path, [row], SCAN_SCHEMA)


def read_scan(folder):
    """All result rows of a scan folder (temporary files of interrupted writers are ignored).

    The rows are ``scan.out/results/*.parquet``; ``pyarrow.dataset.dataset(scan.out / "results")``
    reads them as one table.
    """
    rows = []
    for path in sorted((Path(folder) / "results").glob("*.parquet")):
        if not path.name.startswith("."):
            rows.extend(read_rows(path))
    return rows
