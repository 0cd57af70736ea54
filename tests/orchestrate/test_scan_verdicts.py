"""Scan verdicts: failed is never "no match", rescans check only what is new, bad secrets stop the scan.

One small world (two 3,000-point assets issued to alice and bob, and bob's copy of asset-0 moved and
reshuffled among the suspects) is built once, at one path (ledger rows and the catalogue name files
by path), and every test gets it back as built.  Scans run through the CLI in this process, on an
in-process Dask cluster; the feature index a first scan builds is kept for the session
(``ScanIndexes``).
"""

import json
import os
import shutil
from pathlib import Path
import numpy as np

import pytest
import yaml

from pipeline import cli
from pipeline.io.catalog import catalogue_record, discover_assets, write_catalogue
from pipeline.io.pointcloud import read_points, sha256_file, write_array
from pipeline.kernels import attacks
from pipeline.orchestrate.scan import read_scan
from tests.conftest import SMALL_DETECTION, SMALL_WATERMARK
from tests.orchestrate.test_run import _run, make_catalogue, write_config

pytestmark = pytest.mark.slow


class _Result:
    def __init__(self, returncode, stdout, stderr):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


@pytest.fixture()
def scan(capsys, scan_indexes):
    """Scan ``tmp/scan.yaml`` through the CLI; returns its exit status and output.

    ``seed``: give the scan the feature index an earlier scan of the same catalogue built.
    """
    def scan(tmp, *flags, seed=True):
        out = Path(yaml.safe_load((tmp / "scan.yaml").read_text())["scan"]["out"])
        if seed:
            scan_indexes.seed(out)
        capsys.readouterr()
        code = cli.main(["scan", str(tmp / "scan.yaml"), *flags])
        res = _Result(code, *capsys.readouterr())
        scan_indexes.keep(out)
        return res

    return scan


def _latest(tmp):
    latest = {}
    for r in sorted(read_scan(tmp / "scan"), key=lambda r: r["scanned_at"]):
        latest[os.path.basename(r["suspect_path"])] = r
    return latest


@pytest.fixture(scope="module")
def _built(tmp_path_factory, shared_cluster):
    root = tmp_path_factory.mktemp("verdicts")
    tmp = root / "world"
    src = make_catalogue(tmp / "assets", n_assets=2)
    cfg_path = write_config(tmp, src, extra={"watermark": SMALL_WATERMARK, "detection": SMALL_DETECTION,
                                             "dask": {"address": shared_cluster.scheduler_address}})
    _run(cfg_path, serial=True)
    write_catalogue([catalogue_record(a) for a in discover_assets(src)], tmp / "catalog.parquet")
    points = read_points(tmp / "out" / "marked" / "bob" / "asset-0.ply").points
    write_array(tmp / "suspects", "found", attacks.apply_chain(points, [("random_similarity", None),
                                                                     ("shuffle", None)], 2), "ply")
    cfg = yaml.safe_load(cfg_path.read_text())
    cfg["scan"] = {"suspects": str(tmp / "suspects"), "catalogue": str(tmp / "catalog.parquet"),
                   "out": str(tmp / "scan"), "top_k": 1}   # one candidate: the bookkeeping is under test
    (tmp / "scan.yaml").write_text(yaml.safe_dump(cfg))
    shutil.copytree(tmp, root / "pristine", symlinks=True)
    return root


@pytest.fixture()
def world(_built):
    """The world as built, back at the path it was built at."""
    tmp = _built / "world"
    shutil.rmtree(tmp)
    shutil.copytree(_built / "pristine", tmp, symlinks=True)
    return tmp, tmp / "out.yaml"


def test_a_check_that_cannot_be_made_is_failed_exit_3_and_retried_with_one_result_file(world, scan):
    tmp, _ = world
    cfg = yaml.safe_load((tmp / "scan.yaml").read_text())
    cfg["scan"]["top_k"] = 2      # the other candidate's check completes, as "no match": still failed
    (tmp / "scan.yaml").write_text(yaml.safe_dump(cfg))
    original = tmp / "assets" / "asset-0.ply"
    hidden = tmp / "asset-0.ply.away"
    kept = tmp / "out" / "manifests" / "bases" / "originals"
    original.rename(hidden)                                  # the check finds the original nowhere:
    kept.rename(tmp / "originals.away")                      # not in the catalogue, nor kept by the run
    for _ in range(2):         # (the scan indexes the catalogue without the missing file itself)
        res = scan(tmp, seed=False)
        assert res.returncode == 3, res.stdout + res.stderr
        assert "1 failed" in res.stdout and "no match" not in _latest(tmp)["found.ply"]["verdict"]
        assert _latest(tmp)["found.ply"]["verdict"] == "failed"
    assert len(list((tmp / "scan" / "results").glob("*.failed.parquet"))) == 1
    hidden.rename(original)
    res = scan(tmp)
    assert res.returncode == 1, res.stdout + res.stderr      # retried, and found
    assert _latest(tmp)["found.ply"]["verdict"] == "match" and _latest(tmp)["found.ply"]["recipient"] == "bob"


def test_a_forced_rescan_adds_a_record_and_keeps_the_first(world, scan):
    tmp, _ = world
    assert scan(tmp).returncode == 1
    first = read_scan(tmp / "scan")
    assert scan(tmp, "--force").returncode == 1
    rows = read_scan(tmp / "scan")
    assert len(rows) == 2 and first[0] in rows
    assert _latest(tmp)["found.ply"]["scanned_at"] > first[0]["scanned_at"]
    assert "1 already scanned" in scan(tmp).stdout       # the latest record counts


def test_a_rescan_checks_old_suspects_only_against_new_copies(world, scan):
    tmp, cfg_path = world
    write_array(tmp / "suspects", "unrelated", read_points(tmp / "assets" / "asset-1.pcd").points[::-1] * 1.5, "ply")
    assert scan(tmp).returncode == 1
    first = _latest(tmp)
    assert first["found.ply"]["n_checked"] == 2 and first["unrelated.ply"]["verdict"] == "no match"
    res = scan(tmp)                                          # nothing new: both skipped
    assert "2 already scanned" in res.stdout, res.stdout
    _run(cfg_path, serial=True, sets=["recipients=[alice, bob, carol]"])     # one new copy per asset
    assert scan(tmp).returncode == 1
    second = _latest(tmp)
    # the unmatched suspect checked only against carol's new copy of its candidate, counted on top of before
    assert second["unrelated.ply"]["n_checked"] == first["unrelated.ply"]["n_checked"] + 1
    assert second["unrelated.ply"]["verdict"] == "no match"
    assert second["found.ply"]["verdict"] == "match" and second["found.ply"]["recipient"] == "bob"
    assert second["found.ply"]["ledger_version"] != first["found.ply"]["ledger_version"]


def test_a_secret_that_opens_no_issued_key_refuses_the_scan_and_marks_nothing(world, scan):
    tmp, _ = world
    cfg = yaml.safe_load((tmp / "scan.yaml").read_text())
    (tmp / "rotated.key").write_text("a-rotated-secret-that-issued-nothing\n")
    cfg["key"]["secret_file"] = str(tmp / "rotated.key")
    (tmp / "scan.yaml").write_text(yaml.safe_dump(cfg))
    res = scan(tmp)
    assert res.returncode == 2 and "matches none of the key fingerprints" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp / "scan").exists() or not read_scan(tmp / "scan")


def test_leftover_temporary_files_are_ignored(world, scan):
    tmp, _ = world
    (tmp / "scan" / "results").mkdir(parents=True)
    (tmp / "scan" / "results" / ".found.x1y2.tmp.parquet").write_bytes(b"PAR1 half a file")
    (tmp / "out" / "manifests" / "copies" / ".part-x.parquet.tmp").write_bytes(b"junk")
    res = scan(tmp)
    assert res.returncode == 1, res.stdout + res.stderr
    assert _latest(tmp)["found.ply"]["verdict"] == "match"


def test_copies_of_an_original_since_revised_stay_attributable_and_never_read_no_match(world, scan):
    # asset-0 is revised (new bytes, at a new path) and the revision issued to carol; bob's copy of the
    # first bytes leaks.  Its check must read the first bytes, which the ledger recorded where they still are.
    tmp, cfg_path = world
    first = tmp / "assets" / "asset-0.ply"
    revised = read_points(first).points.copy()
    revised[:50] *= 1.01
    write_array(tmp / "revised", "asset-0", revised, "ply")
    _run(cfg_path, serial=True, sets=[f"catalog.source={tmp / 'revised'}", "recipients=[carol]"])
    records = [catalogue_record(a) for a in discover_assets(tmp / "revised")]
    records += [catalogue_record(a) for a in discover_assets(tmp / "assets") if a.key == "asset-1"]
    write_catalogue(records, tmp / "catalog.parquet")
    res = scan(tmp)
    assert res.returncode == 1, res.stdout + res.stderr
    assert _latest(tmp)["found.ply"]["verdict"] == "match" and _latest(tmp)["found.ply"]["recipient"] == "bob"
    first.rename(tmp / "asset-0.ply.gone")                  # the first bytes are gone from where they were issued
    carol = read_points(next((tmp / "out" / "marked" / "carol").glob("asset-0*.ply"))).points
    write_array(tmp / "suspects", "revision", attacks.apply_chain(carol, [("random_similarity", None),
                                                                          ("shuffle", None)], 3), "ply")
    res = scan(tmp, "--force")
    assert res.returncode == 1, res.stdout + res.stderr     # the run kept them in the basis store
    assert _latest(tmp)["found.ply"]["recipient"] == "bob" and _latest(tmp)["revision.ply"]["recipient"] == "carol"
    kept = tmp / "out" / "manifests" / "bases" / "originals" / f"{sha256_file(tmp / 'asset-0.ply.gone')}.ply"
    kept.unlink()                                           # and now they are nowhere
    res = scan(tmp, "--force")
    assert res.returncode == 3, res.stdout + res.stderr     # failed (and retried), never "no match"
    row = _latest(tmp)["found.ply"]
    assert row["verdict"] == "failed" and row["error"].startswith("asset-0: 2 issued copies cannot be checked")
    assert "asset-0.ply: missing" in row["error"]
    # a copy of the bytes at hand is still attributed
    assert _latest(tmp)["revision.ply"]["verdict"] == "match" and _latest(tmp)["revision.ply"]["recipient"] == "carol"


def test_a_following_scan_takes_files_that_appear_while_it_runs(world, scan):
    import threading
    import time

    tmp, _ = world
    late = attacks.apply_chain(read_points(tmp / "out" / "marked" / "alice" / "asset-1.pcd").points,
                               [("random_similarity", None), ("shuffle", None)], 5)

    def crawler():               # as a crawler saves: a hidden temporary name, then the rename
        time.sleep(1.0)
        write_array(tmp / "suspects" / "tmp", ".late", late, "ply")
        (tmp / "suspects" / "tmp" / ".late.ply").rename(tmp / "suspects" / "late.ply")

    thread = threading.Thread(target=crawler)
    thread.start()
    try:
        res = scan(tmp, "--set", "scan.follow=8")
    finally:
        thread.join()
    assert res.returncode == 1, res.stdout + res.stderr
    assert "scanned 2 suspects" in res.stdout
    latest = _latest(tmp)
    assert latest["found.ply"]["recipient"] == "bob" and latest["late.ply"]["recipient"] == "alice"
    assert "suspects 2/2" in res.stderr                   # the progress counts the file that came late


def test_the_cascade_stops_far_candidates_unregistered_and_still_counts_their_recipients(world, scan):
    from pipeline.demo import procedural_shape

    tmp, _ = world
    write_array(tmp / "suspects", "stranger", procedural_shape("shell", 3000, seed=7) * 4.0, "ply")
    cfg = yaml.safe_load((tmp / "scan.yaml").read_text())
    cfg["scan"].update(top_k=2, deep_votes=1.0, deep_shape=0.0, quick_shape=1e-6)   # nothing near enough
    (tmp / "scan.yaml").write_text(yaml.safe_dump(cfg))
    res = scan(tmp)
    assert res.returncode == 0, res.stdout + res.stderr
    row = _latest(tmp)["stranger.ply"]
    assert row["verdict"] == "no match" and row["n_stopped"] == 2
    assert row["n_checked"] == 4                          # both candidates' two recipients, never scored
    assert row["seconds_registration"] == 0.0 and "stopped by the cascade" in row["note"]
    # the copy of asset-0 is also stopped at so tight a gate: the gate, not the scan, decides what is missed
    assert _latest(tmp)["found.ply"]["verdict"] == "no match" and _latest(tmp)["found.ply"]["n_stopped"] == 2


def test_in_a_catalogue_of_two_an_original_laid_whole_leaves_the_other_asset_its_deep_steps(world, scan):
    # the blob's own check lays its unmarked original whole; with the blob left out, the torus alone
    # would draw every vote (the background's too): the votes cannot tell whether it holds the blob,
    # so the torus, sent deep by its shape at so wide a gate, keeps its deep steps
    tmp, _ = world
    original = read_points(tmp / "assets" / "asset-0.ply").points
    write_array(tmp / "suspects", "own", attacks.apply_chain(original, [("random_similarity", None),
                                                                      ("shuffle", None)], 4), "ply")
    cfg = yaml.safe_load((tmp / "scan.yaml").read_text())
    cfg["scan"].update(top_k=2, deep_shape=0.9, deep_votes=1.0)
    (tmp / "scan.yaml").write_text(yaml.safe_dump(cfg))
    res = scan(tmp)
    assert res.returncode == 1, res.stdout + res.stderr          # bob's copy is still named
    latest = _latest(tmp)
    row = latest["own.ply"]
    assert row["verdict"] == "no match" and row["n_checked"] == 4 and row["n_stopped"] == 0, row
    assert row["seconds_deep_registration"] > 0.0
    assert latest["found.ply"]["recipient"] == "bob"
    # that deep check witnessed that the blob's surface lies nowhere on the torus (kept in the basis
    # store): another copy laid whole on the blob's original is not registered on the torus again
    witnesses = [json.loads(p.read_text()) for p in (tmp / "out" / "manifests" / "bases").glob("holdings/*/*/*.json")]
    assert [(w["whole_asset_key"], w["asset_key"], w["held"]) for w in witnesses] == [("asset-0", "asset-1", False)]
    assert witnesses[0]["witness_sha256"] == row["suspect_sha256"]
    write_array(tmp / "suspects", "own-again", attacks.apply_chain(original, [("random_similarity", None),
                                                                            ("shuffle", None)], 5), "ply")
    assert scan(tmp).returncode == 0
    again = _latest(tmp)["own-again.ply"]
    assert again["verdict"] == "no match" and again["n_checked"] == 4 and again["n_stopped"] == 1, again
    assert again["seconds_deep_registration"] == 0.0 and "registered before" in again["note"], again


@pytest.fixture()
def apart_scheduler(tmp_path):
    """A Dask scheduler and two one-thread workers started as separate processes, as an operator starts them."""
    import subprocess
    import sys

    from distributed import Client

    file = tmp_path / "scheduler.json"
    env = {k: v for k, v in os.environ.items() if "SECRET" not in k and k != "DASK_SCHEDULER_ADDRESS"}
    env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
               DASK_DISTRIBUTED__WORKER__MULTIPROCESSING_METHOD="spawn")
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--scheduler-file",
                               str(file), "--port", "0", "--dashboard-address", ":0"], env=env, cwd=tmp_path,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file",
                                       str(file), "--nthreads", "1", "--nworkers", "2", "--no-dashboard"],
                                      env=env, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        with Client(scheduler_file=str(file), timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
            yield client.scheduler.address
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait(timeout=60)


def test_a_mixed_folder_is_scanned_on_a_scheduler_started_apart_and_given_by_address(world, scan, apart_scheduler):
    tmp, _ = world
    marked = tmp / "out" / "marked"
    rng = np.random.default_rng(3)
    leaks = {"leak-alice-1": (marked / "alice" / "asset-1.pcd", [("noise", 0.003)]),
             "leak-bob-0": (marked / "bob" / "asset-0.ply", [("removal", 0.3), ("random_similarity", None)]),
             "leak-alice-0": (marked / "alice" / "asset-0.ply", [("random_similarity", None)])}
    for name, (path, chain) in leaks.items():
        write_array(tmp / "suspects", name, attacks.apply_chain(read_points(path).points,
                                                                chain + [("shuffle", None)], rng), "ply")
    # the stranger: a box, like no catalogue shape
    innocents = {"stranger": attacks.box(np.random.default_rng(99), 3000, sides=(3.0, 2.0, 1.0)) * 10,
                 "unmarked": attacks.apply_chain(read_points(tmp / "assets" / "asset-1.pcd").points,
                                                 [("random_similarity", None), ("shuffle", None)], rng)}
    for name, points in innocents.items():
        write_array(tmp / "suspects", name, points, "ply")
    res = scan(tmp, "--set", f"dask.address={apart_scheduler}")
    assert res.returncode == 1, res.stdout + res.stderr
    latest = _latest(tmp)
    named = {Path(k).stem: (r["verdict"], r["recipient"]) for k, r in latest.items()}
    assert named == {"found": ("match", "bob"), "leak-alice-1": ("match", "alice"), "leak-bob-0": ("match", "bob"),
                     "leak-alice-0": ("match", "alice"), "stranger": ("no match", None),
                     "unmarked": ("no match", None)}
    # the workers it checked suspects on keep their freed memory, whatever environment their operator gave them
    from distributed import Client

    from pipeline.allocator import keeps_freed_memory
    with Client(apart_scheduler, timeout="30s") as client:
        assert set(client.run(keeps_freed_memory).values()) == {True}
