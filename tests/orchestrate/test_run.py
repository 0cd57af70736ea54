"""The catalogue job on a real Dask cluster, against a plain serial loop."""

import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pyarrow.dataset as ds
import pytest
import yaml

from pipeline import __version__, config
from pipeline.io.ledger import LEDGER_SCHEMA, Ledger
from pipeline.io.pointcloud import write_array
from pipeline.demo import procedural_shape
from pipeline.orchestrate.run import MARK, _generation_id, plan_job, run_job
from pipeline.orchestrate.progress import Progress
from pipeline.config import WatermarkParams
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


def _run(cfg_path, *, serial=False, force=False, sets=()):
    cfg = config.load_config(cfg_path, sets)
    job = plan_job(cfg, SECRET.encode(), force=force)
    return job, run_job(job, cfg, serial=serial, progress=Progress())


def _outputs(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(Path(folder).rglob("*"))
            if p.is_file()}


def _rows(job_or_folder):
    folder = job_or_folder.manifests if hasattr(job_or_folder, "manifests") else job_or_folder
    return Ledger(folder).rows(status=None)


def test_dask_outputs_are_byte_identical_to_a_serial_loop(tmp_path, own_cluster):
    src = make_catalogue(tmp_path / "assets")
    _, c1 = _run(write_config(tmp_path, src, out="dask"))
    _, c2 = _run(write_config(tmp_path, src, out="serial"), serial=True)
    assert c1 == c2 == {"ok": 4, "failed": 0, "skipped": 0}
    a, b = _outputs(tmp_path / "dask" / "marked"), _outputs(tmp_path / "serial" / "marked")
    assert len(a) == 8 and a == b
    table = ds.dataset(str(tmp_path / "dask" / "manifests" / "copies"), format="parquet").to_table()
    assert table.num_rows == 8 and table.schema.equals(LEDGER_SCHEMA)
    assert sorted(set(table["recipient"].to_pylist())) == ["alice", "bob"]
    assert set(table["generation"].to_pylist()) == {1}
    assert min(table["realized_ratio"].to_pylist()) > 0.99      # float64 and LAS 1e-4 keep the mark


def test_a_rerun_issues_nothing_and_an_added_recipient_costs_one_copy(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=2)
    cfg = write_config(tmp_path, src)
    job, _ = _run(cfg, serial=True)
    parts = {p.name: p.read_bytes() for p in Ledger(job.manifests).parts()}
    outputs = _outputs(tmp_path / "out" / "marked")
    _, counts = _run(cfg, serial=True)
    assert counts == {"ok": 0, "failed": 0, "skipped": 2}
    job, counts = _run(cfg, serial=True, sets=["recipients=[alice, bob, carol]"])
    assert counts == {"ok": 2, "failed": 0, "skipped": 0}
    after = {p.name: p.read_bytes() for p in Ledger(job.manifests).parts()}
    assert all(after[name] == blob for name, blob in parts.items())          # earlier rows untouched
    new = _outputs(tmp_path / "out" / "marked")
    assert {k: v for k, v in new.items() if k in outputs} == outputs
    assert sorted(set(new) - set(outputs)) == ["carol/asset-0.ply", "carol/asset-1.pcd"]
    rows = _rows(job)
    assert len(rows) == 6 and len({(r["asset_key"], r["recipient"]) for r in rows}) == 6
    # each copy carries its distortion as the field measures it
    assert all(0 < r["mrms_rel_diag"] < 0.01 and r["surface_hausdorff_rel_diag"] >= r["mrms_rel_diag"]
               and r["normal_deviation_deg"] > 0 and 0 <= r["msdm"] <= 1 for r in rows)


def test_a_changed_parameter_starts_generation_2_and_generation_1_stays_attributable(tmp_path, monkeypatch):
    from pipeline.kernels import attacks
    from pipeline.orchestrate.detect import detect_from_ledger
    from pipeline.io.pointcloud import read_points

    src = make_catalogue(tmp_path / "assets", n_assets=1)
    cfg = write_config(tmp_path, src)
    job, _ = _run(cfg, serial=True)
    first = {p.name: p.read_bytes() for p in Ledger(job.manifests).parts()}
    job, counts = _run(cfg, serial=True, sets=["beta=0.003"])
    assert counts["ok"] == 1
    rows = _rows(job)
    assert sorted((r["generation"], r["recipient"]) for r in rows) == [(1, "alice"), (1, "bob"), (2, "alice"),
                                                                       (2, "bob")]
    assert all(Ledger(job.manifests).folder.joinpath("copies", n).read_bytes() == b for n, b in first.items())
    gen1 = tmp_path / "out" / "marked" / "bob" / "asset-0.ply"
    assert (tmp_path / "out" / "marked" / "bob" / "asset-0.g2.ply").is_file()
    leak = attacks.apply_chain(read_points(gen1).points, [("random_similarity", None), ("shuffle", None)], 5)
    write_array(tmp_path, "leak", leak, "ply")
    result = detect_from_ledger(tmp_path / "leak.ply", job.manifests, SECRET.encode(),
                                config.detect_params(config.load_config(cfg)))
    assert result["verdict"] == "match"
    assert [a["recipient"] for a in result["accused"]] == ["bob"]
    assert [g for g, _ in result["accused"][0]["copies"]] == [1]
    assert result["n_checked"] == 4       # 2 recipients x 2 generations (references differ in nothing but beta)


def test_a_band_sized_for_noise_is_issued_recorded_and_attributed_from_the_ledger(tmp_path):
    # a dense asset (8,000 points, noise of 1 % about 2 spacings) takes a narrower band; the ledger
    # keeps the chip rate and beta it was marked with, and detection reads them from there alone
    from pipeline.kernels import attacks
    from pipeline.orchestrate.detect import detect_from_ledger
    from pipeline.io.pointcloud import read_points
    from tests.conftest import sphere_patch

    write_array(tmp_path / "assets", "dense", sphere_patch(8000, rng=6) * 10, "ply")
    cfg = write_config(tmp_path, tmp_path / "assets",
                       extra={"watermark": {"n_bits": 32, "band_noise": 0.01}})
    job, counts = _run(cfg, serial=True)
    assert counts["ok"] == 1
    params = [json.loads(r["params_json"]) for r in _rows(job)]
    assert {(p["chip_rate"], p["band_noise"]) for p in params} == {(params[0]["chip_rate"], None)}
    assert 3 <= params[0]["chip_rate"] < 10
    leak = attacks.apply_chain(read_points(tmp_path / "out" / "marked" / "bob" / "dense.ply").points,
                               [("noise", 0.005), ("random_similarity", None), ("shuffle", None)], 3)
    write_array(tmp_path, "leak", leak, "ply")
    result = detect_from_ledger(tmp_path / "leak.ply", job.manifests, SECRET.encode(),
                                config.detect_params(config.load_config(cfg)))
    assert result["verdict"] == "match" and [a["recipient"] for a in result["accused"]] == ["bob"]


def test_two_concurrent_runs_lose_no_row(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=3)
    cfg = write_config(tmp_path, src)
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "pipeline.cli", "run", str(cfg), "--serial"]
    procs = [subprocess.Popen(cmd + ["--set", f"recipients=[{who}]"], cwd=tmp_path, env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for who in ("alice, bob", "bob, carol")]
    outs = [p.communicate(timeout=600) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    rows = _rows(tmp_path / "out" / "manifests")
    pairs = [(r["asset_key"], r["recipient"]) for r in rows]
    assert len(pairs) == len(set(pairs)) == 9                       # 3 assets x {alice, bob, carol}
    assert all(r["status"] == "ok" and Path(r["output_path"]).is_file() for r in rows)


def test_a_changed_clustering_constant_fails_detection_with_a_digest_mismatch(tmp_path, monkeypatch):
    from pipeline.kernels import clustering
    from pipeline.orchestrate.detect import detect_from_ledger
    from pipeline.watermark import ReferenceMismatch

    src = make_catalogue(tmp_path / "assets", n_assets=1)
    cfg = write_config(tmp_path, src)
    job, _ = _run(cfg, serial=True)
    copy = tmp_path / "out" / "marked" / "alice" / "asset-0.ply"
    dparams = config.detect_params(config.load_config(cfg))
    ok = detect_from_ledger(copy, job.manifests, SECRET.encode(), dparams, store=tmp_path / "fresh-store")
    assert [a["recipient"] for a in ok["accused"]] == ["alice"]        # a rebuilt reference verifies
    monkeypatch.setattr(clustering, "_FRONTIER_K", 5)
    with pytest.raises(ReferenceMismatch, match="cluster 0 members digest"):
        detect_from_ledger(copy, job.manifests, SECRET.encode(), dparams, store=tmp_path / "other-store")


def test_worker_processes_never_hold_the_master_secret(tmp_path, monkeypatch, own_cluster):
    from pipeline.orchestrate.run import start_client

    monkeypatch.setenv("POINTMARK_SECRET", SECRET)
    cfg = config.load_config(write_config(tmp_path, tmp_path))
    client, cluster = start_client(cfg)
    try:
        seen = client.run(lambda: {k: v for k, v in __import__("os").environ.items()
                                   if "POINTMARK_SECRET" in k or SECRET in v})
    finally:
        client.close()
        cluster.close()
    assert len(seen) == 2 and all(found == {} for found in seen.values())
    assert os.environ["POINTMARK_SECRET"] == SECRET                 # restored for this process


def test_a_corrupt_asset_becomes_failed_rows_and_the_rest_complete(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=3)
    (src / "broken.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 900\n"
                                     b"property float x\nproperty float y\nproperty float z\nend_header\n" + b"\0" * 50)
    job, counts = _run(write_config(tmp_path, src))
    assert counts == {"ok": 3, "failed": 1, "skipped": 0}
    rows = _rows(job)
    failed = [r for r in rows if r["status"] == "failed"]
    assert {r["asset_key"] for r in failed} == {"broken"} and len(failed) == 2
    assert "broken.ply" in failed[0]["error"]
    assert all(Path(r["output_path"]).is_file() for r in rows if r["status"] == "ok")
    assert not (tmp_path / "out" / "marked" / "alice" / "broken.ply").exists()


def test_a_missing_or_corrupt_asset_in_a_catalogue_file_is_a_failed_row(tmp_path):
    from pipeline.io.catalog import catalogue_record, discover_assets, write_catalogue

    src = make_catalogue(tmp_path / "assets", n_assets=2)
    (src / "broken.xyz").write_text("1 2 3\nnot numbers at all\n")
    rows = [catalogue_record(a) for a in discover_assets(src)]
    rows.append({"asset_key": "gone", "path": str(tmp_path / "nowhere.ply"), "recipients": []})
    write_catalogue(rows, tmp_path / "catalog.parquet")
    job, counts = _run(write_config(tmp_path, tmp_path / "catalog.parquet"), serial=True)
    assert counts == {"ok": 2, "failed": 2, "skipped": 0}
    failed = {r["asset_key"]: r["error"] for r in _rows(job) if r["status"] == "failed"}
    assert set(failed) == {"broken", "gone"} and "no such file" in failed["gone"]


def test_catalogue_and_config_recipients_are_both_issued(tmp_path):
    from pipeline.io.catalog import catalogue_record, discover_assets, write_catalogue

    src = make_catalogue(tmp_path / "assets", n_assets=1)
    rows = [catalogue_record(a) for a in discover_assets(src, default_recipients=("dave",))]
    write_catalogue(rows, tmp_path / "catalog.parquet")
    job, _ = _run(write_config(tmp_path, tmp_path / "catalog.parquet"), serial=True)
    assert sorted(r["recipient"] for r in _rows(job)) == ["alice", "bob", "dave"]


@pytest.mark.parametrize("name", ["../x", "/abs", "a/b", "..", ".hidden"])
def test_a_recipient_that_escapes_the_output_folder_is_refused(tmp_path, name):
    src = make_catalogue(tmp_path / "assets", n_assets=1)
    cfg = write_config(tmp_path, src)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "run", str(cfg), "--serial", "--set",
                          f"recipients=[alice, '{name}']"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert res.returncode == 2 and "recipients" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists() and not (tmp_path / "x").exists()


def test_a_beta_too_small_to_change_the_file_is_refused(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=1)
    job, counts = _run(write_config(tmp_path, src), serial=True, sets=["beta=1.0e-300"])
    assert counts == {"ok": 0, "failed": 1, "skipped": 0}
    rows = _rows(job)
    assert all(r["status"] == "failed" and "does not differ measurably" in r["error"] for r in rows)
    assert not [p for p in (tmp_path / "out" / "marked").rglob("*") if p.is_file()]


def test_cli_exit_status_and_secret_never_in_ledger_or_logs(tmp_path, own_cluster):
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
    blobs = [p.read_bytes() for p in (tmp_path / "out" / "manifests").rglob("*") if p.is_file()]
    assert len(blobs) >= 3
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
    assert "asset-0: generation 1, 0 issued; to issue: alice, bob" in res.stdout
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


def test_an_interrupted_run_resumes_and_issues_each_copy_once(tmp_path, own_cluster):
    src = make_catalogue(tmp_path / "assets", n_assets=6)
    cfg = write_config(tmp_path, src, extra={"dask": {"n_workers": 1}})
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "run", str(cfg)], cwd=tmp_path, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    ledger = Ledger(tmp_path / "out" / "manifests")
    deadline = time.time() + 300
    while time.time() < deadline and len(ledger.parts()) < 2:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)                 # the run and its workers, mid-way
    proc.wait()
    first = len(ledger.parts())
    assert 2 <= first < 6
    job, counts = _run(cfg)
    assert counts["skipped"] == first and counts["ok"] == 6 - first and counts["failed"] == 0
    rows = _rows(job)
    keys = [(r["asset_key"], r["recipient"]) for r in rows]
    assert len(keys) == len(set(keys)) == 12
    assert all(r["status"] == "ok" for r in rows)
    assert not [p for p in (tmp_path / "out" / "marked").rglob("*") if p.name.startswith(".")]


@pytest.mark.parametrize("key", ["../../escape", "/etc/evil", "a/../../b"])
def test_an_asset_key_that_escapes_the_output_folder_is_refused(tmp_path, key):
    import csv

    src = make_catalogue(tmp_path / "assets", n_assets=1)
    with open(tmp_path / "catalog.csv", "w", newline="") as f:
        csv.writer(f).writerows([["asset_key", "path"], [key, str(src / "asset-0.ply")]])
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "run", str(write_config(tmp_path, tmp_path / "catalog.csv")),
                          "--serial"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert res.returncode == 2 and "would leave the output folder" in res.stderr
    assert not (tmp_path / "out" / "marked").exists() and not (tmp_path / "escape").exists()


def test_an_asset_with_every_point_stored_twice_is_a_failed_row(tmp_path):
    import numpy as np

    from pipeline.io.pointcloud import read_points

    src = make_catalogue(tmp_path / "assets", n_assets=1)
    points = read_points(src / "asset-0.ply").points
    write_array(src, "doubled", np.vstack([points, points]), "ply")
    job, counts = _run(write_config(tmp_path, src), serial=True)
    assert counts == {"ok": 1, "failed": 1, "skipped": 0}
    failed = [r for r in _rows(job) if r["status"] == "failed"]
    assert {r["asset_key"] for r in failed} == {"doubled"} and "repeat another point" in failed[0]["error"]


# the parameter record of a 0.2.0 ledger row (before amplitude and max_displacement; valence as a config gives it)
RECORD_0_2_0 = {"n_bits": 32, "chip_rate": 10, "beta": 0.002, "valence": 12, "n_clusters": 5,
                "cluster_size": 4000, "seeds": None, "on_touch": "skip", "cover": False,
                "chip_layout": "consecutive", "first_coefficient": 0, "crc_bits": 0, "displacement": "xyz"}


def _id_0_2_0(record):
    text = json.dumps({"params": record, "key_id": "k", "fp": "f" * 16, "mark": MARK, "source": "s" * 64,
                       "version": __version__}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# the 0.2.0 defaults, which that record holds (resolved for an asset, as a plan holds them: no band_noise)
PARAMS_0_2_0 = WatermarkParams(beta=0.002, chip_layout="consecutive", displacement="xyz", code="repetition",
                               cover=False, band_noise=None)


def test_a_rerun_with_an_unchanged_config_stays_in_its_generation():
    assert _generation_id(PARAMS_0_2_0, "k", "f" * 16, "s" * 64) == _id_0_2_0(RECORD_0_2_0)


def test_a_new_amplitude_rule_or_cap_is_a_new_generation():
    base = _generation_id(PARAMS_0_2_0, "k", "f" * 16, "s" * 64)
    assert _generation_id(replace(PARAMS_0_2_0, amplitude="cluster"), "k", "f" * 16, "s" * 64) != base
    assert _generation_id(replace(PARAMS_0_2_0, max_displacement=0.01), "k", "f" * 16, "s" * 64) != base
    # the message's channel code changes no fingerprinted copy: same generation
    assert _generation_id(replace(PARAMS_0_2_0, code="convolutional"), "k", "f" * 16, "s" * 64) == base


def test_a_new_generation_says_which_parameters_changed(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=1)
    cfg_path = write_config(tmp_path, src)
    _run(cfg_path, serial=True, sets=["beta=0.002", "displacement=xyz", "chip_layout=consecutive"])
    job = plan_job(config.load_config(cfg_path), SECRET.encode())      # today's defaults
    (item,) = job.assets
    assert item.generation == 2
    assert item.note.startswith("generation 2: beta 0.002 -> 0.00115, chip_layout 'consecutive' -> "
                                "'interleaved', displacement 'xyz' -> 'normal'; pin the earlier values")
    again = plan_job(config.load_config(cfg_path, ["beta=0.002", "displacement=xyz", "chip_layout=consecutive"]),
                     SECRET.encode())
    assert again.assets[0].generation == 1 and again.assets[0].note is None and not again.assets[0].items


def test_a_geographic_lidar_tile_is_a_failed_row_and_the_rest_are_issued(tmp_path):
    import laspy
    import numpy as np
    from laspy.vlrs.known import WktCoordinateSystemVlr

    src = make_catalogue(tmp_path / "assets", n_assets=1)
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = np.array([1e-7] * 3), np.array([-122.0, 45.0, 0.0])
    header.vlrs.append(WktCoordinateSystemVlr('GEOGCS["WGS 84", DATUM["WGS_1984", SPHEROID["WGS 84",6378137,'
                                              '298.257223563]], UNIT["degree",0.0174532925199433]]'))
    las = laspy.LasData(header)
    pts = procedural_shape("terrain", 3000, seed=5) * 1e-3 + [-122.0, 45.0, 0.0]
    las.x, las.y, las.z = pts.T
    las.write(str(src / "degrees.las"))
    job, counts = _run(write_config(tmp_path, src), serial=True)
    assert counts["ok"] == 1 and counts["failed"] == 1
    failed = [r for r in _rows(job) if r["status"] == "failed"]
    assert {r["asset_key"] for r in failed} == {"degrees"}
    assert "geographic coordinates (degrees)" in failed[0]["error"]
