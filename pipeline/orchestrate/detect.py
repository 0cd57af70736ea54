"""``pointmark detect --ledger``: attribute one suspect from the ledger alone, no config.

The ledger names the originals, the parameters of every generation and the
recipients; the secret (environment or key file) must match at least one key
fingerprint recorded there.  Only rows with a valid row MAC are used
(:func:`held_rows`).  Copies under keys the secret does not open are never
checked: when the suspect is the exact bytes of one, or one of its candidate
assets has such copies, a result that would read "no match" reads
"inconclusive", with ``unchecked`` ("N copies under key ID (fingerprint F)")
and ``n_unchecked``.
"""

from __future__ import annotations

import hashlib
from collections import defaultdict
from pathlib import Path

from .. import config
from ..io.ledger import Ledger
from ..io.pointcloud import InputError, read_points, sha256_file
from ..kernels.descriptor import d2_descriptor
from .attribute import check_asset, decide, held_rows, laid_whole, original_files, unheld_copies, unheld_summary
from .candidates import (after_whole, build_index, candidates, cascade, holdings, load_index, planned_recipients,
                         triage, votes_without, whole_may_stop, whole_original, witness, witness_settings)

__all__ = ["detect_from_ledger", "candidate_groups"]


def candidate_groups(rows, asset=None):
    """Issued rows grouped by (asset, source sha256): one original file each."""
    groups = defaultdict(list)
    for r in rows:
        if asset is None or r["asset_key"] == asset:
            groups[(r["asset_key"], r["source_sha256"])].append(r)
    if asset is not None and not groups:
        raise InputError(f"--asset {asset}: no issued copy of this asset under the keys held")
    return groups


def _rank(suspect_path, groups, top_k, shape_margin, gates, store):
    """The originals to check, by ``pointmark scan``'s candidate search.

    Local-descriptor votes over an index of the ledger's originals (built
    once per set of originals, kept beside the basis store) find parts of an
    asset and assets inside a scene; the shape views find whole copies,
    crops and near-identical assets.  Fewer originals than ``top_k`` are
    all returned, ranked, so the first match comes early.  Returns (asset,
    source sha256) keys, and how far each one's check may go
    (:func:`pipeline.orchestrate.candidates.cascade` at ``gates``, the
    config's ``deep_votes``, ``deep_shape``, ``quick_shape`` and
    ``twin_shape``; "deep" for one original), and the triage's shape ranking
    and twins under those keys (for :func:`after_whole`) with its ``seconds``.
    """

    if len(groups) == 1:
        return list(groups), dict.fromkeys(groups, "deep"), {"seconds": 0.0}
    keys = {f"{asset}@{sha[:16]}": (asset, sha) for asset, sha in groups}
    found = {g: original_files(groups[g], store=store)[0] for g in keys.values()}
    paths = {k: found[g].get(g[1], groups[g][-1]["source_path"]) for k, g in keys.items()}
    version = hashlib.sha256("\n".join(sorted(keys)).encode()).hexdigest()[:16]
    index_path = build_index(store, version, paths)
    indexed = set(load_index(index_path).keys) if index_path else set()
    descriptors = {k: None if k in indexed else _whole_d2(paths[k]) for k in keys}   # D2 for what it lacks
    *stage_gates, twin_shape = gates
    info = triage(suspect_path, descriptors, index_path, twin_shape=twin_shape)
    picked = candidates(info, set(keys), top_k, shape_margin)
    shapes = {"ranking": [keys[k] for k in info["ranking"]], "distances": info["distances"],
              "whole_distances": info["whole_distances"],
              "twins": {keys[k]: [[keys[a], d] for a, d in near] for k, near in info["twins"].items()},
              "index": index_path, "keys": keys, "seconds": info["seconds"]}
    return [keys[k] for k in picked], {keys[k]: s for k, s in cascade(info, picked, *stage_gates).items()}, shapes


def _whole_d2(path):
    points = read_points(path).points
    return d2_descriptor(points - points.mean(axis=0))


def _check_in_order(suspect, candidates, stages, groups, materials, store, detect_params, shapes=None,
                    gates=(None, None, None)):
    """Check candidates best-ranked first and stop at the first match, as a scan does.

    The threshold counts every recipient of every candidate planned, those
    the cascade stops (``stages``, and :func:`after_whole` at ``gates``,
    ``deep_votes``, ``deep_shape`` and ``twin_shape``, with ``shapes``, the
    triage's from :func:`_rank`, once a check laid the suspect whole on an
    original)
    included, so neither stopping early nor the cascade adds a chance to
    accuse.  Once a check laid the suspect whole, the witnesses kept in ``store`` take part in that
    staging, and each later check is kept as one (:func:`pipeline.orchestrate.candidates.witness`).
    The result holds ``seconds_ranked_again``, what :func:`votes_without` took (0 when not called).
    """

    planned = planned_recipients([groups[c] for c in candidates], materials)
    checks, stages, whole, ranked_again = [], dict(stages), None, 0.0
    witnessing = witness_settings(detect_params)
    for i, c in enumerate(candidates):
        if stages[c] is None:
            continue
        checks.append(check_asset(suspect, groups[c], materials, store, detect_params, deep=stages[c] == "deep"))
        if whole is not None:       # a check after the suspect was laid whole: what it witnessed is kept
            witness(store, whole, checks[-1], stages[c] == "deep", suspect_sha256, witnessing)
        if decide(checks, detect_params.epsilon, planned=planned)["accused"]:
            break
        rest = {k: stages[k] for k in candidates[i + 1:]}
        if (whole is None and shapes and shapes.get("index") and laid_whole(checks[-1])
                and whole_may_stop(rest, *gates[:2])):
            whole, suspect_sha256 = whole_original(checks[-1]), sha256_file(suspect)
            held = holdings(store, whole, {k: {r["source_sha256"] for r in groups[k]} for k, s in rest.items() if s},
                            witnessing)
            without = {}                # not ranked where every candidate left was witnessed before
            if not all(h is not None for h in held.values()):
                named = {v: k for k, v in shapes["keys"].items()}
                again = votes_without(suspect, shapes["index"], None, named[c], gates[2])
                ranked_again = again["seconds"]
                without = None if again["votes"] is None else {shapes["keys"][k]: v for k, v in again["votes"].items()}
            stages.update(after_whole(shapes, rest, c, *gates[:2], without, held))
    return {**decide(checks, detect_params.epsilon, planned=planned), "checks": checks,
            "seconds_ranked_again": ranked_again}


def detect_from_ledger(suspect, ledger_dir, secret, detect_params, *, asset=None, store=None, top_k=None,
                       shape_margin=None, gates="config"):
    """Attribute one suspect file.

    Without ``asset``, the candidates of ``pointmark scan``'s search are
    checked: the ``top_k`` best by local-descriptor votes and the ``top_k``
    best by shape views, interleaved, and near-identical shapes within
    ``shape_margin`` (None: the config's ``scan.top_k`` and ``scan.shape_margin``),
    so parts of an asset and assets inside a scene are found as a scan
    finds them.  They are checked best-ranked first, up to the first match,
    each through the scan's cascade at ``gates`` ((deep_votes, deep_shape,
    quick_shape, twin_shape); "config": the config's ``scan`` values).

    Returns
    -------
    dict
        The verdict of :func:`pipeline.orchestrate.attribute.decide`, plus
        ``suspect``, ``candidates``, ``n_candidates_checked``, per-check timings
        (``seconds``) and the candidate search's (``seconds_candidates``, as a
        scan counts it: the triage, and the ranking again once an original
        laid the suspect whole; not the index's build nor finding the originals).
    """
    ledger = Ledger(ledger_dir)
    read_points(suspect)                         # a bad suspect stops here, before any work
    report = {}
    rows, materials = held_rows(ledger, secret, report=report)
    groups = candidate_groups(rows, asset)
    store = Path(store) if store else ledger.folder / "bases"
    defaults = config.load_config()
    search = defaults["scan"]
    top_k = search["top_k"] if top_k is None else top_k
    shape_margin = search["shape_margin"] if shape_margin is None else shape_margin
    gates = config.cascade_gates(defaults) if gates == "config" else gates
    candidates, stages, shapes = _rank(suspect, groups, top_k, shape_margin, gates, store)
    result = _check_in_order(suspect, candidates, stages, groups, materials, store, detect_params, shapes,
                             (gates[0], gates[1], gates[3]))
    checks = result.pop("checks")
    seconds_candidates = shapes["seconds"] + result.pop("seconds_ranked_again")
    unchecked = [line for c in checks for line in c["unchecked"]]
    if unchecked and result["verdict"] != "match":      # never "no match" while copies went unchecked
        raise InputError(unchecked[0] + (f" (and {len(unchecked) - 1} more)" if len(unchecked) > 1 else ""))
    # copies it cannot check: under keys not held, or rows set aside (no valid MAC); an asset that has
    # only such copies was never ranked, so it counts as a candidate
    unchecked_rows = report["unheld"] + [r for rs in report["untrusted"].values() for r in rs if r["status"] == "ok"]
    never_ranked = {r["asset_key"] for r in unchecked_rows} - {a for a, _ in groups}
    if asset is not None:
        never_ranked &= {asset}
    unheld = unheld_copies(unchecked_rows, {c[0] for c in candidates} | never_ranked, sha256_file(suspect))
    if unheld and result["verdict"] == "no match":     # copies under keys not held may be what it is
        result["verdict"] = "inconclusive"
    result.update(unchecked=unheld_summary(unheld), n_unchecked=len(unheld))
    result.update(suspect=str(suspect), candidates=[c[0] for c in candidates], n_candidates_checked=len(checks),
                  seconds=[c["seconds"] for c in checks], seconds_candidates=seconds_candidates,
                  ledger_version=ledger.version())
    return result
