"""Run the catalogue job: plan against the ledger, execute on Dask (or serially), append rows.

Per asset the graph is ``plan_asset`` -> one ``cluster_task`` per cluster ->
``issue_task`` per chunk of recipients.  Cluster tasks are submitted when
their asset's plan arrives, so the eigendecompositions of all clusters of
all assets run in parallel across workers.

The ledger is append-only: a run issues only copies it does not hold yet.
Changed parameters, key, tool version or source bytes start a new
generation of the asset (new file names, new rows); earlier rows stay.
Each asset is locked while it is planned and issued, and the plan is
redone under the locks, so concurrent runs never issue the same copy twice
or lose a row.

Every check comes before any write: the catalogue, recipients, output
folders (never inside an input, never holding an asset), planned copy paths
(each distinct from every other planned or recorded one) and the Dask
scheduler.  Only then are the ledger folder, its salt and locks created.
A copy is published under its final name only after its row is durable
(see :mod:`pipeline.io.ledger`); an interrupted run's intents are finished
or undone by the next run of the same assets.
"""

from __future__ import annotations

import errno
import hashlib
import json
import logging
import os
import sys
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from .. import __version__, threads
from ..config import ConfigError, marking_rule, watermark_params
from ..io.basis_store import BasisStore
from ..io.catalog import check_recipient, discover_assets
from ..io.ledger import Ledger, LedgerError, mac_ok
from ..io.paths import check_apart, check_disjoint, copy_path, pending_path, source_folders
from ..io.pointcloud import InputError, read_points, sha256_file, units_of
from ..io.secrets import without_secret_env
from ..kernels import keys
from ..watermark import ADDED_LATER, band_applies, band_for, params_record
from . import tasks
from .progress import Progress

log = logging.getLogger("pointmark.run")

__all__ = ["Job", "plan_job", "run_job", "start_client", "PINNED_THREADS", "WORKER_ENV", "CHUNK"]

# BLAS and OpenMP threads of every worker: one, so processes do not oversubscribe cores
PINNED_THREADS = threads.PINNED
# What a spawned worker starts with: the pinned threads, and glibc returning freed memory to the
# system at 64 KiB (Dask's own default, which a replaced pre-spawn-environ would drop): without it
# the blocks of a large tile's read-back and measures stay resident, 0.2-0.7 GB on 10M points.
WORKER_ENV = {"MALLOC_TRIM_THRESHOLD_": "65536", **PINNED_THREADS}

CHUNK = 32   # recipients per issue task
MARK = "fingerprint"


@dataclass
class AssetJob:
    key: str
    path: Path
    source_sha256: str
    generation: int = 1
    generation_id: str = ""
    items: list = field(default_factory=list)     # (recipient, output path) to issue
    issued: int = 0                               # copies of this generation already in the ledger
    missing: list = field(default_factory=list)   # issued copies whose file is gone
    error: str | None = None
    params: object = None                         # WatermarkParams resolved for this asset
    rule: str | None = None                       # how auto parameters were resolved (survey data)
    note: str | None = None                       # why a new generation starts, when earlier ones exist


@dataclass
class Job:
    run_id: str
    key_id: str
    key_fingerprint: str
    key_salt: str
    material: bytes = field(repr=False)
    mac_key: bytes = field(default=b"", repr=False)     # authenticates ledger rows; never sent to workers
    new_salt: bool = False                              # the salt is this run's: recorded when it starts
    params: object = None                               # the config's, for an asset that is not survey data
    cfg: dict = field(default=None, repr=False)         # resolves auto parameters per asset
    ledger: Ledger = None
    store: Path = None
    assets: list = field(default_factory=list)
    ledger_version: str = ""
    replan: object = field(default=None, repr=False)

    @property
    def manifests(self):
        return self.ledger.folder

    @property
    def todo(self):
        return [a for a in self.assets if a.items or a.error]


# Fields added after a ledger format was first written are left out of the
# generation id at the value a record without them meant (ADDED_LATER), so a
# rerun of an older ledger with an unchanged config stays in its generation
# Issued copies carry recipient fingerprints, not the message: its channel code changes no copy.
_NOT_IN_COPIES = ("code",)


def _generation_id(params, key_id, fingerprint, source_sha256):
    record = {k: v for k, v in params_record(params).items()
              if k not in _NOT_IN_COPIES and not (k in ADDED_LATER and v == ADDED_LATER[k])}
    text = json.dumps({"params": record, "key_id": key_id, "fp": fingerprint, "mark": MARK,
                       "source": source_sha256, "version": __version__}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def recipients_of(asset, configured, where):
    """The asset's recipients: its catalogue's, then the config's; "default" if none."""
    names = list(dict.fromkeys([*asset.recipients, *configured])) or ["default"]
    return [check_recipient(r, where) for r in names]


def plan_job(cfg, secret, *, force=False, shard=None, create=True):
    """Everything the run will do, without doing it, and without writing anything.

    Parameters
    ----------
    cfg : dict
        Validated config.
    secret : bytes
    force : bool
        Also re-write issued copies whose file is missing (same bytes).
    shard : (int, int), optional
        (i, n): only assets i, i + n, i + 2n, ... (sorted by key).
    create : bool
        Unused (kept for callers): a plan never writes; :func:`run_job`
        records a new ledger's salt.

    Returns
    -------
    Job

    Raises
    ------
    InputError, ConfigError, LedgerError
        A check failed; nothing was written.
    """
    params = watermark_params(cfg)
    key_id = cfg["key"]["id"]
    if not key_id:
        raise ConfigError("config: key.id: a key id is needed for a catalogue run")
    if not cfg["catalog"]["source"]:
        raise ConfigError("config: catalog.source: name a folder, glob or catalogue file")
    out = cfg["output"]
    all_assets = discover_assets(cfg["catalog"]["source"])
    store = Path(out["bases"] or Path(out["manifests"]) / "bases")
    check_apart([("output.dir", out["dir"]), ("output.manifests", out["manifests"]), ("output.bases", store)],
                [("catalogue folder", f) for f in source_folders(cfg["catalog"]["source"])],
                [a.path for a in all_assets])
    check_disjoint(("output.dir", out["dir"]), [("output.manifests", out["manifests"]), ("output.bases", store)])
    ledger = Ledger(out["manifests"])
    version = ledger.version()
    salt = ledger.salt()
    new_salt = salt is None
    salt = salt or keys.new_salt()
    fingerprint = keys.key_fingerprint(secret, salt)
    job = Job(uuid.uuid4().hex[:16], key_id, fingerprint, salt, keys.derive_key_material(secret, key_id),
              keys.ledger_mac_key(secret), new_salt, params, cfg, ledger, store, ledger_version=version)
    job.replan = lambda: plan_job(cfg, secret, force=force, shard=shard)
    assets = all_assets[shard[0]::shard[1]] if shard is not None else all_assets
    recorded = ledger.rows(status=None)
    _check_deployment(recorded, salt, key_id, fingerprint, ledger)
    _check_macs(recorded, fingerprint, job.mac_key, ledger)
    issued = {}
    for row in recorded:
        if row["status"] == "ok":
            issued.setdefault(row["asset_key"], []).append(row)
    for asset in assets:
        recipients = recipients_of(asset, cfg["recipients"], cfg["catalog"]["source"])
        job.assets.append(_plan_asset(job, asset, recipients, issued.get(asset.key, []), Path(out["dir"]), force))
    _check_copy_paths(job, recorded)
    return job


def _check_deployment(recorded, salt, key_id, fingerprint, ledger):
    """Refuse a salt no row was issued under, or a secret that is not the one the key id was issued under.

    Either would silently start a new generation of every asset: a
    ``deployment.json`` restored from another ledger, or a wrong key file.
    """
    if recorded and salt not in {r["key_salt"] for r in recorded}:
        raise InputError(f"{ledger.folder / 'deployment.json'}: its salt is not the one the ledger's rows were "
                         f"issued under (restored from another ledger?); restore this ledger's own")
    prints = {r["key_fingerprint"] for r in recorded if r["key_id"] == key_id and r["key_salt"] == salt}
    if prints and fingerprint not in prints:
        raise InputError(f"config: key.id: {key_id} was issued under another secret (fingerprint "
                         f"{', '.join(sorted(prints))}, this one gives {fingerprint}): a wrong secret or key file? "
                         f"A new secret needs a new key id")


def _check_macs(recorded, fingerprint, mac_key, ledger):
    """Refuse to plan on rows under this secret's key that carry no valid MAC (added or altered by hand)."""
    bad = [r for r in recorded if r["key_fingerprint"] == fingerprint and not mac_ok(mac_key, r)]
    if bad:
        parts = sorted({r["ledger_part"] for r in bad})
        raise LedgerError(f"{ledger.copies / parts[0]}: {len(bad)} row(s) under this key without a valid row MAC "
                          f"(in {len(parts)} part file(s)): added or altered without the secret? Move the part "
                          f"out; rows written before MACs are sealed with pointmark ledger seal LEDGER")


def _plan_asset(job, asset, recipients, rows, out_dir, force):
    item = AssetJob(asset.key, asset.path, "")
    if asset.error or not asset.path.is_file():      # a link out of the catalogue folder is not read
        item.error = asset.error or f"{asset.path}: no such file"
        item.items = [(r, None) for r in recipients]
        return item
    item.source_sha256 = sha256_file(asset.path)
    units = units_of(asset.path)
    try:
        item.params = watermark_params(job.cfg, units)
        # the band follows the asset's sampling (records hold what acted: band_noise null)
        item.params = band_for(item.params, read_points(asset.path).points if band_applies(item.params) else None)
    except ValueError as exc:                        # no parameters for this asset: a failed row, not a stop
        item.error, item.params = f"{asset.path}: {exc}", job.params
        item.items = [(r, None) for r in recipients]
        return item
    item.rule = marking_rule(job.cfg, units)
    item.generation_id = _generation_id(item.params, job.key_id, job.key_fingerprint, item.source_sha256)
    # only this key's rows (their MACs were checked) say what is issued; every key's rows number generations
    same = [r for r in rows if r["generation_id"] == item.generation_id and r["key_fingerprint"] == job.key_fingerprint]
    item.generation = same[0]["generation"] if same else 1 + max((r["generation"] for r in rows), default=0)
    mine = [r for r in rows if r["key_fingerprint"] == job.key_fingerprint and r["status"] == "ok"]
    if not same and mine:          # say why a new generation starts (e.g. a default that changed)
        item.note = _why_new(json.loads(max(mine, key=lambda r: r["generation"])["params_json"]), item)
    if item.generation >= 2**31 - 1:
        raise InputError(f"{job.ledger.copies}: a row of {asset.key} claims generation {item.generation - 1}: "
                         f"not a ledger this tool wrote (a forged row?)")
    done = {r["recipient"] for r in same}
    item.issued = len(done)
    item.missing = sorted({r["recipient"] for r in same if not Path(r["output_path"]).is_file()})
    redo = set(item.missing) if force else set()
    item.items = [(r, copy_path(out_dir.resolve(), r, asset.key, item.generation, asset.path.suffix.lower()))
                  for r in recipients if r not in done or r in redo]
    return item


def _why_new(last, item):
    """One line: what differs from the last generation issued of this asset (parameters, or its bytes)."""
    now = params_record(item.params)
    changed = [f"{k} {last.get(k, ADDED_LATER.get(k))!r} -> {now[k]!r}" for k in sorted(now)
               if k not in _NOT_IN_COPIES and last.get(k, ADDED_LATER.get(k)) != now[k]]
    if not changed:
        return f"generation {item.generation}: the original's bytes, the key or the tool version changed"
    return (f"generation {item.generation}: {', '.join(changed)}; pin the earlier values in the config to stay "
            f"in the earlier generation")


def _check_copy_paths(job, recorded):
    """Refuse planned copy paths that equal another planned or recorded one, or an unrecorded file."""
    owner = {}
    for r in recorded:
        if r["output_path"] and r["status"] == "ok":
            owner.setdefault(str(r["output_path"]), (r["asset_key"], r["generation"], r["recipient"]))
    planned = {}
    for item in job.assets:
        for recipient, path in item.items:
            if path is None:
                continue
            me, text = (item.key, item.generation, recipient), str(path)
            other = planned.get(text) or (owner.get(text) if owner.get(text) != me else None)
            if other is not None:
                raise InputError(f"{path}: planned for {item.key} (generation {item.generation}, {recipient}) "
                                 f"but also the copy of {other[0]} (generation {other[1]}, {other[2]}); "
                                 f"rename one of the assets")
            if text not in owner and (path.exists() or path.is_symlink()):
                raise InputError(f"{path}: exists, and no ledger row records it as an issued copy; move it "
                                 f"away (it may be a copy of an interrupted older run) and run again")
            planned[text] = me


def _row_base(job, item):
    params = params_record(item.params or job.params)
    return {"run_id": job.run_id, "generation": item.generation, "generation_id": item.generation_id,
            "asset_key": item.key, "source_path": str(Path(item.path).resolve()), "source_sha256": item.source_sha256,
            "mark": MARK, "key_id": job.key_id, "key_fingerprint": job.key_fingerprint, "key_salt": job.key_salt,
            "params_json": json.dumps(params, sort_keys=True),
            **{k: params[k] for k in ("n_bits", "chip_rate", "beta", "valence", "n_clusters", "cluster_size",
                                      "chip_layout", "displacement")},
            "reference_key": BasisStore(job.store).key(item.source_sha256, item.params or job.params),
            "tool_version": __version__}


def _failed_rows(job, item, error, items=None):
    return [{**_row_base(job, item), "recipient": r, "output_path": None if o is None else str(o),
             "status": "failed", "error": error} for r, o in (items if items is not None else item.items)]


def _error_text(exc):
    return str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"


def start_client(cfg):
    """A Dask client: to ``dask.address`` if set, else Dask's ``scheduler-address``, else on a new LocalCluster.

    Dask's ``scheduler-address`` is its own setting (the environment variable
    ``DASK_SCHEDULER_ADDRESS`` or its YAML config), as set by a workflow
    engine or a job script that started the cluster.

    LocalCluster workers are spawned processes with one thread each, BLAS
    threads pinned to one (SciPy's ARPACK holds a process-wide lock; open3d
    must not be forked), and without the master secret in their environment.
    """
    import dask
    from distributed import Client, LocalCluster

    settings = cfg["dask"]
    # an existing scheduler: the config's, else Dask's own setting (DASK_SCHEDULER_ADDRESS), as Dask's Client reads it
    address = settings["address"] or dask.config.get("scheduler-address", None)
    if address:
        source = "dask.address" if settings["address"] else "Dask's scheduler-address (DASK_SCHEDULER_ADDRESS)"
        try:
            return Client(address, timeout="30s"), None
        except OSError as exc:          # said with where the address came from, before anything is written
            raise OSError(f"{source} {address}: the scheduler cannot be reached ({exc})") from None
    dask.config.set({"distributed.worker.multiprocessing-method": "spawn",
                     "distributed.nanny.pre-spawn-environ": WORKER_ENV,
                     # the statistical profiler samples stacks every 10 ms under the GIL:
                     # measurable on long numerical tasks, and we do not read its output
                     "distributed.worker.profile.enabled": False})
    n_workers = settings["n_workers"] or os.cpu_count() or 1
    logging.getLogger("distributed").setLevel(logging.WARNING)
    with without_secret_env():
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                               dashboard_address=":0", memory_limit=settings["memory_limit"],
                               silence_logs=logging.CRITICAL)
    return Client(cluster), cluster


def run_job(job, cfg, *, serial=False, progress=None):
    """Execute a planned job under the assets' locks; append one ledger part per asset.

    The Dask scheduler is reached before anything is written; then the
    ledger's salt (for a new ledger) and locks are created, interrupted
    intents of the assets are finished, and the copies are issued.

    Returns
    -------
    dict
        Counts of assets: ok, failed, skipped (nothing to issue).
    """
    client, cluster = (None, None) if serial else start_client(cfg)
    try:
        with job.ledger.lock([a.key for a in job.assets]):
            if job.new_salt and job.ledger.create_salt(job.key_salt) != job.key_salt:
                job = job.replan()      # another first run recorded its salt first
            if _recover(job) or (job.replan is not None and job.ledger.version() != job.ledger_version):
                job = job.replan()      # another run added rows, or an interrupted one was finished
            progress = progress or Progress.for_stream(cfg["dask"]["progress"], sys.stderr)
            todo = job.todo
            progress.start(len(todo), job.params.n_clusters)
            results = _run_serial(job, todo, cfg, progress) if serial else _run_dask(job, todo, cfg, progress, client)
            progress.finish()
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    counts = {"ok": 0, "failed": 0, "skipped": len(job.assets) - len(todo)}
    for item in todo:
        counts["ok" if all(r["status"] == "ok" for r in results[item.key]) else "failed"] += 1
    return counts


def _recover(job):
    """Finish or undo the intents an interrupted run left for the job's assets; True if any was found.

    A pending copy whose row is in the ledger, with the sha256 the row
    records, is published; any other pending copy is removed.
    """
    found = False
    for item in job.assets:
        intents = job.ledger.intents(item.key)
        if not intents:
            continue
        found = True
        rows = {str(r["output_path"]): r for r in job.ledger.rows(asset_key=item.key)
                if r["key_fingerprint"] == job.key_fingerprint and mac_ok(job.mac_key, r)}
        for intent, paths in intents:
            for final in paths:
                _settle(final, rows.get(str(final)))
            intent.unlink(missing_ok=True)
    return found


def _settle(final, row):
    pending = pending_path(final)
    if not pending.is_file():
        return
    if row is not None and sha256_file(pending) == row["output_sha256"]:
        if not (final.exists() or final.is_symlink()):
            _publish(pending, final)
            log.warning("published %s, issued by an interrupted run", final)
            return
        if sha256_file(final) != row["output_sha256"]:      # keep the issued bytes; say so
            print(f"[pointmark] {final}: holds other bytes than the copy its ledger row records; the issued "
                  f"copy is kept as {pending}", file=sys.stderr, flush=True)
            return
    pending.unlink()


def _chunks(items):
    return [items[a:a + CHUNK] for a in range(0, len(items), CHUNK)]


def _start_asset(job, item):
    """Record the copies the asset's issue tasks will write, before any is written."""
    job.ledger.write_intent(item.key, job.run_id, [o for _, o in item.items if o is not None])


def _finish_asset(job, item, rows, results, progress):
    """Append the asset's rows durably, then publish its copies; a ledger that cannot be written fails them."""
    pending = {r["output_path"]: r.pop("pending_path", None) for r in rows}
    try:
        job.ledger.append(rows, mac_key=job.mac_key)
    except OSError as exc:
        error = f"{job.ledger.copies}: the ledger could not be written ({exc.strerror or exc}); nothing issued"
        print(f"[pointmark] {item.key}: {error}", file=sys.stderr, flush=True)
        for path in pending.values():
            if path:
                Path(path).unlink(missing_ok=True)
        rows = _failed_rows(job, item, error)
    else:
        for row in rows:
            path = pending.get(row["output_path"])
            if row["status"] == "ok" and path:
                _publish(Path(path), Path(row["output_path"]))
    errors = sorted({r["error"] for r in rows if r["status"] != "ok" and r.get("error")})
    if errors:
        print(f"[pointmark] {item.key}: {sum(r['status'] != 'ok' for r in rows)} failed: {errors[0]}",
              file=sys.stderr, flush=True)
    for _, out in item.items:           # what was written but not issued goes
        if out is not None:
            pending_path(out).unlink(missing_ok=True)
    for intent, _ in job.ledger.intents(item.key):
        if intent.name.endswith(f".{job.run_id}.json"):
            intent.unlink(missing_ok=True)
    results[item.key] = rows
    progress.asset_done()


def _publish(pending, final):
    """Link a checked pending copy to its final name (never over another file).

    Where the file system has no hard links (exFAT, SMB), the copy is renamed
    instead, once no file holds the name (the asset's lock keeps other runs out).
    """
    final.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(pending, final)
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV, errno.EMLINK, errno.ENOSYS):
            raise
        if final.exists() or final.is_symlink():
            raise FileExistsError(errno.EEXIST, "exists", str(final)) from None
        os.rename(pending, final)
        return
    pending.unlink()


def _run_serial(job, todo, cfg, progress):
    results = {}
    for item in todo:
        if item.error:
            _finish_asset(job, item, _failed_rows(job, item, item.error), results, progress)
            continue
        _start_asset(job, item)
        try:
            plan = tasks.plan_asset(item.key, item.path, item.source_sha256, item.params, job.store,
                                    _row_base(job, item)["reference_key"], cfg["output"]["keep_originals"])
            progress.plan_done(len(plan.clusters))
            parts = []
            for i in range(len(plan.clusters)):
                parts.append(tasks.cluster_task(plan, i, item.params))
                progress.cluster_done()
        except Exception as exc:  # one bad asset is a failed row, not a stopped run
            _finish_asset(job, item, _failed_rows(job, item, _error_text(exc)), results, progress)
            continue
        rows = []
        for chunk in _chunks(item.items):
            try:
                rows += tasks.issue_task(plan, parts, job.material, chunk, item.params, _row_base(job, item))
            except Exception as exc:
                rows += _failed_rows(job, item, _error_text(exc), chunk)
        _finish_asset(job, item, rows, results, progress)
    return results


def _run_dask(job, todo, cfg, progress, client):
    from distributed import as_completed

    results, stage, open_chunks, rows = {}, {}, {}, {}
    pending = as_completed([], with_results=False)
    for item in todo:
        if item.error:
            _finish_asset(job, item, _failed_rows(job, item, item.error), results, progress)
            continue
        _start_asset(job, item)
        # absolute paths: a worker of an existing cluster has its own working directory
        fut = client.submit(tasks.plan_asset, item.key, os.path.abspath(item.path), item.source_sha256, item.params,
                            os.path.abspath(job.store), _row_base(job, item)["reference_key"],
                            cfg["output"]["keep_originals"], key=f"plan-{job.run_id}-{item.key}", pure=False)
        stage[fut.key] = ("plan", item, None)
        pending.add(fut)
    for fut in pending:
        kind, item, chunk = stage.pop(fut.key)
        if kind == "plan" and fut.status != "finished":
            _finish_asset(job, item, _failed_rows(job, item, _error_text(fut.exception())), results, progress)
        elif kind == "plan":
            n = len(fut.result().clusters)
            progress.plan_done(n)
            parts = [client.submit(tasks.cluster_task, fut, i, item.params, pure=False,
                                   key=f"cluster-{job.run_id}-{item.key}-{i}") for i in range(n)]
            for part in parts:
                stage[part.key] = ("cluster", item, None)
                pending.add(part)
            chunks = _chunks(item.items)
            open_chunks[item.key], rows[item.key] = len(chunks), []
            for c, chunk in enumerate(chunks):
                done = client.submit(tasks.issue_task, fut, parts, job.material, chunk, item.params,
                                     _row_base(job, item), key=f"issue-{job.run_id}-{item.key}-{c}", pure=False)
                stage[done.key] = ("issue", item, chunk)
                pending.add(done)
        elif kind == "cluster":
            progress.cluster_done()
        else:
            ok = fut.status == "finished"
            rows[item.key] += fut.result() if ok else _failed_rows(job, item, _error_text(fut.exception()), chunk)
            open_chunks[item.key] -= 1
            if open_chunks[item.key] == 0:
                _finish_asset(job, item, rows.pop(item.key), results, progress)
    return results
