"""Hostile config values, secrets, catalogue sources and attack arguments (issue #36, engineer A's slice).

Each test is one cause: exit status 2 (or ConfigError / InputError / SecretError in process), one line
that names the file or the key and the problem, and nothing written.
"""

import os
import subprocess
import sys

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline import config
from pipeline.cli import main
from pipeline.io.catalog import catalogue_record, discover_assets
from pipeline.io.pointcloud import InputError
from pipeline.io.secrets import SecretError, check_key_id, load_secret
from pipeline.kernels.attacks import chain_size, check_strength
from tests.conftest import ROOT, sphere_patch
from tests.test_cli import _ply

SECRET = "hostile-config-secret-5c1e"
PASTED = "2120398471029384710293847102938470192384709"     # a numeric secret pasted as a path


def _refused(capsys, argv, *needles):
    """main(argv) exits 2 with one stderr line holding every needle; returns that line."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    for needle in needles:
        assert needle in err, err
    return err


def _config_error(text, tmp_path, overrides=()):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(config.ConfigError) as info:
        config.load_config(path, overrides)
    message = str(info.value)
    assert "\n" not in message
    return message


# -- 1. schema errors under key never show the value -----------------------------------------------

@pytest.mark.parametrize("text,overrides,needle", [
    (f"key:\n  secret_file: {PASTED}\n", (), "key.secret_file"),
    (f"key:\n  secret_file: [{PASTED}, 1]\n", (), "key.secret_file"),
    (f"key:\n  id: \"{PASTED}\\t\"\n", (), "key.id"),
    (f"key:\n  {PASTED}: 1\n", (), "key: the key is not a string"),
    (f"key:\n  '{PASTED}': 1\n", (), "key: unknown key(s) 1 (names not shown)"),
    ("key:\n  secret_file: .nan\n", (), "key.secret_file"),
    ("{}\n", (f"key.secret_file=[{PASTED}",), "--set key.secret_file"),
    ("{}\n", (f"key.id=[{PASTED}]",), "key.id"),
    ("{}\n", (PASTED,), "--set"),
])
def test_errors_under_key_never_show_the_value(tmp_path, text, overrides, needle):
    message = _config_error(text, tmp_path, overrides)
    assert needle in message and PASTED not in message and PASTED[:12] not in message


def test_other_keys_show_a_short_escaped_value(tmp_path):
    message = _config_error("output:\n  dir: 5\n", tmp_path)
    assert "output.dir: 5 is not of type 'string'" in message
    message = _config_error(f"dask:\n  memory_limit: \"{'x' * 500}\"\n", tmp_path)
    assert "dask.memory_limit" in message and len(message) < 250


# -- 2. weak or leaked secrets -------------------------------------------------------------------

@pytest.mark.parametrize("value,needle", [
    (" " * 20, "only white space"),
    ("\t \n" * 8, "only white space"),
    ("a" * 30 + "bcdef", "one repeated byte"),
    ("0" * 16 + "123456789abcdef", "one repeated byte"),
    ("short", "at least 16"),
    ("\ud800" * 20, "not shown"),                  # a lone surrogate: no bytes to take
])
def test_weak_secrets_are_refused_without_quoting_them(value, needle):
    with pytest.raises(SecretError) as info:
        load_secret(environ={"POINTMARK_SECRET": value})
    assert needle in str(info.value) and value not in str(info.value)


def test_a_non_utf8_secret_is_taken_as_its_bytes():
    raw = b"\xff\xfe-not-utf8-but-random-enough-9f3"
    value = raw.decode("utf-8", "surrogateescape")       # how os.environ holds it on POSIX
    assert load_secret(environ={"POINTMARK_SECRET": value}) == raw


@pytest.mark.parametrize("content", [b"x" * 5000, b"\x00" * 64])
def test_unusable_key_files_are_refused_without_their_path(tmp_path, content):
    path = tmp_path / "hidden-keys" / "k.key"
    path.parent.mkdir()
    path.write_bytes(content)
    with pytest.raises(SecretError) as info:
        load_secret(path)
    assert "hidden-keys" not in str(info.value) and "secret file" in str(info.value)


@pytest.mark.parametrize("key_id", [SECRET, f"id-{SECRET}-x", SECRET[3:15], "a\tb", "", "x" * 200])
def test_key_ids_holding_the_secret_or_not_one_line_are_refused(key_id):
    with pytest.raises(SecretError) as info:
        check_key_id(key_id, SECRET.encode(), "key.id")
    assert "key.id" in str(info.value) and (not key_id or key_id not in str(info.value))
    assert check_key_id("asset-key-1", SECRET.encode()) == "asset-key-1"


def test_embed_and_run_refuse_the_secret_as_key_id(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("POINTMARK_SECRET", SECRET)
    src = _ply(tmp_path / "m.ply", sphere_patch(500))
    err = _refused(capsys, ["embed", str(src), str(tmp_path / "o.ply"), "--key-id", SECRET, "--message", "1"],
                   "--key-id", "holds the secret")
    assert SECRET not in err
    cfg = tmp_path / "run.yaml"
    cfg.write_text(f"key:\n  id: {SECRET}\ncatalog:\n  source: {tmp_path}\noutput:\n"
                   f"  dir: {tmp_path / 'out'}\n  manifests: {tmp_path / 'ledger'}\n")
    assert SECRET not in _refused(capsys, ["run", str(cfg), "--serial"], "key.id", "holds the secret")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply", "run.yaml"]


# -- 3. integer-valued floats are ints, uniformly -------------------------------------------------

@pytest.mark.parametrize("assignment,path,value", [
    ("chip_rate=6.0", ("watermark", "chip_rate"), 6),
    ("n_clusters=2.0", ("watermark", "n_clusters"), 2),
    ("iterations=2.0", ("detection", "iterations"), 2),
    ("dask.n_workers=1.0", ("dask", "n_workers"), 1),
    ("seeds=[3.0, 7.0]", ("watermark", "seeds"), [3, 7]),
    ("tile_points=5e3", ("watermark", "tile_points"), 5000),
    ("shards=2.0", ("workflow", "shards"), 2),
])
def test_integer_valued_floats_become_ints(assignment, path, value):
    extra = ["cover=true", "seeds=null"] if "tile_points" in assignment else []
    cfg = config.load_config(overrides=[assignment, *extra])
    got = cfg[path[0]][path[1]]
    assert got == value and all(type(v) is int for v in (got if isinstance(got, list) else [got]))


def test_seed_coordinates_stay_floats():
    assert config.load_config(overrides=["seeds=[[1.0, 2.0, 3.5]]"])["watermark"]["seeds"] == [[1.0, 2.0, 3.5]]


# -- 4 and 6. every value checked for type, finiteness and range --------------------------------

@pytest.mark.parametrize("assignment,needle", [
    ("seeds=[[1e300, 0, 0]]", "watermark.seeds.0.0: 1e+300 is greater than the maximum"),
    ("seeds=[-1]", "watermark.seeds.0: -1 is less than the minimum"),
    ("ridge=1e308", "detection.ridge: 1e+308 is greater than the maximum"),
    ("outlier_trim=1e300", "detection.outlier_trim"),
    ("chip_rate=6.5", "watermark.chip_rate: 6.5 is not of type 'integer'"),
    ("n_clusters=1e300", "watermark.n_clusters: 1e+300 is not of type 'integer'"),
    ("chip_rate=-1", "watermark.chip_rate: -1 is less than the minimum of 1"),
    ("n_bits=100000", "watermark.n_bits: 100000 is greater than the maximum"),
    ("cluster_size=1000000000000", "watermark.cluster_size"),
    ("beta=.nan", "watermark.beta: nan is not a finite number"),
    ("max_displacement=1e-320", "watermark.max_displacement"),
    ("max_displacement=0", "watermark.max_displacement"),
    ("dask.memory_limit=lots", "dask.memory_limit: 'lots' is not a memory size"),
    ("dask.address=garbage://x", "dask.address: 'garbage://x' is not a scheduler address"),
    ("dask.address=tcp://host:99999", "dask.address: port 99999"),
    ("dask.address=tcp://host", "dask.address"),
    ("dask.n_workers=100000", "dask.n_workers: 100000 is greater than the maximum of 1024"),
    ("dask.n_workers=0", "dask.n_workers"),
    ("output.dir=\"a\\0b\"", "output.dir: the text holds a NUL byte"),
    ("catalog.source=\"x\\0.ply\"", "catalog.source: the text holds a NUL byte"),
    ("recipients=[\"alice\\n\"]", "recipients.0: recipient 'alice\\n' is not a valid id"),
    ("recipients=[\"../evil\"]", "recipients.0: recipient '../evil' is not a valid id"),
    ("recipients=[alice, alice]", "recipients: ['alice', 'alice'] has non-unique elements"),
    ("top_k=100000", "scan.top_k"),
    ("max_bit_errors=-1", "scan.max_bit_errors"),
    ("epsilon=0", "detection.epsilon"),
    ("experiments=[{name: a, models: [m], attacks: [noise], parameters: [{betta: 1}]}]",
     "evaluate.experiments.0.parameters.0: unknown key(s) betta"),
    ("experiments=[{name: a, models: [m], attacks: [noise], parameters: [{chip_rate: .inf}]}]",
     "not a finite number"),
    ("nonsense=1", "--set nonsense: no such config key"),
])
def test_bad_values_are_refused_naming_the_key(assignment, needle):
    with pytest.raises(config.ConfigError) as info:
        config.load_config(overrides=[assignment])
    assert needle in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("assignment", ["dask.memory_limit=4GB", "dask.memory_limit=512 MiB",
                                        "dask.memory_limit=2e9", "dask.address=tcp://127.0.0.1:8786",
                                        "dask.address=tls://[::1]:8786", "epsilon=1e-9",
                                        "max_displacement=1e-6", "recipients=[alice, bob@x.org]"])
def test_good_values_stay_accepted(assignment):
    config.load_config(overrides=[assignment])


# -- 5. the YAML itself -----------------------------------------------------------------------------

@pytest.mark.parametrize("text,needles", [
    ("watermark:\n  beta: 0.001\nwatermark:\n  beta: 0.002\n", ["'watermark' is given twice", "line 3"]),
    ("watermark:\n  beta: 0.001\n  beta: 0.002\n", ["'beta' is given twice (first on line 2)", "line 3"]),
    ("- watermark\n- beta\n", ["must be a mapping of sections"]),
    ("watermark:\n\tbeta: 1\n", ["not valid YAML", "line 2"]),
    ("watermark: !!python/object:os.system x\n", ["not valid YAML"]),
    ("a: &a [*a]\n", ["alias refers to itself"]),
])
def test_bad_yaml_is_refused_with_the_line(tmp_path, text, needles):
    message = _config_error(text, tmp_path)
    assert all(n in message for n in needles) and "c.yaml" in message


def test_yaml_reads_exponents_as_numbers_and_keeps_merge_keys(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("detection:\n  epsilon: 1e-9\n  p_threshold: 1E-5\nwatermark:\n  beta: 2e-3\n")
    cfg = config.load_config(path)
    assert (cfg["detection"]["epsilon"], cfg["detection"]["p_threshold"], cfg["watermark"]["beta"]) == \
        (1e-9, 1e-5, 0.002)
    path.write_text("base: &b {n_bits: 8}\n")      # an unknown top-level key: still refused as such
    with pytest.raises(config.ConfigError, match="unknown key"):
        config.load_config(path)
    path.write_text("")
    assert config.load_config(path)["watermark"]["n_bits"] == 32       # an empty file: the defaults


def test_a_huge_config_is_refused_before_it_is_parsed(tmp_path):
    path = tmp_path / "big.yaml"
    path.write_bytes(b"# " + b"x" * (5 << 20) + b"\n")
    with pytest.raises(config.ConfigError, match=r"big\.yaml: .* a config is at most"):
        config.load_config(path)


# -- 6 and 9. catalogue sources -----------------------------------------------------------------

def _parquet(path, columns):
    pq.write_table(pa.table(columns), path)
    return path


@pytest.mark.parametrize("name,make,needle", [
    ("garbage.parquet", lambda p: p.write_bytes(b"PAR1 this is not parquet" * 50), "not a readable Parquet"),
    ("bad.csv", lambda p: p.write_bytes(b"asset_key,path\nb\xe9b\xe9,x.ply\n"), "not a UTF-8 CSV catalogue"),
    ("wide.csv", lambda p: p.write_text("asset_key,path\na,x.ply,extra\n"), "more fields than the header"),
    ("str.parquet", lambda p: _parquet(p, {"asset_key": ["a"], "path": ["x.ply"], "recipients": ["alice"]}),
     "recipients is not a list of names"),
    ("evil.parquet", lambda p: _parquet(p, {"asset_key": ["a"], "path": ["x.ply"], "recipients": [["../e"]]}),
     "recipient '../e' is not a valid id"),
    ("nopath.parquet", lambda p: _parquet(p, {"asset_key": ["a"], "path": [3]}), "path is not a text path"),
    ("missing.parquet", lambda p: None, "no such catalogue file or folder"),
    ("missing-folder", lambda p: None, "no such catalogue file or folder"),
])
def test_bad_catalogue_sources_are_refused_naming_the_file(tmp_path, name, make, needle):
    make(tmp_path / name)
    with pytest.raises(InputError) as info:
        discover_assets(tmp_path / name)
    assert str(tmp_path / name) in str(info.value) and needle in str(info.value)


def test_a_link_out_of_the_catalogue_folder_is_a_failed_row_unread(tmp_path, capsys):
    folder = tmp_path / "cat"
    folder.mkdir()
    _ply(folder / "good.ply", sphere_patch(300))
    key = tmp_path / "master.key"
    key.write_text(SECRET + "\n")
    (folder / "key.ply").symlink_to(key)
    (folder / "passwd.ply").symlink_to("/etc/passwd")
    (folder / "inside.ply").symlink_to(folder / "good.ply")      # a link within the folder is fine
    rows = {a.key: catalogue_record(a) for a in discover_assets(folder)}
    assert rows["good"]["status"] == rows["inside"]["status"] == "ok"
    for name in ("key", "passwd"):
        assert rows[name]["status"] == "failed" and "symlink leaves the catalogue folder" in rows[name]["error"]
    assert main(["catalog", "build", str(folder), "--out", str(tmp_path / "c.parquet")]) == 1
    out = capsys.readouterr()
    assert SECRET not in out.out + out.err and "root:" not in out.out + out.err


@pytest.mark.parametrize("recipients,needle", [("../evil", "'../evil'"), ("alice,alice", "twice"),
                                               ("a/b", "'a/b'"), (".hidden", "'.hidden'")])
def test_catalog_build_refuses_bad_recipients_before_reading(tmp_path, capsys, recipients, needle):
    _ply(tmp_path / "a.ply", sphere_patch(300))
    _refused(capsys, ["catalog", "build", str(tmp_path), "--out", str(tmp_path / "c.parquet"),
                      "--recipients", recipients], "--recipients", needle)
    assert not (tmp_path / "c.parquet").exists()


@pytest.mark.parametrize("out,needle", [("c.csv", "written as Parquet"), ("sub", "is a folder")])
def test_catalog_build_refuses_its_output_before_reading(tmp_path, capsys, out, needle):
    (tmp_path / "sub").mkdir()
    _refused(capsys, ["catalog", "build", str(tmp_path / "nothing-here"), "--out", str(tmp_path / out)], needle)


# -- 6 and 7. attack arguments --------------------------------------------------------------------

@pytest.mark.parametrize("attack,needle", [
    ("crop:0", "crop: the strength 0 is outside (0, 1]"),
    ("quantize:0", "quantize: the strength 0 is outside [1, 52]"),
    ("removal:1.5", "removal: the strength 1.5 is outside (0, 1]"),
    ("removal:0", "outside (0, 1]"),
    ("noise:nan", "not a finite number"),
    ("noise:-1", "outside [0, 1]"),
    ("quantize:8.5", "not a whole number"),
    ("shuffle:3", "shuffle takes no strength"),
    ("smooth", "needs a strength"),
    ("resample:1000000000", "resample: the strength 1e+09 is outside [1, 5e+07]"),
    ("outliers:1e9", "outliers: the strength 1e+09 is outside [0, 100]"),
    ("resample:1e6", "would make 1000000 points; at most 30000"),
    ("bogus:1", "unknown attack 'bogus'"),
])
def test_attack_arguments_are_checked_before_any_work(tmp_path, capsys, attack, needle):
    src = _ply(tmp_path / "m.ply", sphere_patch(300))
    _refused(capsys, ["attack", str(src), str(tmp_path / "a.ply"), "--attack", attack], "--attack", needle)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]


def test_chain_sizes_are_bounded():
    assert check_strength("quantize", 8.0) == 8 and isinstance(check_strength("quantize", 8.0), int)
    assert chain_size([("outliers", 1.0), ("removal", 0.5)], 1000) == 1000
    with pytest.raises(ValueError, match="outliers:50 would make"):
        chain_size([("outliers", 50.0), ("outliers", 50.0)], 1000)


def _cli_with_peak(*argv):
    """Run the CLI in a child: (exit status, stderr, the child's own peak resident kB since exec).

    VmHWM, not wait4's ru_maxrss: that also counts the test runner's resident size at the fork.
    """
    code = ("import sys\nfrom pipeline.cli import main\ntry:\n    code = main(sys.argv[1:])\nfinally:\n"
            "    peak = next(l for l in open('/proc/self/status') if l.startswith('VmHWM')).split()[1]\n"
            "    print(peak, file=sys.stdout, flush=True)\nsys.exit(code)\n")
    proc = subprocess.run([sys.executable, "-c", code, *map(str, argv)], capture_output=True, text=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}, timeout=300)
    return proc.returncode, proc.stderr, int(proc.stdout.split()[-1])


def test_a_huge_resample_is_refused_in_little_memory(tmp_path):
    src = _ply(tmp_path / "m.ply", sphere_patch(300))
    code, err, peak = _cli_with_peak("attack", src, tmp_path / "a.ply", "--attack", "resample:1000000000")
    assert code == 2 and "resample" in err and len(err.splitlines()) == 1, err
    assert peak < 500 * 1024          # kB
    assert not (tmp_path / "a.ply").exists()


@pytest.mark.parametrize("depth", [8, 12])
def test_a_yaml_alias_bomb_is_refused_quickly_in_little_memory(tmp_path, depth):
    # 700 bytes that expand to 9^depth values: the checks never render or copy the tree
    text = "x0: &x0 [lol,lol,lol,lol,lol,lol,lol,lol,lol]\n" + "".join(
        f"x{i}: &x{i} [" + ",".join([f"*x{i - 1}"] * 9) + "]\n" for i in range(1, depth + 1))
    (tmp_path / "bomb.yaml").write_text(text)
    code, err, peak = _cli_with_peak("validate", tmp_path / "bomb.yaml")
    assert code == 2 and "more than" in err and len(err.splitlines()) == 1, err
    assert peak < 500 * 1024


# -- 8. a copy the file's precision leaves unmarked ---------------------------------------------

def test_embed_refuses_a_copy_that_keeps_no_displacement(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("POINTMARK_SECRET", SECRET)
    src = _ply(tmp_path / "m.ply", sphere_patch(1500))
    _refused(capsys, ["embed", str(src), str(tmp_path / "o.ply"), "--key-id", "k", "--message", "1",
                      "--set", "n_bits=8", "--set", "cluster_size=600", "--set", "max_displacement=1e-300"],
             "o.ply", "does not differ measurably")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.ply"]


# -- end to end: the console script ----------------------------------------------------------------

@pytest.mark.parametrize("text,needle", [
    (f"key:\n  secret_file: {PASTED}\n", "key.secret_file: the value (not shown)"),
    ("dask:\n  n_workers: 100000\n", "dask.n_workers"),
    ("output:\n  dir: \"out\\0x\"\n", "output.dir"),
])
def test_the_console_script_refuses_in_one_line_and_writes_nothing(tmp_path, text, needle):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text + f"catalog:\n  source: {tmp_path}\nkey:\n  id: k\n" if "key:" not in text else text)
    res = subprocess.run([str(ROOT / ".venv" / "bin" / "pointmark"), "run", str(cfg), "--serial"], cwd=tmp_path,
                         capture_output=True, text=True, env={**os.environ, "POINTMARK_SECRET": SECRET})
    assert res.returncode == 2 and needle in res.stderr and len(res.stderr.splitlines()) == 1, res.stderr
    assert PASTED not in res.stderr and "Traceback" not in res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.yaml"]


def test_an_original_of_repeated_points_is_refused_in_little_memory(tmp_path):
    # 4 M identical points (24 MB): refused while the text is checked, before any full parse
    # (the whole parse and the exact count peaked at 750 MB)
    (tmp_path / "same.xyz").write_bytes(b"1 2 3\n" * 4_000_000)
    (tmp_path / "k.key").write_text(SECRET + "\n")
    code, err, peak = _cli_with_peak("embed", tmp_path / "same.xyz", tmp_path / "m.xyz", "--key-id", "k1",
                                     "--message", "c0", "--secret-file", tmp_path / "k.key", "--set", "n_bits=16")
    assert code == 2 and "all points are identical" in err and len(err.splitlines()) == 1, err
    assert peak < 500 * 1024 and not (tmp_path / "m.xyz").exists()


def test_repeated_points_are_refused_only_where_they_are_watermarked():
    # a suspect may repeat points (a quantised leak): only originals are refused for it
    import tempfile
    from pathlib import Path

    from pipeline.io.pointcloud import InputError, read_points

    pts = np.random.default_rng(3).uniform(-1, 1, (500, 3)).round(2)
    text = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in np.repeat(pts, 4, axis=0).tolist())
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "quantised.xyz"
        path.write_text(text)
        assert len(read_points(path).points) == 2000
        with pytest.raises(InputError, match="1500 of 2000 points repeat"):
            read_points(path, distinct=True)
