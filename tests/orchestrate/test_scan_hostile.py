"""Hostile scans: never a silent miss, never an accusation from forged or injected text (issue 36).

One small world (two 3,000-point assets issued to alice and bob) is built
once; every test scans its own suspects folder into its own ``scan.out``
through the CLI, in this process, on an in-process Dask cluster, and undoes
what it changed in the world.
"""

import contextlib
import os
import re
import shutil
import stat
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import yaml

from pipeline import cli, config
from pipeline.demo import procedural_shape
from pipeline.io.catalog import catalogue_record, discover_assets, write_catalogue
from pipeline.io.ledger import LEDGER_SCHEMA, Ledger
from pipeline.io.pointcloud import read_points, sha256_file, write_array
from pipeline.kernels import attacks
from pipeline.orchestrate.run import plan_job, run_job
from pipeline.orchestrate.progress import Progress
from pipeline.orchestrate.scan import read_scan
from tests.conftest import SMALL_DETECTION, SMALL_WATERMARK
from tests.orchestrate.test_run import SECRET, _run, make_catalogue, write_config

pytestmark = pytest.mark.slow
NEW_SECRET = "rotated-secret-for-carol-5e1"


@pytest.fixture(scope="module")
def world(tmp_path_factory, shared_cluster, scan_indexes):
    tmp = tmp_path_factory.mktemp("hostile")
    src = make_catalogue(tmp / "assets", n_assets=2)
    cfg_path = write_config(tmp, src, extra={"watermark": SMALL_WATERMARK, "detection": SMALL_DETECTION,
                                             "dask": {"address": shared_cluster.scheduler_address}})
    _run(cfg_path, serial=True)
    write_catalogue([catalogue_record(a) for a in discover_assets(src)], tmp / "catalog.parquet")
    _INDEXES.append(scan_indexes)
    yield tmp
    _INDEXES.remove(scan_indexes)


_INDEXES = []     # the session's ScanIndexes while the world is up (the index of a catalogue scanned before)


def _scan(world, name, suspects=None, *, secret_file=None, catalogue=None, ledger=None, top_k=1):
    """A config scanning ``suspects`` (default ``world/name``) into ``world/name.out``; returns its path.

    The new ``scan.out`` is given the feature index an earlier scan of the same catalogue built, if any.
    """
    for indexes in _INDEXES:
        indexes.seed(world / f"{name}.out")
    cfg = yaml.safe_load((world / "out.yaml").read_text())
    cfg["scan"] = {"suspects": str(suspects or world / name), "out": str(world / f"{name}.out"), "top_k": top_k,
                   "catalogue": str(catalogue or world / "catalog.parquet"), "manifests": ledger}
    if secret_file:
        cfg["key"]["secret_file"] = str(secret_file)
    (world / f"{name}.yaml").write_text(yaml.safe_dump(cfg))
    return world / f"{name}.yaml"


def _cli(capsys, cfg_path, *flags):
    code = cli.main(["scan", str(cfg_path), *flags])
    out, err = capsys.readouterr()
    folder = Path(yaml.safe_load(Path(cfg_path).read_text())["scan"]["out"])
    for indexes in _INDEXES:
        indexes.keep(folder)
    return code, out, err, ({os.path.basename(r["suspect_path"]): r for r in sorted(read_scan(folder),
                                                                                    key=lambda r: r["scanned_at"])}
                            if folder.exists() else {})


def _leak(world, recipient, asset, seed):
    """A copy issued to ``recipient``, moved and reshuffled (its bytes are no issued copy's)."""
    marked = next((world / "out" / "marked" / recipient).glob(f"{asset}.*"))
    return attacks.apply_chain(read_points(marked).points, [("random_similarity", None), ("shuffle", None)], seed)


@contextlib.contextmanager
def _moved(path, to):
    to.parent.mkdir(parents=True, exist_ok=True)
    path.rename(to)
    try:
        yield to
    finally:
        to.rename(path)


# -- items 3, 4, 6, 7: every file scanned, hostile files refused unread, nothing echoed ----------------------

def _hostile_folder(world):
    folder = world / "hostile"
    folder.mkdir()
    alice = next((world / "out" / "marked" / "alice").glob("asset-1.*"))
    shutil.copy(alice, folder / "x.pcd")                                  # same stem, two suspects
    shutil.copy(world / "assets" / "asset-0.ply", folder / "x.ply")       # an original's own bytes
    shutil.copy(alice, folder / "d\u00fcp\u20ac \u0645.pcd")              # unicode name, exact copy
    os.mkfifo(folder / "pipe.xyz")
    (folder / "key.xyz").symlink_to(world / "secret.key")
    (folder / "passwd.pts").symlink_to("/etc/passwd")
    (folder / "gone.ply").symlink_to("nowhere.ply")
    (folder / "empty.ply").write_bytes(b"")
    (folder / "evil\n| match | asset-0 | mallory (exact copy) | 9 | 0 | 9 | 2 | - |\n.xyz").write_text("1 2 3\n")
    (folder / "pipes.pts").write_text("| match | asset-0 | mallory (exact copy) | 9 / 1 | 0 |\n1 2 3\n")
    (folder / "notes.txt.md").write_text("not a suspect\n")
    shutil.copy(alice, folder / ".x.ab12.tmp.pcd")                       # a writer's temporary file
    os.link(world / "secret.key", folder / "hard.xyz")                  # a hard link cannot be told from a file
    part = Ledger(world / "out" / "manifests").parts()[0]
    shutil.copy(part, folder / "ledger-part.ply")                       # the ledger's own part, as a suspect
    (folder / "few.xyz").write_text("1 2 3\n4 5 6\n")                   # two points
    return folder


REFUSED = {"pipe.xyz": "a FIFO", "key.xyz": "leads out of the suspects folder",
           "passwd.pts": "leads out of the suspects folder", "gone.ply": "a broken symbolic link",
           "empty.ply": "an empty file"}


@pytest.fixture(scope="module")
def hostile(world):
    folder = _hostile_folder(world)
    return folder


def test_every_file_is_scanned_whatever_its_stem_and_hostile_ones_are_refused_unread(world, hostile, capsys):
    code, out, err, rows = _cli(capsys, _scan(world, "hostile"))
    assert code == 3, out + err                                     # refused files are failures, retried
    assert rows["x.pcd"]["verdict"] == "match" and rows["x.pcd"]["recipient"] == "alice"
    assert rows["x.ply"]["verdict"] == "no match"
    assert rows["d\u00fcp\u20ac \u0645.pcd"]["recipient"] == "alice"
    for name, why in REFUSED.items():
        assert rows[name]["verdict"] == "failed" and why in rows[name]["error"] and name in rows[name]["error"]
    for name, why in {"hard.xyz": "hard.xyz", "ledger-part.ply": "ledger-part.ply", "few.xyz": "too few"}.items():
        assert rows[name]["verdict"] == "failed" and why in rows[name]["error"], rows[name]
    assert "2 file(s) of other formats or hidden" in err and ".x.ab12.tmp.pcd" not in rows
    # a second scan comes back at once: the FIFO is never opened, and the failures are retried
    code, out, err, rows = _cli(capsys, _scan(world, "hostile"))
    assert code == 3 and f"{len(REFUSED) + 5} failed" in out and "3 already scanned" in out, out


@pytest.mark.parametrize("leak", ["secret", "passwd", "forged row"])
def test_no_file_content_and_no_forged_row_reaches_the_results_or_report(world, hostile, capsys, leak):
    code, _, _, rows = _cli(capsys, _scan(world, "hostile"))
    text = "\n".join(str(v) for r in rows.values() for v in r.values())
    report = (world / "hostile.out" / "report.md").read_text()
    if leak == "secret":
        assert SECRET[:12] not in text and SECRET[:12] not in report
    elif leak == "passwd":
        first = Path("/etc/passwd").read_text().splitlines()[0]
        assert first[:10] not in text and first[:10] not in report
    else:
        table = [re.split(r"(?<!\\)\|", line)[1:-1] for line in report.splitlines() if line.startswith("|")]
        assert len(table) == 2 + len(rows) and all(len(cells) == 9 for cells in table)   # one row per suspect
        assert not any(cells[1].strip().startswith("match") and "mallory" in cells[3] for cells in table)
        assert all("\n" not in (r["error"] or "") for r in rows.values())


def test_a_suspects_folder_that_is_the_scan_output_or_a_glob_matching_nothing_is_refused_first(world, capsys):
    (world / "self.out" / "results").mkdir(parents=True)
    for suspects in (world / "self.out", world / "self.out" / "results", str(world / "none-*.ply"),
                     str(world / "out" / "manifests" / "copies" / "*"),           # the ledger's own parts
                     world / "secret.key"):                                       # not a point-cloud file
        code, _, err, _ = _cli(capsys, _scan(world, "self", suspects))
        assert code == 2 and len(err.strip().splitlines()) == 1 and "scan.suspects" in err, err
        assert SECRET[:12] not in err
    assert not list((world / "self.out" / "results").iterdir())


@pytest.mark.parametrize("where", ["inside the suspects folder", "holding the catalogue", "the ledger",
                                   "inside the ledger", "inside the issued copies"])
def test_a_scan_output_that_touches_its_inputs_is_refused_before_anything_is_written(world, capsys, where):
    (world / "apart").mkdir(exist_ok=True)
    out = {"inside the suspects folder": world / "apart" / "scan", "holding the catalogue": world, "the ledger": world / "out" / "manifests",
           "inside the ledger": world / "out" / "manifests" / "copies" / "scan",
           "inside the issued copies": world / "out" / "marked" / "scan"}[where]
    cfg_path = _scan(world, "apart")
    cfg = yaml.safe_load(cfg_path.read_text())
    cfg["scan"]["out"] = str(out)
    cfg_path.write_text(yaml.safe_dump(cfg))
    before = sorted(p for p in world.rglob("*"))
    code, _, err, _ = _cli(capsys, cfg_path)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "scan.out" in err, err
    assert sorted(p for p in world.rglob("*")) == before


@pytest.mark.parametrize("what", ["garbage bytes", "the key file", "a CSV"])
def test_a_scan_catalogue_that_is_no_catalogue_is_refused_in_one_line(world, capsys, what):
    bad = world / f"bad-{what.split()[-1]}.parquet"
    bad.write_bytes({"garbage bytes": b"\x00\x13garbage" * 200, "the key file": (world / "secret.key").read_bytes(),
                     "a CSV": b"asset_key,path\na,b.ply\n"}[what])
    code, _, err, _ = _cli(capsys, _scan(world, "badcat", world / "apart", catalogue=bad))
    assert code == 2 and len(err.strip().splitlines()) == 1 and str(bad) in err, err
    assert SECRET[:12] not in err and "Traceback" not in err


# -- item 1: an original that left the catalogue --------------------------------------------------------------

@pytest.mark.parametrize("how", ["moved into a subfolder", "deleted", "deleted with its kept copy"])
def test_a_copy_of_an_original_that_left_the_catalogue_is_still_attributed(world, capsys, how):
    name = "left-" + how.split()[0]
    write_array(world / name, "found", _leak(world, "bob", "asset-0", 5), "ply")
    original = world / "assets" / "asset-0.ply"
    target = world / "assets" / "old" / "asset-0.ply" if how.startswith("moved") else world / "away" / "asset-0.ply"
    kept = world / "out" / "manifests" / "bases" / "originals"
    with contextlib.ExitStack() as undo:
        undo.enter_context(_moved(original, target))
        if how.endswith("kept copy"):
            name = "left-lost"
            write_array(world / name, "found", _leak(world, "bob", "asset-0", 5), "ply")
            undo.enter_context(_moved(kept, world / "kept.away"))
        write_catalogue([catalogue_record(a) for a in discover_assets(world / "assets")], world / f"{name}.parquet")
        keys = {r["asset_key"] for r in pq.read_table(world / f"{name}.parquet").to_pylist()}
        assert "asset-0" not in keys                                    # the catalogue rebuilt, as one does
        code, out, err, rows = _cli(capsys, _scan(world, name, catalogue=world / f"{name}.parquet"))
    if how.endswith("kept copy"):                                       # no file holds it: said, never "no match"
        assert code == 0 and rows["found.ply"]["verdict"] == "inconclusive", out + err
        assert rows["found.ply"]["n_unchecked"] == 2 and "whose original no file holds" in err
        assert "asset-0" in (world / f"{name}.out" / "report.md").read_text()
        # the kept copy is back: the next scan checks the suspect again (same ledger and catalogue)
        code, out, err, rows = _cli(capsys, _scan(world, name, catalogue=world / f"{name}.parquet"))
        assert code == 1 and rows["found.ply"]["verdict"] == "match" and rows["found.ply"]["recipient"] == "bob", out + err
        return
    assert code == 1, out + err
    assert rows["found.ply"]["verdict"] == "match" and rows["found.ply"]["recipient"] == "bob"
    assert rows["found.ply"]["candidate_asset"] == "asset-0"


# -- item 5: ledger rows without a valid MAC ------------------------------------------------------------------

def _forge(world, case):
    """A part file someone without the secret drops into the ledger; returns its path."""
    ledger = Ledger(world / "out" / "manifests")
    rows = [r for r in ledger.rows() if r["asset_key"] == "asset-1" and r["recipient"] == "alice"]
    forged = {k: v for k, v in rows[0].items() if k in LEDGER_SCHEMA.names}
    path = ledger.copies / "part-99990101T000000-forged000000.parquet"
    if case == "foreign part":
        pq.write_table(pa.table({"asset_key": ["asset-1"], "recipient": ["mallory"]}), path)
        return path
    if case == "forged key id":       # under a fingerprint nobody holds: unverifiable, reported, escaped
        forged.update(key_id="k\n| match | asset-1 | mallory (exact copy) | 9 | 0 | 9 | 2 | - |",
                      key_fingerprint="0123456789abcdef", recipient="mallory", row_mac=None)
        pq.write_table(pa.Table.from_pylist([forged], schema=LEDGER_SCHEMA), path)
        return path
    if case == "reassigned recipient":
        forged["recipient"] = "mallory"                                  # alice's copy, said to be mallory's
    else:
        forged.update(recipient="mallory", output_sha256=sha256_file(world / "forged sha256" / "innocent.ply"))
    pq.write_table(pa.Table.from_pylist([forged], schema=LEDGER_SCHEMA), path)
    return path


@pytest.mark.parametrize("case", ["reassigned recipient", "forged sha256", "foreign part", "forged key id"])
def test_a_forged_ledger_part_never_accuses(world, capsys, case):
    folder = world / case
    folder.mkdir()
    shutil.copy(next((world / "out" / "marked" / "alice").glob("asset-1.*")), folder / "alice-copy.pcd")
    write_array(folder, "innocent", procedural_shape("shell", 3000, seed=77) * 10, "ply")
    part = _forge(world, case)
    try:
        code, out, err, rows = _cli(capsys, _scan(world, case))
    finally:
        part.unlink()
    if case == "foreign part":
        assert code == 2 and part.name in err and len(err.strip().splitlines()) == 1, err
        assert not rows
        return
    assert code == 1, out + err
    assert rows["alice-copy.pcd"]["recipient"] == "alice"
    assert rows["innocent.ply"]["verdict"] != "match" and rows["innocent.ply"]["recipient"] is None
    report = (world / f"{case}.out" / "report.md").read_text()
    table = [re.split(r"(?<!\\)\|", line)[1:-1] for line in report.splitlines() if line.startswith("|")]
    assert all(len(cells) == 9 for cells in table) and not any("mallory" in cells[3] for cells in table)
    if case == "forged key id":
        assert "unchecked: 1 copy under key k\\\\x0a\\| match" in report     # escaped, one line
        return
    assert part.name in err and "untrusted" in err
    assert "1 ledger row(s) set aside as untrusted" in report and "mallory" not in report
    if case == "forged sha256":         # the file a set-aside row names is unchecked: never a clean no match
        assert rows["innocent.ply"]["verdict"] == "inconclusive" and rows["innocent.ply"]["n_unchecked"] == 1


# -- item 2: copies under a key the secret does not open ------------------------------------------------------

def test_copies_under_a_key_not_held_are_said_and_never_read_no_match(world, capsys, tmp_path):
    # a rotated key issues carol's copies; the scan holds only the new secret, the leak is bob's old copy
    shutil.copytree(world, tmp_path / "w", symlinks=True, ignore=shutil.ignore_patterns("*.out", "hostile"))
    w = tmp_path / "w"
    for p in w.glob("*.yaml"):
        p.write_text(p.read_text().replace(str(world), str(w)))
    (w / "new.key").write_text(NEW_SECRET)
    cfg = config.load_config(w / "out.yaml", ["recipients=[carol]", "key.id=rotated", f"key.secret_file={w / 'new.key'}"])
    assert run_job(plan_job(cfg, NEW_SECRET.encode()), cfg, serial=True, progress=Progress())["ok"] == 2
    write_array(w / "rotated", "old-leak", _leak(w, "bob", "asset-0", 7), "ply")
    shutil.copy(next((w / "out" / "marked" / "alice").glob("asset-1.*")), w / "rotated" / "old-exact.pcd")
    cfg_path = _scan(w, "rotated", secret_file=w / "new.key")
    code, out, err, rows = _cli(capsys, cfg_path)
    assert code == 0, out + err
    for name in ("old-leak.ply", "old-exact.pcd"):
        assert rows[name]["verdict"] == "inconclusive" and rows[name]["n_unchecked"] >= 1, rows[name]
        assert "under key test-key (fingerprint" in rows[name]["unchecked"]
    assert "unchecked: 4 copies under key test-key" in (w / "rotated.out" / "report.md").read_text()
    # the old secret opens them: the same versions are scanned again, and bob is named
    code, out, err, rows = _cli(capsys, _scan(w, "rotated", secret_file=w / "secret.key"))
    assert code == 1, out + err
    assert rows["old-leak.ply"]["verdict"] == "match" and rows["old-leak.ply"]["recipient"] == "bob"


# -- the listing alone: nothing is opened ---------------------------------------------------------------------

def _entry(folder, cause):
    if cause == "FIFO":
        os.mkfifo(folder / "s.ply")
    elif cause == "device":
        try:
            os.mknod(folder / "s.ply", 0o600 | stat.S_IFCHR, os.makedev(1, 3))
        except PermissionError:
            pytest.skip("no permission to make a device node")
    elif cause == "link out":
        (folder / "s.ply").symlink_to("/etc/hostname")
    elif cause == "link into a linked folder":
        (folder / "sub").symlink_to(folder.parent)
        (folder.parent / "s.ply").write_text("1 2 3\n")
        return "sub/s.ply"
    elif cause == "broken link":
        (folder / "s.ply").symlink_to("missing.ply")
    elif cause == "empty":
        (folder / "s.ply").write_bytes(b"")
    elif cause == "folder":
        (folder / "s.ply").mkdir()
    return "s.ply"


@pytest.mark.parametrize("cause, why", [("FIFO", "a FIFO"), ("device", "a character device"),
                                        ("link out", "leads out"), ("link into a linked folder", "leads out"),
                                        ("broken link", "broken"), ("empty", "empty"), ("folder", "a folder")])
def test_a_hostile_entry_is_listed_with_its_refusal_and_never_opened(tmp_path, cause, why):
    from pipeline.io.catalog import list_suspects

    folder = tmp_path / "suspects"
    folder.mkdir()
    (folder / "x.xyz").write_text("1 2 3\n")
    (folder / "x.obj").write_text("v 1 2 3\n")
    (folder / "loop").symlink_to(folder)                                 # a link loop: never followed
    name = _entry(folder, cause)
    suspects, _ = list_suspects(f"{folder}/**/*.*")                       # "**" follows no link to a folder
    found = {p.relative_to(folder).as_posix(): reason for p, reason in suspects}
    assert found["x.xyz"] is None and found["x.obj"] is None            # same stem: two suspects
    assert not any(k.startswith("loop/") for k in found)
    if "/" in name:                                                      # a wildcard folder does follow it
        found = {p.relative_to(folder).as_posix(): why for p, why in list_suspects(f"{folder}/*/*.ply")[0]}
    assert why in found[name]


# -- suspect names that are markup: Markdown, mathtext, newlines ----------------------------------------------

def test_a_leak_whose_name_is_markup_is_attributed_with_its_evidence(world, capsys):
    names = ["leak $\\undefinedcmd{x}$", "leak\nwith | pipes | `ticks`"]
    for i, name in enumerate(names):
        write_array(world / "markup", name, _leak(world, "bob", "asset-0", 20 + i), "ply")
    code, out, err, rows = _cli(capsys, _scan(world, "markup"))
    assert code == 1, out + err
    for name in names:
        row = rows[f"{name}.ply"]
        assert row["recipient"] == "bob" and row["evidence_path"] and Path(row["evidence_path"]).is_file(), row
    assert not any(line.startswith("with |") for line in err.splitlines())     # a name never starts a line


def test_suspects_in_hidden_subfolders_are_scanned_too(tmp_path):
    # a crawler's ".cache/" or a user's ".trash/": never skipped unsaid
    from pipeline.io.catalog import list_suspects

    write_array(tmp_path / ".hidden", "leak", procedural_shape("blob", 100, seed=1), "ply")
    suspects, _ = list_suspects(tmp_path)
    assert [(p.name, why) for p, why in suspects] == [("leak.ply", None)]
