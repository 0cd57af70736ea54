"""The catalogue job on a real Dask cluster, against a plain serial loop."""

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.dataset as ds
import pytest
import yaml

from pipeline import config
from pipeline.io.manifest import EMBED_SCHEMA, read_dataset
from pipeline.io.pointcloud import write_array
from pipeline.demo import procedural_shape
from pipeline.orchestrate.run import plan_job, run_job
from pipeline.orchestrate.progress import Progress
from tests.conftest import ROOT

pytestmark = pytest.mark.slow
SECRET = "orchestrate-test-secret-7f3a"


def make_catalogue(folder, n_assets=4, n_points=3000, formats=("ply", "pcd", "xyz", "las")):
    for i in range(n_assets):
        pts = procedural_shape(["blob", "torus", "shell", "terrain"][i % 4], n_points, seed=100 + i) * 10
        write_array(folder, f"asset-{i}", pts, formats[i % len(formats)])
    return folder


def write_config(tmp, source, *, out="out", extra=None):
    cfg = {
        "catalog": {"source": str(source)},
        "recipients": ["alice", "bob"],
        "output": {"dir": str(tmp / out / "marked"), "manifests": str(tmp / out / "manifests")},
        "key": {"id": "test-key", "secret_file": str(tmp / "secret.key")},
        "watermark": {"n_bits": 16, "n_clusters": 2, "cluster_size": 1200},
        "dask": {"n_workers": 2, "progress": "lines"},
    }
    (tmp / "secret.key").write_text(SECRET + "\n")
    for section, values in (extra or {}).items():
        cfg.setdefault(section, {}).update(values)
    path = tmp / f"{out}.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def _run(cfg_path, *, serial=False, force=False):
    cfg = config.load_config(cfg_path)
    job = plan_job(cfg, SECRET.encode(), force=force)
    return job, run_job(job, cfg, serial=serial, progress=Progress())


def _outputs(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(Path(folder).rglob("*"))
            if p.is_file()}


def test_dask_outputs_are_byte_identical_to_a_serial_loop(tmp_path):
    src = make_catalogue(tmp_path / "assets")
    _, c1 = _run(write_config(tmp_path, src, out="dask"))
    _, c2 = _run(write_config(tmp_path, src, out="serial"), serial=True)
    assert c1 == c2 == {"ok": 4, "failed": 0, "skipped": 0}
    a, b = _outputs(tmp_path / "dask" / "marked"), _outputs(tmp_path / "serial" / "marked")
    assert len(a) == 8 and a == b
    table = ds.dataset(str(tmp_path / "dask" / "manifests"), format="parquet").to_table()
    assert table.num_rows == 8 and table.schema.equals(EMBED_SCHEMA)
    assert sorted(set(table["recipient"].to_pylist())) == ["alice", "bob"]
    assert len(set(table["payload"].to_pylist())) == 8


def test_rerun_skips_done_assets_and_force_redoes_them(tmp_path):
    cfg = write_config(tmp_path, make_catalogue(tmp_path / "assets", n_assets=2))
    _run(cfg, serial=True)
    _, counts = _run(cfg, serial=True)
    assert counts == {"ok": 0, "failed": 0, "skipped": 2}
    # a tampered output is redone
    victim = next((tmp_path / "out" / "marked" / "alice").iterdir())
    victim.write_bytes(victim.read_bytes()[:-10] + b"0123456789")
    _, counts = _run(cfg, serial=True)
    assert counts == {"ok": 1, "failed": 0, "skipped": 1}
    _, counts = _run(cfg, serial=True, force=True)
    assert counts == {"ok": 2, "failed": 0, "skipped": 0}


def test_a_corrupt_asset_becomes_one_failed_row(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=3)
    (src / "broken.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 900\n"
                                     b"property float x\nproperty float y\nproperty float z\nend_header\n" + b"\0" * 50)
    job, counts = _run(write_config(tmp_path, src))
    assert counts == {"ok": 3, "failed": 1, "skipped": 0}
    table = read_dataset(job.manifests, EMBED_SCHEMA).to_pylist()
    failed = [r for r in table if r["status"] == "failed"]
    assert {r["asset_key"] for r in failed} == {"broken"} and len(failed) == 2
    assert "broken.ply" in failed[0]["error"] and "truncated" in failed[0]["error"]
    assert all(Path(r["output_path"]).is_file() for r in table if r["status"] == "ok")
    assert not (tmp_path / "out" / "marked" / "alice" / "broken.ply").exists()


def test_cli_exit_status_and_secret_never_in_manifests_or_logs(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=2)
    (src / "bad.xyz").write_text("1 2 3\nnot numbers at all\n")
    cfg = write_config(tmp_path, src)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("POINTMARK_SECRET", None)
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "-v", "run", str(cfg)], cwd=tmp_path,
                         env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 1, res.stderr
    logs = res.stdout + res.stderr
    assert "[pointmark] assets" in logs                     # plain progress lines off a terminal
    blobs = [p.read_bytes() for p in (tmp_path / "out" / "manifests").glob("*.parquet")]
    assert len(blobs) == 3
    for text in [logs.encode(), *blobs]:
        assert SECRET.encode() not in text
    bad = subprocess.run([sys.executable, "-m", "pipeline.cli", "run", str(cfg), "--set", "beta=-3"],
                         cwd=tmp_path, env=env, capture_output=True, text=True)
    assert bad.returncode == 2 and "watermark.beta" in bad.stderr


def test_dry_run_prints_the_plan_and_writes_nothing(tmp_path):
    cfg = write_config(tmp_path, make_catalogue(tmp_path / "assets", n_assets=2))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "run", str(cfg), "--dry-run"], cwd=tmp_path,
                         env=env, capture_output=True, text=True, check=True)
    assert "asset-0" in res.stdout and "2 recipients" in res.stdout and "tasks" in res.stdout
    assert not (tmp_path / "out").exists()


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_run_through_an_existing_scheduler_with_two_worker_processes(tmp_path):
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    bin_dir = Path(sys.executable).parent
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", PYTHONPATH=str(ROOT))
    procs = [subprocess.Popen([str(bin_dir / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        time.sleep(3)
        for _ in range(2):
            procs.append(subprocess.Popen([str(bin_dir / "dask"), "worker", addr, "--nthreads", "1",
                                           "--no-dashboard"], env=env, stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL))
        from distributed import Client
        with Client(addr, timeout="30s") as client:
            client.wait_for_workers(2, timeout=60)
            assert len(client.scheduler_info()["workers"]) == 2
        src = make_catalogue(tmp_path / "assets", n_assets=3)
        job, counts = _run(write_config(tmp_path, src, extra={"dask": {"address": addr}}))
        assert counts == {"ok": 3, "failed": 0, "skipped": 0}
        _run(write_config(tmp_path, src, out="serial"), serial=True)
        assert _outputs(tmp_path / "out" / "marked") == _outputs(tmp_path / "serial" / "marked")
    finally:
        for p in procs[::-1]:
            p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()


def test_an_interrupted_run_resumes_with_each_asset_done_once(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=6)
    cfg = write_config(tmp_path, src, extra={"dask": {"n_workers": 1}})
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "run", str(cfg)], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    manifests = tmp_path / "out" / "manifests"
    deadline = time.time() + 300
    while time.time() < deadline and len(list(manifests.glob("*.parquet"))) < 2:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)                 # the run and its workers, mid-way
    proc.wait()
    first = len(list(manifests.glob("*.parquet")))
    assert 2 <= first < 6
    job, counts = _run(cfg)
    assert counts["skipped"] == first and counts["ok"] == 6 - first and counts["failed"] == 0
    rows = read_dataset(manifests, EMBED_SCHEMA).to_pylist()
    keys = [(r["asset_key"], r["recipient"]) for r in rows]
    assert len(keys) == len(set(keys)) == 12
    assert all(r["status"] == "ok" for r in rows)
    assert not list((tmp_path / "out").rglob(".*.tmp*"))
