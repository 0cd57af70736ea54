"""Run the catalogue job: plan, resume, execute on Dask (or serially), write manifests.

The graph per asset: ``plan_asset`` -> one ``embed_cluster_task`` per cluster
-> ``assemble_asset``.  Cluster tasks are submitted when their asset's plan
arrives, so the eigen-decompositions of all clusters of all assets run in
parallel across workers; no task ever waits on another from inside.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from .. import __version__
from ..config import watermark_params
from ..io.catalog import discover_assets
from ..io.manifest import EMBED_SCHEMA, manifest_path, read_rows, write_rows
from ..io.pointcloud import sha256_file
from ..kernels import keys
from ..watermark import params_record
from . import tasks
from .progress import Progress

log = logging.getLogger("pointmark.run")

__all__ = ["Job", "plan_job", "run_job", "start_client"]

# BLAS and OpenMP threads of every worker: one, so processes do not oversubscribe cores
PINNED_THREADS = {name: "1" for name in (
    "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")}


@dataclass
class AssetJob:
    key: str
    path: Path
    source_sha256: str
    outputs: list                  # (recipient, payload, output path)
    skip: bool = False


@dataclass
class Job:
    run_id: str
    key_id: str
    key_fingerprint: str
    material: bytes = field(repr=False)
    params: object = None
    manifests: Path = None
    assets: list = field(default_factory=list)

    @property
    def todo(self):
        return [a for a in self.assets if not a.skip]


def _run_id(params, key_id, fingerprint):
    text = json.dumps({"params": params_record(params), "key_id": key_id, "fp": fingerprint,
                       "version": __version__}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def plan_job(cfg, secret, *, force=False, shard=None):
    """Everything the run will do, without doing it.

    Parameters
    ----------
    cfg : dict
        Validated config.
    secret : bytes
    force : bool
        Redo assets whose manifest says they are done.
    shard : (int, int), optional
        (i, n): only assets i, i + n, i + 2n, ... (sorted by key).

    Returns
    -------
    Job
    """
    params = watermark_params(cfg)
    key_id = cfg["key"]["id"]
    if not key_id:
        from ..config import ConfigError
        raise ConfigError("config: key.id: a key id is needed for a catalogue run")
    fingerprint = keys.fingerprint(secret)
    if not cfg["catalog"]["source"]:
        from ..config import ConfigError
        raise ConfigError("config: catalog.source: name a folder, glob or catalogue file")
    job = Job(_run_id(params, key_id, fingerprint), key_id, fingerprint,
              keys.derive_key_material(secret, key_id), params, Path(cfg["output"]["manifests"]))
    assets = discover_assets(cfg["catalog"]["source"], default_recipients=cfg["recipients"])
    if shard is not None:
        assets = assets[shard[0]::shard[1]]
    out_dir = Path(cfg["output"]["dir"])
    for asset in assets:
        outputs = [(r, keys.recipient_payload(asset.key, r, params.n_bits),
                    out_dir / r / f"{asset.key}{asset.path.suffix.lower()}") for r in asset.recipients]
        source_sha = sha256_file(asset.path) if asset.path.is_file() else ""
        item = AssetJob(asset.key, asset.path, source_sha, outputs)
        item.skip = not force and _is_done(job, item)
        job.assets.append(item)
    return job


def _is_done(job, item):
    rows = read_rows(manifest_path(job.manifests, item.key))
    if len(rows) != len(item.outputs) or not item.source_sha256:
        return False
    want = {(r, p, str(o)) for r, p, o in item.outputs}
    have = {(row["recipient"], row["payload"], row["output_path"]) for row in rows}
    return want == have and all(
        row["status"] == "ok" and row["run_id"] == job.run_id
        and row["source_sha256"] == item.source_sha256
        and Path(row["output_path"]).is_file() and sha256_file(row["output_path"]) == row["output_sha256"]
        for row in rows)


def _row_base(job, item):
    params = params_record(job.params)
    seeds = params.pop("seeds")
    return {"run_id": job.run_id, "asset_key": item.key, "source_path": str(item.path),
            "source_sha256": item.source_sha256, "key_id": job.key_id,
            "key_fingerprint": job.key_fingerprint, "seeds_json": json.dumps(seeds), **params,
            "tool_version": __version__}


def _write_manifest(job, item, rows):
    now = datetime.now(timezone.utc).replace(microsecond=0)
    write_rows(manifest_path(job.manifests, item.key), [{**r, "created_at": now} for r in rows],
               EMBED_SCHEMA)


def _failed_rows(job, item, error):
    return [{**_row_base(job, item), "output_path": str(o), "recipient": r, "payload": p,
             "status": "failed", "error": error} for r, p, o in item.outputs]


def _error_text(exc):
    return f"{type(exc).__name__}: {exc}" if not isinstance(exc, ValueError) else str(exc)


def start_client(cfg):
    """A Dask client: to ``dask.address`` if set, else on a new LocalCluster.

    LocalCluster workers are spawned processes with one thread each and BLAS
    threads pinned to one (SciPy's ARPACK holds a process-wide lock, and
    open3d must not be forked).
    """
    import dask
    from distributed import Client, LocalCluster

    settings = cfg["dask"]
    if settings["address"]:
        return Client(settings["address"], timeout="30s"), None
    dask.config.set({"distributed.worker.multiprocessing-method": "spawn",
                     "distributed.nanny.pre-spawn-environ": PINNED_THREADS,
                     # the statistical profiler samples stacks every 10 ms under the GIL:
                     # measurable on long numerical tasks, and we do not read its output
                     "distributed.worker.profile.enabled": False})
    n_workers = settings["n_workers"] or os.cpu_count() or 1
    logging.getLogger("distributed").setLevel(logging.WARNING)
    cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                           dashboard_address=":0", memory_limit=settings["memory_limit"],
                           silence_logs=logging.CRITICAL)
    return Client(cluster), cluster


def run_job(job, cfg, *, serial=False, progress=None):
    """Execute a planned job; write one manifest file per asset.

    Returns
    -------
    dict
        Counts: ok, failed, skipped (assets).
    """
    progress = progress or Progress.for_stream(cfg["dask"]["progress"], sys.stderr)
    todo = job.todo
    progress.start(len(todo), job.params.n_clusters)
    if serial:
        results = _run_serial(job, todo, progress)
    else:
        results = _run_dask(job, todo, cfg, progress)
    progress.finish()
    counts = {"ok": 0, "failed": 0, "skipped": len(job.assets) - len(todo)}
    for item in todo:
        counts["ok" if all(r["status"] == "ok" for r in results[item.key]) else "failed"] += 1
    return counts


def _run_serial(job, todo, progress):
    results = {}
    for item in todo:
        try:
            plan = tasks.plan_asset(item.path, job.params)
            progress.plan_done(len(plan.clusters))
            parts = []
            for i in range(len(plan.clusters)):
                parts.append(tasks.embed_cluster_task(plan, i, job.material,
                                                      [p for _, p, _ in item.outputs], job.params))
                progress.cluster_done()
            results[item.key] = tasks.assemble_asset(plan, parts, item.outputs, _row_base(job, item))
        except Exception as exc:  # one bad asset is a failed row, not a stopped run
            results[item.key] = _failed_rows(job, item, _error_text(exc))
        _write_manifest(job, item, results[item.key])
        progress.asset_done()
    return results


def _run_dask(job, todo, cfg, progress):
    from distributed import as_completed

    client, cluster = start_client(cfg)
    results = {}
    try:
        stage = {}
        plans = []
        for item in todo:
            fut = client.submit(tasks.plan_asset, str(item.path), job.params,
                                key=f"plan-{job.run_id}-{item.key}", pure=False)
            stage[fut.key] = ("plan", item)
            plans.append(fut)
        pending = as_completed(plans, with_results=False)
        for fut in pending:
            kind, item = stage.pop(fut.key)
            if item.key in results:
                continue  # the asset already failed at an earlier task
            if fut.status != "finished":
                results[item.key] = _failed_rows(job, item, _error_text(fut.exception()))
                _write_manifest(job, item, results[item.key])
                progress.asset_done()
                continue
            if kind == "plan":
                plan = fut.result()
                progress.plan_done(len(plan.clusters))
                payloads = [p for _, p, _ in item.outputs]
                parts = [client.submit(tasks.embed_cluster_task, fut, i, job.material, payloads,
                                       job.params, key=f"cluster-{job.run_id}-{item.key}-{i}", pure=False)
                         for i in range(len(plan.clusters))]
                for part in parts:
                    stage[part.key] = ("cluster", item)
                    pending.add(part)
                done = client.submit(tasks.assemble_asset, fut, parts, item.outputs, _row_base(job, item),
                                     key=f"assemble-{job.run_id}-{item.key}", pure=False)
                stage[done.key] = ("assemble", item)
                pending.add(done)
            elif kind == "cluster":
                progress.cluster_done()
            else:
                results[item.key] = fut.result()
                _write_manifest(job, item, results[item.key])
                progress.asset_done()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return results
