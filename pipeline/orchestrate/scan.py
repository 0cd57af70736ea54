"""Leak scans on Dask: which asset, and which recipient, suspect files came from.

Suspects are every point-cloud file of ``scan.suspects`` (a folder,
recursively, a glob or one file), told apart by path and sha256, never by
stem.  A FIFO, a device, a socket, an empty file, a broken link or a link
that leads out of the suspects folder is refused from its metadata, before
anything opens, reads or hashes it: a failed row naming the path and why
(counted, retried by the next scan).

Per suspect: (1) a suspect that is a catalogue original's own bytes is no
match; (2) an exact sha256 match with an issued copy attributes at once;
(3) otherwise the top-K ledger assets by local-descriptor votes
(part-to-whole: crops, scenes) and the top-K by shape distribution (the
suspect whole, without outliers and object by object, against each asset
whole, cut and without outliers) are checked, alternately best-ranked first and until the
first match, through the one attribution
path (:mod:`pipeline.orchestrate.attribute`), each against every recipient
issued under the keys held; the verdict is corrected for every recipient of
every candidate planned.

Every issued copy the ledger holds is searched, in the current catalogue or
not: an asset whose original left the catalogue (deleted, moved, renamed) is
ranked and checked through a catalogue file with its bytes, its recorded
source path or the copy the run kept in the basis store.

Ledger rows are trusted only with a valid row MAC (:func:`held_rows`):
the others are set aside, counted in report.md, and never attribute or
accuse anyone.

Copies the scan cannot check: those under keys the secret does not open,
and those of assets whose original no file holds.  A suspect is affected
when its sha256 is the recorded sha256 of such a copy, or when it is not a
match and one of its candidate assets (ranked over every asset of the
ledger, whatever its key) has copies under keys not held; copies whose
original is lost cannot be ranked, so they affect every suspect that is not
a match.  An affected suspect is never "no match": it reads "inconclusive",
with ``n_unchecked`` and ``unchecked`` ("N copies under key ID (fingerprint
F)") in its row and report.md, and is scanned again when the secret opens
other keys (``keys_held``).

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

import hashlib
import json
import os
import sys
import time
from collections import defaultdict
from datetime import datetime, timezone
from pathlib import Path

import pyarrow as pa

from .. import __version__, config as config_mod
from ..io.catalog import glob_root, list_suspects, read_catalogue
from ..io.evidence import plain_text, render_match, write_summary
from ..io.ledger import Ledger
from ..io.manifest import read_rows, write_rows
from ..io.paths import check_apart, check_disjoint, source_folders
from ..io.pointcloud import InputError, atomic_write_bytes, read_points, sha256_file
from ..kernels.descriptor import d2_descriptor
from .attribute import (check_asset, decide, held_rows, laid_whole, original_files, params_from_row, unheld_copies,
                        unheld_summary)
from .candidates import (after_whole, build_index, candidates, cascade, holdings, load_index, planned_recipients,
                         triage, votes_without, whole_may_stop, whole_original, witness, witness_settings)
from .progress import Bar, Progress
from .reference import load_reference

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
    ("seconds_quick_registration", pa.float64()),
    ("seconds_deep_registration", pa.float64()),
    ("n_stopped", pa.int64()),
    ("status", pa.string()),
    ("error", pa.string()),
    ("note", pa.string()),
    ("n_unchecked", pa.int64()),
    ("unchecked", pa.string()),
    ("keys_held", pa.string()),
    ("tool_version", pa.string()),
    ("scanned_at", pa.timestamp("ms", tz="UTC")),
])


def _reference(cfg, secret):
    """What a scan checks against, read before any work: ledger rows, catalogue, the file of each asset."""
    sc = cfg["scan"]
    for name in ("suspects", "catalogue"):
        if not sc[name]:
            raise config_mod.ConfigError(f"config: scan.{name}: required for a scan")
    ledger = Ledger(sc["manifests"] or cfg["output"]["manifests"])
    report = {}
    rows, materials = held_rows(ledger, secret, report=report)      # refuses a secret that opens nothing
    catalogue = [r for r in read_catalogue(sc["catalogue"]) if r["status"] == "ok"]
    cat_version = hashlib.sha256("\n".join(sorted(r["sha256"] for r in catalogue)).encode()).hexdigest()[:16]
    issued, unheld = defaultdict(list), defaultdict(list)
    for r in rows:
        issued[r["asset_key"]].append(r)
    # rows set aside (no valid MAC) are copies the scan cannot check either: a suspect that may be one
    # of them is inconclusive, never "no match", and is checked again by the next scan (a seal may come)
    unchecked = report["unheld"] + [r for rs in report["untrusted"].values() for r in rs if r["status"] == "ok"]
    for r in unchecked:
        unheld[r["asset_key"]].append(r)
    originals = {r["sha256"] for r in catalogue} | {r["source_sha256"] for r in rows}
    # an issued copy with its original's bytes is no copy: it never attributes anything
    by_sha = {r["output_sha256"]: r for r in rows if r["output_sha256"] not in originals}
    store = str(Path(cfg["output"]["bases"] or ledger.folder / "bases"))
    paths, lost = _asset_files(catalogue, Path(sc["catalogue"]).resolve().parent, {**unheld, **issued}, store)
    descriptors = {r["asset_key"]: r["descriptor"] for r in catalogue if r["asset_key"] in paths}
    return {"ledger": ledger, "materials": materials, "issued": issued, "unheld": unheld, "by_sha": by_sha,
            "unheld_sha": {r["output_sha256"]: r for r in unchecked}, "originals": originals,
            "descriptors": descriptors, "cat_version": cat_version,
            "assets": {r["asset_key"]: r["sha256"] for r in catalogue}, "paths": paths, "lost": lost,
            "untrusted": report["untrusted"], "store": store,
            "keys_held": ",".join(sorted({r["key_fingerprint"] for r in rows}))}


def _asset_files(catalogue, base, ledger_assets, store):
    """The file each ledger asset is ranked by, and the assets no file holds.

    The catalogue's file of that key; else (the original moved, renamed or
    deleted and the catalogue rebuilt) a catalogue file with the bytes the
    copies were issued from, the source path recorded, or the copy a run kept
    in the basis store (:func:`pipeline.orchestrate.attribute.original_files`):
    a scan checks every issued copy the ledger holds, in the catalogue or not.

    Returns
    -------
    paths : dict asset key -> Path
    lost : dict asset key -> list of dict (its rows: copies no file can be checked against)
    """
    by_key = {r["asset_key"]: r for r in catalogue}
    by_sha = {r["sha256"]: r for r in catalogue}
    paths, lost = {}, {}
    for asset, rows in ledger_assets.items():
        if asset in by_key:
            row = by_key[asset]
        else:
            row = next((by_sha[r["source_sha256"]] for r in reversed(rows) if r["source_sha256"] in by_sha), None)
        if row is not None:
            paths[asset] = Path(row["path"]) if Path(row["path"]).is_absolute() else base / row["path"]
            continue
        found, _ = original_files(rows, (), store)
        newest = next((found[r["source_sha256"]] for r in reversed(rows) if r["source_sha256"] in found), None)
        if newest is None:
            lost[asset] = rows
        else:
            paths[asset] = Path(newest)
    return paths, lost


def _ranked_by(ref, out):
    """The candidate index (kept in ``out``) and each asset's whole-shape descriptor where the index lacks it.

    Assets outside the catalogue have no catalogue descriptor: theirs is
    computed from their file when the index lacks them; one no file can be
    read for joins ``ref["lost"]``.
    """
    extra = sorted(set(ref["paths"]) - set(ref["descriptors"]))
    version = ref["cat_version"]
    if extra:      # a catalogue version's index never mixes with one that ranks ledger-only assets
        version = hashlib.sha256((version + "\n".join(f"{a}={ref['paths'][a]}" for a in extra)).encode()).hexdigest()[:16]
    index_path = build_index(out, version, ref["paths"])
    indexed = set(load_index(index_path).keys) if index_path else set()
    descriptors = dict(ref["descriptors"])
    for asset in extra:
        if asset not in indexed:
            try:
                points = read_points(ref["paths"][asset]).points
            except InputError:
                ref["lost"][asset] = ref["issued"].get(asset, []) + ref["unheld"].get(asset, [])
                continue
            descriptors[asset] = d2_descriptor(points - points.mean(axis=0))
    return index_path, descriptors


def _result_path(out, sha, versions, failed=False):
    if failed:
        return Path(out) / "results" / f"{sha[:32]}.failed.parquet"
    return Path(out) / "results" / f"{sha[:32]}-{versions[0]}-{versions[1]}.parquet"


def run_scan(cfg, secret, *, force=False):
    """``pointmark scan``: returns the exit status."""
    from .run import start_client

    sc = cfg["scan"]
    ref = _reference(cfg, secret)
    ledger = ref["ledger"]
    versions = (ledger.version(), ref["cat_version"])
    out = Path(sc["out"])
    suspects, others = _suspects(sc["suspects"], out)
    catalogue_files = [p for p in ref["paths"].values()]
    check_apart([("scan.out", out)],
                [("suspects folder", f) for f in source_folders(sc["suspects"])],
                catalogue_files)
    detect_params = config_mod.detect_params(cfg)
    store = ref["store"]
    check_disjoint(("scan.out", out), [("the ledger", ledger.folder), ("the basis store", store),
                                      ("output.dir", cfg["output"]["dir"])])
    client, cluster = start_client(cfg)          # the scheduler is reached before anything is written
    try:
        counts, notices = _scan(client, cfg, ref, out, versions, suspects, others, force)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    summary = write_summary(read_scan(out), out / "report.md", detect_params.epsilon, notices)
    print(f"scanned {sum(counts[k] for k in _VERDICTS + ('skipped',))} suspects in {counts.pop('seconds'):.0f}s: "
          f"{counts['match']} match, "
          f"{counts['inconclusive']} inconclusive, {counts['no match']} no match, {counts['failed']} failed, "
          f"{counts['skipped']} already scanned; results in {out}, evidence report {summary}")
    if counts["failed"]:
        return 3
    return 1 if counts["match"] else 0


_VERDICTS = ("match", "no match", "inconclusive", "failed")
FOLLOW_POLL = 2.0     # seconds between listings of the suspects folder while scan.follow keeps it open


def _scan(client, cfg, ref, out, versions, suspects, others, force):
    """The scan's work once the scheduler is reached: the verdict counts (and seconds) and the notices."""
    out.mkdir(parents=True, exist_ok=True)
    state = _save_state(out, versions, [p.name for p in ref["ledger"].parts()], ref["assets"])
    index_path, descriptors = _ranked_by(ref, out)
    notices = _notices(ref, others)
    for line in notices:
        print(f"[pointmark] scan: {plain_text(line, 1000)}", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    work = _Work(client, cfg, ref, out, versions, state, {} if force else _previous(out), index_path, descriptors)
    work.progress.start_scan(len(suspects))
    work.submit(suspects)
    watch, polled, follow = {"seen": {p for p, _ in suspects}, "stat": {}}, time.monotonic(), cfg["scan"]["follow"]
    while True:
        for fut in work.pending:
            if follow and time.monotonic() - polled >= FOLLOW_POLL:    # files that appeared meanwhile
                work.submit(_new_suspects(cfg["scan"]["suspects"], out, watch, work.progress))
                polled = time.monotonic()
            work.done(fut)
        new = _new_suspects(cfg["scan"]["suspects"], out, watch, work.progress, wait=follow) if follow else []
        if not new:
            break
        work.submit(new)
    work.progress.finish()
    return {**work.counts, "seconds": time.perf_counter() - t0}, notices


class _Work:
    """A scan's suspects in flight: their triage, their candidate checks in order, their verdicts."""

    def __init__(self, client, cfg, ref, out, versions, state, previous, index_path, descriptors):
        from distributed import as_completed

        self.client, self.cfg, self.ref, self.out, self.versions = client, cfg, ref, out, versions
        self.state, self.previous, self.descriptors = state, previous, descriptors
        self.detect_params = config_mod.detect_params(cfg)
        *self.gates, self.twin_shape = config_mod.cascade_gates(cfg)
        self.witnessing = witness_settings(self.detect_params)
        # absolute paths: a worker of an existing cluster has its own working directory; the index's
        # hash, taken once here, spares each triage reading and hashing the index again
        self.index = (os.path.abspath(index_path), sha256_file(index_path)) if index_path else (None, None)
        self.counts = dict.fromkeys(_VERDICTS + ("skipped",), 0)
        self.progress = Progress.for_stream(cfg["dask"]["progress"], sys.stderr)
        self.triages, self.waiting, self.shared, self.pending = {}, {}, {}, as_completed()

    def tally(self, verdict):
        self.counts[verdict] += 1
        self.progress.suspect_done(verdict)

    def submit(self, listed):
        """Triage the readable suspects not scanned against these versions before (skipped unhashed)."""
        for path, why in listed:            # refused from its metadata: never opened, read or hashed
            if why is not None:
                _record(self.out, self.versions, {"suspect_path": str(path)}, "failed", error=f"{path}: {why}")
                self.tally("failed")
        readable = [p for p, why in listed if why is None]
        # suspects already scanned against these versions are skipped before any
        # work (hashing is cheap; ranking a suspect against the catalogue is not)
        done = {p for p in readable if self.previous and _already(self.previous.get(_sha_or_none(p)),
                                                                   self.versions, self.ref["keys_held"])}
        for p in readable:
            if p in done:
                self.tally("skipped")
                continue
            fut = self.client.submit(triage, os.path.abspath(p), self.descriptors, *self.index,
                                     twin_shape=self.twin_shape, pure=False)
            self.triages[fut] = p
            self.pending.add(fut)

    def done(self, fut):
        """One finished triage or check: the suspect's next step, or its verdict."""
        if fut in self.triages:
            self._triaged(self.triages.pop(fut), fut)
        elif fut in self.shared:
            self._after_whole(self.shared.pop(fut), fut)
        else:
            self._checked(self.waiting.pop(fut), fut)

    def _triaged(self, path, fut):
        out, versions, ref, sc = self.out, self.versions, self.ref, self.cfg["scan"]
        if fut.status != "finished":
            _record(out, versions, {"suspect_path": str(path)}, "failed", error=_text(fut.exception()))
            self.tally("failed")
            return
        info = {**fut.result(), "path": str(path)}          # recorded as the folder listed it
        prev = self.previous.get(info["sha256"])
        if _already(prev, versions, ref["keys_held"]):   # the same bytes twice in the folder
            self.tally("skipped")
            return
        verdict = _quick(info, ref, out, versions)
        if verdict:
            self.tally(verdict)
            return
        view = _scope(ref["issued"], prev, self.state, out)
        info["prev"] = prev
        info["candidates"] = candidates(info, set(view) | set(ref["unheld"]), sc["top_k"], sc["shape_margin"])
        info["unheld"] = unheld_copies([r for rows in ref["unheld"].values() for r in rows],
                                       set(info["candidates"]), info["sha256"])
        info["lost"] = [r for rows in ref["lost"].values() for r in rows]
        checked = [a for a in info["candidates"] if a in view]
        # candidates are checked best-ranked first and the search stops at the
        # first match; the cascade registers some only partly, others not at all:
        # the threshold counts every recipient of every candidate planned, so
        # neither adds a chance to accuse
        info["planned"] = planned_recipients([view[a] for a in checked], ref["materials"])
        info["checks"], info["errors"] = [], []
        stage = cascade(info, checked, *self.gates)
        info["stopped"] = sum(stage[a] is None for a in checked)      # not registered at all
        info["queue"] = [(a, view[a], [str(ref["paths"][a])] if a in ref["paths"] else [], stage[a])
                         for a in checked if stage[a] is not None]
        if not self._submit_next(info):
            self._finished(info)

    def _checked(self, info, fut):
        stage = info.pop("stage")
        if fut.status == "finished":
            info["checks"].append(fut.result())
            if "whole" in info:         # a check after the suspect was laid whole: what it witnessed is kept
                witness(self.ref["store"], info["whole_original"], fut.result(), stage == "deep", info["sha256"],
                        self.witnessing)
        else:
            info["errors"].append(_text(fut.exception()))
        matched = decide(info["checks"], self.detect_params.epsilon, _prior(info), info["planned"])["accused"]
        if (not matched and "whole" not in info and self.index[0] and info["checks"] and laid_whole(info["checks"][-1])
                and whole_may_stop({a: s for a, _, _, s in info["queue"]}, *self.gates[:2])):
            # laid whole on one original: which other candidates may hold its surface
            info["whole_original"] = whole_original(info["checks"][-1])
            info["whole"] = info["whole_original"]["asset_key"]
            info["held"] = holdings(self.ref["store"], info["whole_original"],
                                    {a: {r["source_sha256"] for r in rows} for a, rows, _, s in info["queue"] if s},
                                    self.witnessing)
            if all(h is not None for h in info["held"].values()):     # each one witnessed before: not ranked
                self._after_whole(info, None)
                return
            fut = self.client.submit(votes_without, os.path.abspath(info["path"]), *self.index, info["whole"],
                                     self.twin_shape, pure=False, priority=1)
            self.shared[fut] = info
            self.pending.add(fut)
            return
        if matched or not self._submit_next(info):
            self._finished(info)

    def _finished(self, info):
        verdict = _finish(self.out, self.versions, info, self.detect_params.epsilon, self.ref["store"],
                          self.ref["keys_held"])
        self.tally(verdict)
        if not isinstance(self.progress, Bar):             # the bar says it on its own line
            print(f"[pointmark] scan: {plain_text(info['path'])}: {verdict}", file=sys.stderr, flush=True)

    def _after_whole(self, info, fut):
        """The queue once a check laid the suspect whole on an original (:func:`after_whole`).

        ``fut`` is the ranking without that original (:func:`votes_without`); where it failed,
        every stage is kept that no witness decides.  None: every candidate left was witnessed
        before, and it was not ranked.
        """
        without = {} if fut is None else None
        if fut is not None and fut.status == "finished":
            without = fut.result()["votes"]
            info["seconds"] += fut.result()["seconds"]       # counted with the candidate search
        stage = after_whole(info, {a: s for a, _, _, s in info["queue"]}, info["whole"], *self.gates[:2], without,
                            info["held"])
        info["stopped_whole"] = sum(stage[a] is None for a, _, _, _ in info["queue"])
        info["stopped_held"] = sum(stage[a] is None and info["held"].get(a) is False for a, _, _, _ in info["queue"])
        info["stopped"] += info["stopped_whole"]
        info["queue"] = [(a, rows, places, stage[a]) for a, rows, places, _ in info["queue"] if stage[a] is not None]
        if not self._submit_next(info):
            self._finished(info)

    def _submit_next(self, info):
        """Submit the suspect's next candidate check; False when none is left.

        Checks run before the triage of further suspects (higher priority), so
        verdicts come out while a large folder is still being ranked.
        """
        if not info["queue"]:
            return False
        _, rows, places, stage = info["queue"].pop(0)
        info["stage"] = stage
        fut = self.client.submit(check_asset, os.path.abspath(info["path"]), rows, self.ref["materials"],
                                 os.path.abspath(self.ref["store"]), self.detect_params,
                                 places=[os.path.abspath(p) for p in places], deep=stage == "deep", pure=False,
                                 priority=1)
        self.waiting[fut] = info
        self.pending.add(fut)
        return True


def _new_suspects(source, out, watch, progress, wait=0.0):
    """Suspect files that appeared since the last listing, once settled, for ``scan.follow``.

    A new file is taken when its size and modification time are the same at
    two listings :data:`FOLLOW_POLL` seconds or more apart (a crawler may
    still be writing it); hidden files (temporary names) are never suspects.
    With ``wait``, lists again every :data:`FOLLOW_POLL` seconds until one
    is taken or ``wait`` seconds pass.

    Parameters
    ----------
    source : str, ``scan.suspects``
    out : Path, ``scan.out``
    watch : dict
        ``seen`` (set of Path, taken already) and ``stat`` (Path -> (size,
        mtime) at its last listing), updated here.
    progress : Progress
        Its count of suspects grows by those taken.
    wait : float

    Returns
    -------
    list of (Path, str or None), as :func:`_suspects`
    """
    deadline = time.monotonic() + wait
    while True:
        try:
            listed, _ = _suspects(source, out)
        except config_mod.ConfigError:       # a glob that matches nothing now
            listed = []
        taken = []
        for path, why in listed:
            if path in watch["seen"]:
                continue
            try:
                st = path.lstat()
                now = (st.st_size, st.st_mtime_ns)
            except OSError:
                continue
            if why is not None or watch["stat"].get(path) == now:
                taken.append((path, why))
            watch["stat"][path] = now
        if taken or time.monotonic() >= deadline:
            break
        time.sleep(FOLLOW_POLL)
    watch["seen"].update(p for p, _ in taken)
    progress.assets += len(taken)
    return taken


def _suspects(source, out):
    """Every suspect file (path, why it is refused or None), checked before anything is written.

    Raises
    ------
    ConfigError
        ``scan.suspects`` is the scan's own output folder or inside it, or
        a glob that matches no point-cloud file.
    """
    where = glob_root(str(source))
    if where.resolve() == out.resolve() or out.resolve() in where.resolve().parents:
        raise config_mod.ConfigError(f"config: scan.suspects: {plain_text(source)} is inside scan.out "
                                     f"({plain_text(out)}), the scan's own results")
    try:
        suspects, others = list_suspects(source)
    except InputError as exc:
        raise config_mod.ConfigError(f"config: scan.suspects: {exc}") from None
    if not suspects and any(ch in str(source) for ch in "*?["):
        raise config_mod.ConfigError(f"config: scan.suspects: {plain_text(source)} matches no point-cloud file "
                                     f"({len(others)} other files)")
    return suspects, others


def _notices(ref, others):
    """Lines the scan says once, on stderr and in report.md: what it could not check or trust."""
    lines = []
    if ref["untrusted"]:
        n = sum(len(v) for v in ref["untrusted"].values())
        lines.append(f"{n} ledger row(s) set aside as untrusted (row MAC missing or wrong), never used to accuse: "
                     + ", ".join(f"{part} ({len(v)})" for part, v in sorted(ref["untrusted"].items())))
    unheld = [r for rows in ref["unheld"].values() for r in rows]
    if unheld:
        lines.append(f"unchecked: {unheld_summary(unheld)}, which the secret does not open: suspects that may "
                     f"be one of them read inconclusive, never no match (scan again with that secret)")
    if ref["lost"]:
        n = sum(len(v) for v in ref["lost"].values())
        lines.append(f"unchecked: {n} issued copies of {len(ref['lost'])} asset(s) whose original no file holds "
                     f"(not in the catalogue, nor at the recorded path, nor kept in the basis store): "
                     + ", ".join(sorted(ref["lost"])[:10]))
    if others:
        lines.append(f"{len(others)} file(s) of other formats or hidden (temporary) among the suspects were not "
                     f"scanned, e.g. {others[0]}")
    return lines


def _prior(info):
    return (info.get("prev") or {}).get("n_checked") or 0


def _sha_or_none(path):
    """The file's sha256, or None when it cannot be read (its triage then fails and is recorded)."""
    try:
        return sha256_file(path)
    except OSError:
        return None


def _already(prev, versions, keys_held):
    """True when a suspect's last result was against these ledger and catalogue versions.

    A result that left copies unchecked (keys not held, or originals no file
    held) is always redone: the key or the original may be back.
    """
    return (prev is not None and (prev["ledger_version"], prev["catalogue_version"]) == versions
            and not prev.get("n_unchecked"))


def _text(exc):
    return str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"


def _quick(info, ref, out, versions):
    """Verdicts that need no detection: an original's own bytes, an exact issued copy (held key or not)."""
    if info["sha256"] in ref["originals"]:
        _record(out, versions, info, "no match", error="the suspect is a catalogue original's own bytes")
        return "no match"
    row = ref["by_sha"].get(info["sha256"])
    if row is None:
        row = ref["unheld_sha"].get(info["sha256"])
        if row is None:
            return None
        _record(out, versions, info, "inconclusive", candidate_asset=row["asset_key"], n_unchecked=1,
                unchecked=unheld_summary([row]), keys_held=ref["keys_held"],
                note=f"the exact bytes of a copy issued under key {row['key_id']} (fingerprint "
                     f"{row['key_fingerprint']}), which the secret does not open: scan again with that secret")
        return "inconclusive"
    _record(out, versions, info, "match", candidate_asset=row["asset_key"], recipient=row["recipient"],
            key_id=row["key_id"], generation=row["generation"], p_value=0.0, keys_held=ref["keys_held"],
            accused_json=json.dumps([{"recipient": row["recipient"], "asset_key": row["asset_key"],
                                      "exact_sha256": True}]))
    return "match"


def render_evidence(suspect_path, original_path, accused, store, path):
    """The evidence picture of one accusation (see :func:`pipeline.io.evidence.render_match`)."""
    original = read_points(original_path).points
    ref = load_reference(original, params_from_row(accused["reference"]), store, accused["reference_key"],
                         accused["reference"]["digests"])
    title = (f"{Path(suspect_path).name}: issued copy of {accused['asset_key']} to {accused['recipient']} "
             f"(generation {accused['copies'][-1][0]}), score {accused['score']:.1f}, p = {accused['p_value']:.2g}, "
             f"margin {accused['margin']:.1f}")
    return render_match(original, read_points(suspect_path).points, {**accused["registration"], "centre": ref.centre},
                        [s.members for s in ref.specs], accused["cluster_scores"], title, path)


def _finish(out, versions, info, epsilon, store, keys_held):
    if info["errors"]:     # a check that raised is never "no match": retried next scan
        _record(out, versions, info, "failed", error="; ".join(info["errors"]))
        return "failed"
    prev = info.get("prev")
    result = decide(info["checks"], epsilon, _prior(info), info.get("planned", 0))
    # (an earlier "inconclusive" for copies it could not check is no finding: it is redone)
    if prev is not None and result["verdict"] != "match" and (
            prev["verdict"] == "match" or (prev["verdict"] == "inconclusive" and not prev.get("n_unchecked"))):
        # what was found before stands; the new copies and assets did not change it
        carried = {k: prev[k] for k in SCAN_SCHEMA.names if k in prev and k not in ("scanned_at", "ledger_version",
                                                                                     "catalogue_version")}
        _record(out, versions, info, prev["verdict"], **{k: v for k, v in carried.items() if k not in
                                                        ("suspect_path", "suspect_sha256", "n_points", "verdict",
                                                         "status", "tool_version", "schema_version", "note",
                                                         "keys_held")},
                keys_held=keys_held,
                note=f"checked {result['n_checked'] - (prev.get('n_checked') or 0)} more recipients; "
                     f"the verdict of {prev['scanned_at']:%Y-%m-%d %H:%M} stands")
        return prev["verdict"]
    unchecked = [line for c in info["checks"] for line in c.get("unchecked", [])]
    if unchecked and result["verdict"] != "match":
        # copies whose original no file holds may be what this is: failed (retried), never "no match"
        _record(out, versions, info, "failed", error="; ".join(unchecked), n_checked=result["n_checked"])
        return "failed"
    unheld = info.get("unheld", []) + (info.get("lost", []) if result["verdict"] != "match" else [])
    if unheld and result["verdict"] == "no match":
        # copies it may be were not checked (keys not held, originals nowhere): never "no match"
        result["verdict"] = "inconclusive"
    top = result["accused"][0] if result["accused"] else None
    evidence, notes = None, []
    if top is not None and top.get("cluster_scores") is not None:
        evidence = out / "evidence" / f"{info['sha256'][:32]}-{versions[0]}-{versions[1]}.png"
        try:
            render_evidence(info["path"], top["original_path"], top, store, evidence)
        except (ValueError, OSError) as exc:          # the accusation stands without its picture
            evidence = None
            notes.append(f"no evidence picture: {_text(exc)}")
    stopped = info.get("stopped", 0) + sum(c.get("stopped", 0) for c in info["checks"])
    if stopped and result["verdict"] != "match":
        why = ("no whole copy found, and too few descriptor votes and too far in shape to hold a part of one "
               "(scan.deep_votes, deep_shape, quick_shape)")
        if info.get("stopped_whole"):
            why += (f"; or, the suspect lying whole on {info['whole']}'s original with nothing beside it, neither "
                    f"of its shape nor holding its surface")
        if info.get("stopped_held"):
            why += (f" ({info['stopped_held']} of them registered before on a copy laid whole on that original, "
                    f"which lay on them nowhere)")
        notes.append(f"{stopped} candidate original(s) stopped by the cascade: {why}; their recipients count "
                     f"in the threshold")
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
            seconds_quick_registration=sum(s.get("quick", 0.0) for s in seconds),
            seconds_deep_registration=sum(s.get("deep", 0.0) for s in seconds),
            n_stopped=stopped,
            seconds_detection=sum(s["estimate"] + s["scoring"] for s in seconds),
            evidence_path=None if evidence is None else str(evidence), keys_held=keys_held,
            n_unchecked=len(unheld) or None, unchecked=_unchecked_text(info) or None,
            note="; ".join(notes + ([f"unchecked: {_unchecked_text(info)}"] if unheld else [])) or None)
    return result["verdict"]


def _unchecked_text(info):
    """What a suspect's result could not check: copies under keys not held, copies whose original is lost."""
    parts = [unheld_summary(info.get("unheld", []))]
    lost = info.get("lost", [])
    if lost:
        parts.append(f"{len(lost)} cop{'y' if len(lost) == 1 else 'ies'} whose original no file holds")
    return "; ".join(p for p in parts if p)


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
    """Issued rows a suspect must be checked against: all, or those added (or opened) since its last scan.

    A last scan that left copies unchecked (keys not held, originals no file
    held) saw only part of what it should have: the suspect is checked
    against everything again.
    """
    if prev is None or prev.get("n_unchecked"):
        return issued
    folder = Path(out) / "state"
    try:
        parts = set(json.loads((folder / f"ledger-{prev['ledger_version']}.json").read_text()))
        assets = json.loads((folder / f"catalogue-{prev['catalogue_version']}.json").read_text())
    except (OSError, ValueError):
        return issued                       # no record of what it saw: check everything again
    view = {}
    held_then = set((prev.get("keys_held") or "").split(",")) if prev.get("keys_held") is not None else None
    for asset, rows in issued.items():
        new_asset = assets.get(asset) != state["assets"].get(asset)
        keep = [r for r in rows if new_asset or r["ledger_part"] not in parts
                or (held_then is not None and r["key_fingerprint"] not in held_then)]
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
    for name in ("error", "note"):       # one line, bounded: a file's content never starts a line of its own
        if row.get(name) is not None:
            row[name] = plain_text(row[name], 2000)
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
