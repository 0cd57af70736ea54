"""Attribution: which issued copy a suspect came from, read from the ledger.

One path for ``pointmark detect --ledger`` and ``pointmark scan``:

1. :func:`check_asset` rebuilds (or loads from the basis store) each
   reference of a candidate asset, verifies it against the digests recorded
   at embedding, registers the suspect and estimates the coefficient
   differences once per reference, then scores every issued recipient of
   every key id the caller holds, generation by generation (each issued copy
   has its own fingerprint).
2. :func:`decide` pools the checks of one suspect: the threshold and the
   p-values are corrected for every recipient of every asset, key and
   generation that was scored.
"""

from __future__ import annotations

import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from ..allocator import keep_freed_memory
from ..io.basis_store import BasisStore
from ..io.ledger import mac_ok
from ..io.pointcloud import InputError, read_points, sha256_file
from ..io.secrets import SecretError
from ..kernels import fingerprint, keys
from ..watermark import (Undecided, estimate_differences, fingerprint_length, fingerprint_observations,
                         params_from_record)
from .reference import load_reference
from .tasks import copy_label

__all__ = ["params_from_row", "reference_record", "check_asset", "decide", "usable_rows", "original_files", "held_rows", "unheld_copies",
           "unheld_summary", "laid_whole", "TOP"]

TOP = 8          # best scores kept per reference and key, beyond those over the floor
FLOOR = 4.0      # scores kept whatever their rank (an accusation needs more than 5 at any scale)


def params_from_row(row):
    """WatermarkParams recorded in a ledger row (or in a :func:`reference_record`)."""
    return params_from_record(json.loads(row["params_json"]))


def reference_record(row):
    """What a ledger row records of its reference: parameters and digests (what :func:`load_reference` checks)."""
    return {"params_json": row["params_json"],
            "digests": {"membership": list(row["cluster_membership_digests"]),
                        "basis": list(row["cluster_basis_digests"])}}


def usable_rows(rows, secret_fingerprints):
    """Issued rows whose key fingerprint matches a secret the caller holds."""
    return [r for r in rows if r["status"] == "ok" and r["mark"] == "fingerprint"
            and r["key_fingerprint"] in secret_fingerprints]


def check_asset(suspect_path, rows, materials, store, detect_params, *, places=(), deep=True):
    """Score every issued recipient of one asset against one suspect.

    Parameters
    ----------
    suspect_path : str or Path
    rows : list of dict
        Issued ledger rows of the asset (status ok), any generations and
        any bytes of its original: each set of copies is checked against
        the file holding the bytes it was issued from
        (:func:`original_files`).
    materials : dict key_id -> bytes
        Derived key material of the key ids the caller holds.
    store : str or Path
        The basis store.
    detect_params : DetectParams
    places : sequence of str or Path
        Files to try first for an original (the catalogue's), before the
        source paths the ledger recorded.
    deep : bool
        Whether the registration may run its deep steps
        (:func:`pipeline.watermark.register`); False leaves a reference
        that only they could place unscored, counted in ``stopped``.

    Returns
    -------
    dict
        ``groups`` (one per reference and key id: asset, key id, recipients
        scored, their best scores, presence p-value, registration, original
        path and sha256), ``stopped`` (references left unscored after the quick
        registration steps), ``unchecked`` (lines from :func:`original_files`:
        copies whose original no file holds) and timings (``registration``,
        of it ``quick`` and ``deep``, ``estimate``, ``scoring``).

    Raises
    ------
    InputError
        An original found cannot be read as a point set.
    ReferenceMismatch
        The rebuilt reference differs from the one recorded at embedding.
    """
    keep_freed_memory()     # the registration's temporaries, allocated and freed thousands of times
    files, unchecked = original_files(rows, places, store)
    suspect = read_points(suspect_path).points
    originals = {sha: read_points(path).points for sha, path in files.items()}
    by_ref = defaultdict(list)
    for r in rows:
        if r["source_sha256"] in files:         # the rest are reported in ``unchecked``, never "no match"
            by_ref[r["reference_key"]].append(r)
    groups, stopped = [], 0
    seconds = {"registration": 0.0, "quick": 0.0, "deep": 0.0, "estimate": 0.0, "scoring": 0.0}
    for ref_key, ref_rows in sorted(by_ref.items()):
        params = params_from_row(ref_rows[0])
        sha = ref_rows[0]["source_sha256"]       # (a reference is one original's bytes under one parameter set)
        original = originals[sha]
        ref = load_reference(original, params, store, ref_key, reference_record(ref_rows[0])["digests"],
                             detection=True)
        times = {}
        try:
            est = estimate_differences(suspect - ref.centre, original - ref.centre, ref.specs, ref.bases,
                                       detect_params, params, deep=deep, times=times, every_pose=True,
                                       **ref.detection_aids())
        except Undecided:
            seconds["registration"] += times["quick"]
            seconds["quick"] += times["quick"]
            stopped += 1
            continue
        seconds["registration"] += est["seconds_registration"]
        seconds["quick"] += est["seconds_quick"]
        seconds["deep"] += est["seconds_deep"]
        seconds["estimate"] += est["seconds_estimate"]
        t0 = time.perf_counter()
        ys = fingerprint_observations(est, ref.specs, params)
        for key_id, generation_id in sorted({(r["key_id"], r["generation_id"]) for r in ref_rows}):
            if key_id in materials:
                rows_g = [r for r in ref_rows if (r["key_id"], r["generation_id"]) == (key_id, generation_id)]
                groups.append({**_score_group(ys, ref, params, rows_g, materials[key_id], est),
                               "original_path": str(files[sha]), "original_sha256": sha})
        seconds["scoring"] += time.perf_counter() - t0
    return {"asset_key": rows[0]["asset_key"], "groups": groups, "stopped": stopped, "seconds": seconds,
            "unchecked": unchecked}


def laid_whole(check):
    """Whether a check laid the suspect whole on its asset's original (:func:`pipeline.watermark.laid_whole`)."""
    return any(g["registration"].get("whole") for g in check["groups"])


def original_files(rows, places=(), store=None):
    """The file holding the bytes each set of copies was issued from.

    For each original sha256 of ``rows``, the first of ``places``, then of
    the source paths recorded for those copies (newest first), then of the
    copy a run kept in the basis store ``store`` (``output.keep_originals``)
    whose bytes have that hash: an original moved, revised or deleted still
    finds the copies issued from its old bytes.

    Returns
    -------
    found : dict
        source sha256 -> path.
    unchecked : list of str
        One line per set of copies whose bytes no file holds (asset, count,
        sha256, each path tried and why it failed): they cannot be checked.
    """
    hashes, found, unchecked = {}, {}, []
    for sha in dict.fromkeys(r["source_sha256"] for r in reversed(rows)):
        mine = [r for r in reversed(rows) if r["source_sha256"] == sha]
        kept = BasisStore(store).kept_original(sha, Path(mine[0]["source_path"]).suffix.lower()) if store else None
        tried = list(dict.fromkeys([*map(str, places), *(r["source_path"] for r in mine),
                                    *([str(kept)] if kept else [])]))
        for path in tried:
            if path not in hashes:
                hashes[path] = _sha256_or_reason(path)
        hit = next((p for p in tried if hashes[p][0] == sha), None)
        if hit is not None:
            found[sha] = hit
            continue
        why = "; ".join(f"{p}: {hashes[p][1] or 'other bytes'}" for p in tried)
        unchecked.append(f"{mine[0]['asset_key']}: {len(mine)} issued cop{'y' if len(mine) == 1 else 'ies'} "
                         f"cannot be checked, no file holds their original (sha256 {sha[:12]}...) ({why})")
    return found, unchecked


def _sha256_or_reason(path):
    """(the file's sha256, None), or (None, why it cannot be read)."""
    try:
        return sha256_file(path), None
    except FileNotFoundError:
        return None, "missing"
    except OSError as exc:
        return None, exc.strerror or type(exc).__name__


def _score_group(ys, ref, params, rows, material, estimate):
    """One key's recipients of one reference scored at every pose read (``ys``, the chosen pose first).

    ``n_recipients`` times ``n_poses`` recipients count as checked.
    """
    recipients = sorted({r["recipient"] for r in rows})
    bank = fingerprint.chip_bank(material, copy_label(rows[0]["asset_key"], rows[0]["generation"]), recipients,
                                 fingerprint_length(len(ref.specs), params))
    s, pose, table = fingerprint.scores_over_poses(ys, bank)
    keep = np.union1d(np.argsort(-s, kind="stable")[:TOP], np.flatnonzero(s >= FLOOR))
    generations = defaultdict(list)
    for r in rows:
        generations[r["recipient"]].append((int(r["generation"]), r["output_path"]))
    poses = [estimate, *estimate.get("other_poses", ())]
    return {
        "asset_key": rows[0]["asset_key"], "key_id": rows[0]["key_id"], "reference_key": rows[0]["reference_key"],
        "generation": int(rows[0]["generation"]), "reference": reference_record(rows[0]),
        "n_recipients": len(recipients), "n_poses": len(ys),
        "presence_p": fingerprint.presence_over_poses(table),
        "best": [{"recipient": recipients[i], "score": float(s[i]), "copies": sorted(generations[recipients[i]]),
                  "pose": int(pose[i]), "registration": poses[pose[i]]["registration"],
                  "cluster_scores": (fingerprint.cluster_scores(ys[pose[i]], fingerprint.signs(bank[i], len(ys[0]))[0],
                                                                len(ref.specs)).tolist() if s[i] >= FLOOR else None)}
                 for i in keep],
        "registration": estimate["registration"],
    }


def decide(checks, epsilon, prior_checked=0, planned=0):
    """Verdict of one suspect from all its checks, corrected for everything scored.

    Parameters
    ----------
    checks : list of dict (from :func:`check_asset`)
    epsilon : float
        Probability of accusing any innocent, per suspect.
    prior_checked : int
        Recipients this suspect was scored against by earlier scans; they
        count in the correction, so rescans never add chances to accuse.
    planned : int
        Recipients of every candidate this scan may check (it stops at the
        first match); the correction counts at least these.

    Returns
    -------
    dict
        verdict ("match", "inconclusive" or "no match"), accused (recipient,
        asset, key id, score, corrected p-value, margin, copies), n_checked,
        threshold, best_innocent_score.
    """
    groups = [g for c in checks for g in c["groups"]]
    n_checked = max(sum(g["n_recipients"] * g.get("n_poses", 1) for g in groups), int(planned)) + int(prior_checked)
    t = fingerprint.threshold(max(n_checked, 1), epsilon)
    scored = [(b["score"], g, b) for g in groups for b in g["best"]]
    accused = sorted((x for x in scored if x[0] >= t), key=lambda x: -x[0])
    innocent = max((x[0] for x in scored if x[0] < t), default=0.0)
    result = {"n_checked": n_checked, "threshold": t, "best_innocent_score": innocent,
              "accused": [{"recipient": b["recipient"], "asset_key": g["asset_key"], "key_id": g["key_id"],
                           "score": s, "p_value": fingerprint.corrected_p(s, n_checked), "margin": s - innocent,
                           "copies": b["copies"], "registration": b.get("registration", g["registration"]),
                           "cluster_scores": b["cluster_scores"], "reference_key": g["reference_key"],
                           "reference": g["reference"], "original_path": g.get("original_path")}
                          for s, g, b in accused]}
    # a mark is there but nobody clears the threshold: say so, never "no match"
    if accused:
        result["verdict"] = "match"
    elif any(g["presence_p"] * len(groups) < epsilon for g in groups):
        result["verdict"] = "inconclusive"
    else:
        result["verdict"] = "no match"
    best = max(scored, key=lambda x: x[0], default=None)
    result["best_score"] = None if best is None else best[0]
    result["p_value"] = 1.0 if best is None else fingerprint.corrected_p(best[0], n_checked)
    return result


_SEAL_HINT = "; rows of a ledger older than row MACs verify once sealed: pointmark ledger seal LEDGER"


def held_rows(ledger, secret, *, report=None):
    """Issued rows of the ledger whose key the secret opens and whose row MAC holds, and their key materials.

    Every row whose key fingerprint the secret opens must carry the
    ``row_mac`` that :func:`pipeline.kernels.keys.row_mac` gives under the
    secret's ledger MAC key: a row whose MAC is missing or wrong (a part
    file dropped into ``copies/`` by someone without the secret, a recipient
    or sha256 rewritten) is set aside as untrusted, said on stderr once per
    part file, and never used, neither for an exact-hash attribution nor as
    a recipient that can be accused.

    Parameters
    ----------
    ledger : Ledger
    secret : bytes
    report : dict, optional
        Filled with ``unheld`` (issued rows under keys the secret does not
        open: they cannot be checked, nor their MACs verified) and
        ``untrusted`` (ledger part name -> rows set aside).

    Raises
    ------
    InputError
        The folder holds no issued copy.
    SecretError
        The secret matches none of the key fingerprints recorded, or every
        row it opens fails its MAC.
    """
    rows = ledger.rows()
    if not rows:
        raise InputError(f"{ledger.folder}: no issued copy in this ledger (is it output.manifests of a run?)")
    fingerprints = {keys.key_fingerprint(secret, salt) for salt in {r["key_salt"] for r in rows}}
    opened = usable_rows(rows, fingerprints)
    if not opened:
        raise SecretError(f"{ledger.folder}: the secret matches none of the key fingerprints of the issued copies "
                          f"(wrong or rotated secret?)")
    mac_key = keys.ledger_mac_key(secret)
    untrusted = defaultdict(list)
    usable = []
    for r in opened:
        if mac_ok(mac_key, r):
            usable.append(r)
        else:
            untrusted[r["ledger_part"]].append(r)
    for part, bad in sorted(untrusted.items()):
        missing = sum(r.get("row_mac") is None for r in bad)
        print(f"[pointmark] ledger: {ledger.copies / part}: {len(bad)} row(s) under this secret's key set aside as "
              f"untrusted, never used to attribute or accuse ({len(bad) - missing} with a wrong row MAC, {missing} "
              f"without one{_SEAL_HINT if missing else ''})", file=sys.stderr, flush=True)
    if not usable:
        raise SecretError(f"{ledger.folder}: none of the {len(opened)} issued rows under this secret's key carries "
                          f"a valid row MAC (altered, or written before row MACs{_SEAL_HINT})")
    if report is not None:
        report["unheld"] = [r for r in rows if r["status"] == "ok" and r["mark"] == "fingerprint"
                            and r["key_fingerprint"] not in fingerprints]
        report["untrusted"] = dict(untrusted)
    materials = {k: keys.derive_key_material(secret, k) for k in {r["key_id"] for r in usable}}
    return usable, materials


def unheld_copies(unheld, candidates, suspect_sha256):
    """The copies under keys not held that a suspect may be: its exact bytes, or copies of a candidate asset.

    Parameters
    ----------
    unheld : list of dict
        Issued rows under keys the secret does not open (:func:`held_rows`).
    candidates : set of str
        Asset keys the suspect was (or would have been) checked against.
    suspect_sha256 : str

    Returns
    -------
    list of dict
    """
    return [r for r in unheld if r["asset_key"] in candidates or r["output_sha256"] == suspect_sha256]


def unheld_summary(rows):
    """One line per key: "N copies under key ID (fingerprint F)", for rows under keys not held."""
    by_key = defaultdict(int)
    for r in rows:
        by_key[(r["key_id"], r["key_fingerprint"])] += 1
    return "; ".join(f"{n} cop{'y' if n == 1 else 'ies'} under key {k} (fingerprint {f})"
                     for (k, f), n in sorted(by_key.items()))
