"""Issuing never destroys an input, never publishes a copy without its row, never starts over silently.

Crashes are real: a subprocess running the catalogue job kills itself with
SIGKILL at one step of issuing (the functions it patches are the run's own,
called as usual up to that point), and the next run must leave every
published copy with exactly one row whose sha256 matches its file.  A full
disk is a real tmpfs of a few kilobytes.
"""

import contextlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

from pipeline import config
from pipeline.io.ledger import Ledger, LedgerError
from pipeline.io.paths import copy_path
from pipeline.io.pointcloud import sha256_file
from pipeline.orchestrate.progress import Progress
from pipeline.orchestrate.run import plan_job, run_job
from tests.conftest import ROOT
from tests.orchestrate.test_run import SECRET, make_catalogue, write_config

pytestmark = pytest.mark.slow


def _cli(tmp, *args):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env.pop("POINTMARK_SECRET", None)
    return subprocess.run([sys.executable, "-m", "pipeline.cli", *args], cwd=tmp, env=env, capture_output=True,
                          text=True, timeout=600)


def _config(tmp, src, **output):
    path = write_config(tmp, src)
    cfg = yaml.safe_load(path.read_text())
    cfg["output"].update({k: str(v) for k, v in output.items()})
    path.write_text(yaml.safe_dump(cfg))
    return path


def _tree(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def _check_ledger_against_files(manifests, marked):
    """Every published copy has exactly one ok row whose sha256 is its file's; nothing half-written."""
    rows = [r for r in Ledger(manifests).rows(status=None)]
    ok = [r for r in rows if r["status"] == "ok"]
    published = sorted(p for p in Path(marked).rglob("*") if p.is_file() and not p.name.startswith("."))
    by_path = {}
    for r in ok:
        by_path.setdefault(r["output_path"], []).append(r)
    for p in published:
        assert len(by_path.get(str(p), [])) == 1, f"{p}: {len(by_path.get(str(p), []))} rows"
        assert by_path[str(p)][0]["output_sha256"] == sha256_file(p)
    assert sorted(by_path) == [str(p) for p in published]      # and every ok row has its file
    leftovers = [p for p in Path(marked).rglob(".*")] + [p for p in Path(manifests).rglob(".*") if p.is_file()]
    assert not leftovers, leftovers
    assert not list((Path(manifests) / "intents").glob("*.json"))
    return ok


# -- outputs never touch inputs ------------------------------------------------------------------

@pytest.mark.parametrize("case", ["dir is the catalogue", "dir holds the catalogue", "dir inside the catalogue",
                                  "manifests inside the catalogue", "bases inside the catalogue",
                                  "dir is a file", "bases is a file", "dir name too long",
                                  "recipient folder is an asset folder", "dir is the ledger",
                                  "dir inside the ledger", "dir holds the basis store"])
def test_outputs_that_touch_the_catalogue_are_refused_before_anything_is_written(tmp_path, case):
    src = make_catalogue(tmp_path / "assets", n_assets=2)
    (tmp_path / "a-file").write_text("not a folder\n")
    output = {"dir is the catalogue": {"dir": src},
              "dir holds the catalogue": {"dir": tmp_path},
              "dir inside the catalogue": {"dir": src / "marked"},
              "manifests inside the catalogue": {"manifests": src / "ledger"},
              "bases inside the catalogue": {"bases": src / "store"},
              "dir is a file": {"dir": tmp_path / "a-file" / "marked"},
              "bases is a file": {"bases": tmp_path / "a-file"},
              "dir name too long": {"dir": tmp_path / ("x" * 300)},
              "recipient folder is an asset folder": {"dir": "."},
              "dir is the ledger": {"dir": tmp_path / "out" / "l", "manifests": tmp_path / "out" / "l"},
              "dir inside the ledger": {"dir": tmp_path / "out" / "manifests" / "bases"},
              "dir holds the basis store": {"bases": tmp_path / "out" / "marked" / "store"}}[case]
    cfg = _config(tmp_path, src, **output)
    before = _tree(tmp_path)
    res = _cli(tmp_path, "run", str(cfg))
    assert res.returncode == 2, res.stdout + res.stderr
    [line] = res.stderr.strip().splitlines()
    assert "config: output." in line and "Traceback" not in res.stderr
    assert _tree(tmp_path) == before and not (tmp_path / "out").exists()


def test_copy_names_never_collide_whatever_the_asset_keys(tmp_path):
    # asset "a" at generation 2 and an asset named "a.g2" once wrote the same file
    assert len({copy_path("o", "r", k, g, ".ply") for k in ("a", "a.g2", "a.g2.g1", "a.g02", "a.g")
                for g in (1, 2, 3)}) == 15
    src = tmp_path / "assets"
    make_catalogue(src, n_assets=1, formats=("ply",))
    (src / "asset-0.ply").rename(src / "a.ply")
    cfg = write_config(tmp_path, src)
    assert _run_ok(cfg)["ok"] == 1
    make_catalogue(tmp_path / "more", n_assets=1, formats=("ply",))
    (tmp_path / "more" / "asset-0.ply").rename(src / "a.g2.ply")
    assert _run_ok(cfg, sets=["beta=0.003"])["ok"] == 2        # a: generation 2; a.g2: generation 1
    ok = _check_ledger_against_files(tmp_path / "out" / "manifests", tmp_path / "out" / "marked")
    assert len(ok) == 6 and len({r["output_path"] for r in ok}) == 6
    assert {(r["asset_key"], r["generation"]) for r in ok} == {("a", 1), ("a", 2), ("a.g2", 1)}


def test_an_unrecorded_file_at_a_planned_path_is_refused_not_overwritten(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=1, formats=("ply",))
    cfg = write_config(tmp_path, src)
    squatter = tmp_path / "out" / "marked" / "alice" / "asset-0.ply"
    squatter.parent.mkdir(parents=True)
    squatter.write_bytes(b"someone else's file\n")
    res = _cli(tmp_path, "run", str(cfg))
    assert res.returncode == 2 and str(squatter) in res.stderr and "no ledger row" in res.stderr
    assert squatter.read_bytes() == b"someone else's file\n"
    assert not (tmp_path / "out" / "manifests").exists()


def _run_ok(cfg_path, sets=(), serial=True):
    cfg = config.load_config(cfg_path, sets)
    return run_job(plan_job(cfg, SECRET.encode()), cfg, serial=serial, progress=Progress())


# -- nothing is created before every check has passed ---------------------------------------------

@pytest.mark.parametrize("case", ["missing catalogue", "bad recipient", "bad shard", "no key id"])
def test_a_refused_run_creates_no_ledger_folder(tmp_path, case):
    src = make_catalogue(tmp_path / "assets", n_assets=1)
    cfg = write_config(tmp_path, src if case != "missing catalogue" else tmp_path / "nowhere")
    data = yaml.safe_load(cfg.read_text())
    if case == "bad recipient":
        data["recipients"] = ["alice", "../evil"]
    if case == "no key id":
        data["key"]["id"] = None
    cfg.write_text(yaml.safe_dump(data))
    res = _cli(tmp_path, "run", str(cfg), *(["--shard", "3/2"] if case == "bad shard" else []))
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert not (tmp_path / "out").exists()


# -- the deployment salt is never recreated silently ----------------------------------------------

def test_a_lost_deployment_file_is_an_error_that_says_how_to_restore_it(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=1)
    cfg = write_config(tmp_path, src)
    assert _run_ok(cfg)["ok"] == 1
    deployment = tmp_path / "out" / "manifests" / "deployment.json"
    salt = yaml.safe_load(deployment.read_text())["salt"]
    deployment.unlink()
    parts = Ledger(tmp_path / "out" / "manifests").parts()
    res = _cli(tmp_path, "run", str(cfg), "--set", "recipients=[alice,bob,carol]")
    assert res.returncode == 2 and str(deployment) in res.stderr and salt in res.stderr
    assert Ledger(tmp_path / "out" / "manifests").parts() == parts and not deployment.exists()
    hint = res.stderr.split("restore it with: ", 1)[1].split(" (the salt", 1)[0]
    subprocess.run(hint, shell=True, check=True, cwd=tmp_path)
    counts = _run_ok(cfg, sets=["recipients=[alice,bob,carol]"])
    assert counts["ok"] == 1
    ok = _check_ledger_against_files(tmp_path / "out" / "manifests", tmp_path / "out" / "marked")
    assert len(ok) == 3 and {r["generation"] for r in ok} == {1}        # carol joined generation 1


# -- crash safety: kill -9 at each step of issuing -------------------------------------------------

_CRASH = textwrap.dedent("""
    import os, signal, sys
    from pipeline import config
    from pipeline.io.ledger import Ledger
    from pipeline.orchestrate import run
    from pipeline.orchestrate.progress import Progress

    step = sys.argv[2]
    real_append, real_publish = Ledger.append, run._publish
    calls = []

    def die():
        os.kill(os.getpid(), signal.SIGKILL)

    def append(self, rows, mac_key=None):
        if step == "after the pending write" and any(r["status"] == "ok" for r in rows):
            die()
        return real_append(self, rows, mac_key=mac_key)

    def publish(pending, final):
        if step == "after the row":
            die()
        real_publish(pending, final)
        if step == "after the publish":
            die()

    Ledger.append, run._publish = append, publish
    cfg = config.load_config(sys.argv[1])
    run.run_job(run.plan_job(cfg, open(cfg["key"]["secret_file"]).read().strip().encode()), cfg, serial=True,
                progress=Progress())
""")


@pytest.mark.parametrize("step", ["after the pending write", "after the row", "after the publish"])
def test_a_run_killed_at_any_step_of_issuing_is_finished_by_the_next(tmp_path, step):
    src = make_catalogue(tmp_path / "assets", n_assets=2)
    cfg = write_config(tmp_path, src)
    (tmp_path / "crash.py").write_text(_CRASH)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, str(tmp_path / "crash.py"), str(cfg), step], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == -9, res.stderr
    manifests, marked = tmp_path / "out" / "manifests", tmp_path / "out" / "marked"
    published = [p for p in marked.rglob("*") if p.is_file() and not p.name.startswith(".")]
    recorded = {r["output_path"] for r in Ledger(manifests).rows()}
    assert all(str(p) in recorded for p in published)         # even mid-crash: no copy without its row
    assert list((manifests / "intents").glob("*.json"))       # the interrupted run's intent is left
    assert _run_ok(cfg)["failed"] == 0
    ok = _check_ledger_against_files(manifests, marked)
    assert sorted((r["asset_key"], r["recipient"]) for r in ok) == [
        (f"asset-{i}", r) for i in range(2) for r in ("alice", "bob")]


# -- a full disk ------------------------------------------------------------------------------------

@contextlib.contextmanager
def _small_disk(folder, kib):
    folder.mkdir(parents=True)
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={kib}k", "tmpfs", str(folder)], capture_output=True,
                         text=True)
    if res.returncode != 0:
        pytest.fail(f"a full-disk test needs a tmpfs mount (root in its own mount namespace): {res.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


def _fill(folder, leave_kib):
    """Fill a tmpfs but ``leave_kib`` KiB."""
    st = os.statvfs(folder)
    free = st.f_bavail * st.f_frsize - leave_kib * 1024
    with open(folder / "filler", "wb") as f:
        f.write(b"\0" * max(free, 0))
    return folder / "filler"


@pytest.mark.parametrize("where", ["outputs", "ledger"])
def test_a_full_disk_issues_nothing_half_and_the_rerun_completes(tmp_path, where):
    src = make_catalogue(tmp_path / "assets", n_assets=2)
    with _small_disk(tmp_path / "small", 2048) as small:
        output = ({"dir": small / "marked"} if where == "outputs" else
                  {"manifests": small / "manifests", "bases": tmp_path / "bases"})
        cfg = _config(tmp_path, src, **output)
        marked = Path(yaml.safe_load(cfg.read_text())["output"]["dir"])
        manifests = Path(yaml.safe_load(cfg.read_text())["output"]["manifests"])
        filler = _fill(small, 24 if where == "ledger" else 8)
        res = _cli(tmp_path, "run", str(cfg))
        assert res.returncode in (1, 2), res.stdout + res.stderr
        assert "Traceback" not in res.stderr and "no space left" in res.stderr.lower()
        assert str(small) in res.stderr                       # the message names the file
        if manifests.exists():
            rows = Ledger(manifests).rows(status=None)
            assert all(r["status"] == "failed" for r in rows)
            assert not [p for p in (manifests / "copies").glob(".*")] if (manifests / "copies").exists() else True
        assert not [p for p in marked.rglob("*") if p.is_file()] if marked.exists() else True
        filler.unlink()
        assert _run_ok(cfg)["failed"] == 0
        ok = _check_ledger_against_files(manifests, marked)
        assert len(ok) == 4


# -- rows are authenticated, and the ledger refuses foreign parts -----------------------------------

def test_rows_carry_a_mac_and_a_foreign_or_altered_part_is_refused_by_name(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    from pipeline.io.ledger import MAC_FIELDS
    from pipeline.kernels import keys

    src = make_catalogue(tmp_path / "assets", n_assets=1)
    cfg = write_config(tmp_path, src)
    assert _run_ok(cfg)["ok"] == 1
    ledger = Ledger(tmp_path / "out" / "manifests")
    mac_key = keys.ledger_mac_key(SECRET.encode())
    rows = ledger.rows()
    assert all(r["row_mac"] == keys.row_mac(mac_key, r, MAC_FIELDS) for r in rows)
    assert keys.row_mac(mac_key, {**rows[0], "recipient": "mallory"}, MAC_FIELDS) != rows[0]["row_mac"]
    assert keys.row_mac(keys.ledger_mac_key(b"another secret of 24 b"), rows[0], MAC_FIELDS) != rows[0]["row_mac"]
    foreign = ledger.copies / "part-99999999T000000-foreign.parquet"
    pq.write_table(pa.table({"asset_key": [1, 2], "who": ["x", "y"]}), foreign)
    with pytest.raises(LedgerError, match=str(foreign)):
        ledger.rows()
    foreign.unlink()
    bad = ledger.copies / "part-99999999T000000-salt.parquet"
    pq.write_table(pa.Table.from_pylist([{**{k: v for k, v in rows[0].items() if k != "ledger_part"},
                                          "key_salt": "zz"}], schema=pq.read_schema(ledger.parts()[0])), bad)
    with pytest.raises(LedgerError, match="key_salt"):
        ledger.rows()
    res = _cli(tmp_path, "run", str(cfg))
    assert res.returncode == 2 and str(bad) in res.stderr and len(res.stderr.strip().splitlines()) == 1
    bad.unlink()
    other = tmp_path / "elsewhere.parquet"                     # a part of another ledger, linked in
    other.write_bytes(ledger.parts()[0].read_bytes())
    (ledger.copies / "part-99999999T000000-link.parquet").symlink_to(other)
    with pytest.raises(LedgerError, match="a link or not a regular file"):
        ledger.rows()


# -- a secret or salt other than the ledger's never starts a generation silently ----------------------

@pytest.mark.parametrize("case", ["another secret under the key id", "another ledger's salt"])
def test_a_wrong_secret_or_salt_is_refused_not_a_new_generation(tmp_path, case):
    import json

    src = make_catalogue(tmp_path / "assets", n_assets=1)
    cfg = write_config(tmp_path, src)
    assert _run_ok(cfg)["ok"] == 1
    if case == "another secret under the key id":
        (tmp_path / "secret.key").write_text("a different master secret, 41 bytes long\n")
    else:
        (tmp_path / "out" / "manifests" / "deployment.json").write_text(json.dumps({"salt": "0" * 32}))
    parts = Ledger(tmp_path / "out" / "manifests").parts()
    res = _cli(tmp_path, "run", str(cfg), "--set", "beta=0.004")
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert ("another secret" in res.stderr) == (case == "another secret under the key id")
    assert Ledger(tmp_path / "out" / "manifests").parts() == parts


def test_a_glob_catalogue_never_reads_through_a_link_out_of_its_folder(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=1)
    (src / "key.pts").symlink_to(tmp_path / "secret.key")
    cfg = write_config(tmp_path, f"{src}/**/*")
    assert _run_ok(cfg)["ok"] == 1        # the real asset; the link is a failed row, never opened
    failed = Ledger(tmp_path / "out" / "manifests").rows(status="failed")
    assert {r["asset_key"] for r in failed} == {"key"} and len(failed) == 2       # alice's and bob's
    # nothing of the key file, not even its size, reaches the error (the path itself may hold any digits)
    said = [r["error"].replace(str(src / "key.pts"), "") for r in failed]
    assert all("leaves the catalogue folder" in e and SECRET not in e and str(len(SECRET)) not in e for e in said)


def test_a_row_without_a_valid_mac_under_the_runs_key_stops_the_run(tmp_path):
    # a forged row claiming a copy for carol was counted as "already issued" and never said
    src = make_catalogue(tmp_path / "assets", n_assets=1)
    cfg = write_config(tmp_path, src)
    assert _run_ok(cfg)["ok"] == 1
    ledger = Ledger(tmp_path / "out" / "manifests")
    row = ledger.rows()[0]
    forged = ledger.append([{**row, "recipient": "carol", "output_path": str(tmp_path / "pwned.xyz")}])
    res = _cli(tmp_path, "run", str(cfg), "--set", "recipients=[alice,bob,carol]")
    assert res.returncode == 2 and str(forged) in res.stderr and "row MAC" in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and not (tmp_path / "pwned.xyz").exists()
    assert len(ledger.rows()) == 3


@pytest.mark.parametrize("source", ["one file", "a catalogue file beside the outputs"])
def test_outputs_beside_a_catalogue_file_or_one_file_are_accepted(tmp_path, source):
    # such a source names its files: an output folder beside them is never read back as assets
    from pipeline.io.catalog import catalogue_record, discover_assets, write_catalogue

    make_catalogue(tmp_path, n_assets=1, formats=("ply",))
    if source == "one file":
        cfg = write_config(tmp_path, tmp_path / "asset-0.ply")
    else:
        write_catalogue([catalogue_record(a) for a in discover_assets(tmp_path / "asset-0.ply")],
                        tmp_path / "catalog.parquet")
        cfg = write_config(tmp_path, tmp_path / "catalog.parquet")
    assert _run_ok(cfg)["ok"] == 1
    _check_ledger_against_files(tmp_path / "out" / "manifests", tmp_path / "out" / "marked")


def test_a_glob_that_matches_no_asset_is_refused_and_a_trailing_double_star_reads_every_file(tmp_path):
    src = make_catalogue(tmp_path / "assets", n_assets=2)
    res = _cli(tmp_path, "run", str(write_config(tmp_path, f"{src}/*.nothing")))
    assert res.returncode == 2 and "matches no point-cloud file" in res.stderr
    assert _run_ok(write_config(tmp_path, f"{src}/**"))["ok"] == 2
