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
import hmac
import sys
from collections import defaultdict
from pathlib import Path

from .. import config
from ..io.ledger import MAC_FIELDS, Ledger
from ..io.pointcloud import InputError, read_points, sha256_file
from ..io.secrets import SecretError
from ..kernels import keys
from ..kernels.descriptor import d2_descriptor
from .attribute import check_asset, decide, original_files, usable_rows

__all__ = ["detect_from_ledger", "held_rows", "candidate_groups", "unheld_copies", "unheld_summary"]


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
        mac = r.get("row_mac")
        if isinstance(mac, str) and hmac.compare_digest(mac, keys.row_mac(mac_key, r, MAC_FIELDS)):
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


def candidate_groups(rows, asset=None):
    """Issued rows grouped by (asset, source sha256): one original file each."""
    groups = defaultdict(list)
    for r in rows:
        if asset is None or r["asset_key"] == asset:
            groups[(r["asset_key"], r["source_sha256"])].append(r)
    if asset is not None and not groups:
        raise InputError(f"--asset {asset}: no issued copy of this asset under the keys held")
    return groups


def _rank(suspect_path, groups, top_k, store):
    """The originals to check, by ``pointmark scan``'s candidate search.

    Local-descriptor votes over an index of the ledger's originals (built
    once per set of originals, kept beside the basis store) find parts of an
    asset and assets inside a scene; the shape views find whole copies,
    crops and near-identical assets.  Fewer originals than ``top_k`` are
    all returned, ranked, so the first match comes early.  Returns (asset,
    source sha256) keys.
    """
    from .scan import _build_index, _candidates, _index, triage   # (scan imports this module)

    if len(groups) == 1:
        return list(groups)
    keys = {f"{asset}@{sha[:16]}": (asset, sha) for asset, sha in groups}
    found = {g: original_files(groups[g], store=store)[0] for g in keys.values()}
    paths = {k: found[g].get(g[1], groups[g][-1]["source_path"]) for k, g in keys.items()}
    version = hashlib.sha256("\n".join(sorted(keys)).encode()).hexdigest()[:16]
    index_path = _build_index(store, version, paths)
    indexed = set(_index(index_path).keys) if index_path else set()
    descriptors = {k: None if k in indexed else _whole_d2(paths[k]) for k in keys}   # D2 for what it lacks
    info = triage(suspect_path, descriptors, index_path)
    return [keys[k] for k in _candidates(info, set(keys), top_k)]


def _whole_d2(path):
    points = read_points(path).points
    return d2_descriptor(points - points.mean(axis=0))


def _check_in_order(suspect, candidates, groups, materials, store, detect_params):
    """Check candidates best-ranked first and stop at the first match, as a scan does.

    The threshold counts every recipient of every candidate planned, so
    stopping early adds no chance to accuse.
    """
    from .scan import planned_recipients

    planned = planned_recipients([groups[c] for c in candidates], materials)
    checks = []
    for c in candidates:
        checks.append(check_asset(suspect, groups[c], materials, store, detect_params))
        if decide(checks, detect_params.epsilon, planned=planned)["accused"]:
            break
    return {**decide(checks, detect_params.epsilon, planned=planned), "checks": checks}


def detect_from_ledger(suspect, ledger_dir, secret, detect_params, *, asset=None, store=None, top_k=None):
    """Attribute one suspect file.

    Without ``asset``, the candidates of ``pointmark scan``'s search are
    checked: the ``top_k`` best by local-descriptor votes and the ``top_k``
    best by shape views, interleaved (default: the config's ``scan.top_k``),
    so parts of an asset and assets inside a scene are found as a scan
    finds them.  They are checked best-ranked first, up to the first match.

    Returns
    -------
    dict
        The verdict of :func:`pipeline.orchestrate.attribute.decide`, plus
        ``suspect``, ``candidates``, ``n_candidates_checked`` and per-check timings.
    """
    ledger = Ledger(ledger_dir)
    read_points(suspect)                         # a bad suspect stops here, before any work
    report = {}
    rows, materials = held_rows(ledger, secret, report=report)
    groups = candidate_groups(rows, asset)
    store = Path(store) if store else ledger.folder / "bases"
    if top_k is None:
        top_k = config.load_config()["scan"]["top_k"]
    candidates = _rank(suspect, groups, top_k, store)
    result = _check_in_order(suspect, candidates, groups, materials, store, detect_params)
    checks = result.pop("checks")
    unchecked = [line for c in checks for line in c["unchecked"]]
    if unchecked and result["verdict"] != "match":      # never "no match" while copies went unchecked
        raise InputError(unchecked[0] + (f" (and {len(unchecked) - 1} more)" if len(unchecked) > 1 else ""))
    unheld = unheld_copies(report["unheld"], {c[0] for c in candidates}, sha256_file(suspect))
    if unheld and result["verdict"] == "no match":     # copies under keys not held may be what it is
        result["verdict"] = "inconclusive"
    result.update(unchecked=unheld_summary(unheld), n_unchecked=len(unheld))
    result.update(suspect=str(suspect), candidates=[c[0] for c in candidates], n_candidates_checked=len(checks),
                  seconds=[c["seconds"] for c in checks], ledger_version=ledger.version())
    return result
