"""The command line: exit status 2 and one clear line for every kind of bad input."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from pipeline.cli import main
from tests.conftest import ROOT, sphere_patch


def _ply(path, pts):
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\n"
            "property double x\nproperty double y\nproperty double z\nend_header\n")
    path.write_bytes(head.encode() + np.asarray(pts, dtype="<f8").tobytes())
    return path


def _embed(src, out, *extra):
    return main(["embed", str(src), str(out), "--key-id", "k", "--message", "c0ffee", *extra])


@pytest.fixture()
def small_model(tmp_path):
    return _ply(tmp_path / "model.ply", sphere_patch(3000))


SMALL = ["--set", "n_bits=24", "--set", "cluster_size=1200", "--set", "n_clusters=2"]


def test_embed_and_detect_a_small_model(tmp_path, small_model, secret_env, capsys):
    assert _embed(small_model, tmp_path / "out.ply", *SMALL, "--json") == 0
    res = json.loads(capsys.readouterr().out)
    assert res["n_points"] == 3000 and res["n_bits"] == 24
    assert {"seed_index", "size", "radius"} <= set(res["clusters"][0])
    assert 0 < res["distortion"]["rmse_rel_diag"] < 0.01
    assert main(["detect", str(tmp_path / "out.ply"), "--original", str(small_model), "--key-id", "k",
                 "--json", *SMALL]) == 0
    det = json.loads(capsys.readouterr().out)
    assert det["detected"] and det["message"] == "c0ffee" and det["p_value"] < 1e-6
    assert len(det["bits"]) == len(det["bit_scores"]) == 24


def _bad(tmp_path, capsys, argv, *needles):
    assert main(argv) == 2
    err = capsys.readouterr().err
    for needle in needles:
        assert needle in err, err
    assert not (tmp_path / "out.ply").exists()
    assert not [p for p in tmp_path.iterdir() if ".tmp" in p.name]


def test_missing_file(tmp_path, secret_env, capsys):
    _bad(tmp_path, capsys, ["embed", str(tmp_path / "gone.ply"), str(tmp_path / "out.ply"), "--key-id", "k",
                            "--message", "1"], "gone.ply", "no such file")


def test_corrupt_and_truncated_ply(tmp_path, secret_env, capsys):
    (tmp_path / "junk.ply").write_bytes(b"\x00\x01garbage")
    _bad(tmp_path, capsys, ["embed", str(tmp_path / "junk.ply"), str(tmp_path / "out.ply"), "--key-id", "k",
                            "--message", "1"], "junk.ply", "not a PLY file")
    full = _ply(tmp_path / "full.ply", sphere_patch(3000)).read_bytes()
    (tmp_path / "cut.ply").write_bytes(full[: len(full) - 5000])
    _bad(tmp_path, capsys, ["embed", str(tmp_path / "cut.ply"), str(tmp_path / "out.ply"), "--key-id", "k",
                            "--message", "1"], "cut.ply", "truncated")


def test_nan_coordinates(tmp_path, secret_env, capsys):
    pts = sphere_patch(3000)
    pts[10] = np.nan
    _ply(tmp_path / "nan.ply", pts)
    _bad(tmp_path, capsys, ["embed", str(tmp_path / "nan.ply"), str(tmp_path / "out.ply"), "--key-id", "k",
                            "--message", "1"], "nan.ply", "NaN or infinite")


@pytest.mark.parametrize("name,pts,needle", [
    ("few.ply", sphere_patch(200), "fewer than the 320 spectral coefficients"),
    ("same.ply", np.ones((3000, 3)), "repeat another point"),
    ("line.ply", np.outer(np.linspace(0, 1, 3000), [1.0, 2.0, 3.0]), "collinear"),
])
def test_geometry_that_cannot_carry_a_payload(tmp_path, secret_env, capsys, name, pts, needle):
    _ply(tmp_path / name, pts)
    _bad(tmp_path, capsys, ["embed", str(tmp_path / name), str(tmp_path / "out.ply"), "--key-id", "k",
                            "--message", "1"], name, needle)


def test_payload_longer_than_capacity(tmp_path, small_model, secret_env, capsys):
    _bad(tmp_path, capsys, ["embed", str(small_model), str(tmp_path / "out.ply"), "--key-id", "k",
                            "--message", "123456789", "--set", "n_bits=32"], "--message", "capacity")
    _bad(tmp_path, capsys, ["embed", str(small_model), str(tmp_path / "out.ply"), "--key-id", "k",
                            "--message", "1", "--set", "chip_rate=200", "--set", "band_noise=null"],
         "model.ply", "capacity")


def test_missing_secret(tmp_path, small_model, monkeypatch, capsys):
    monkeypatch.delenv("POINTMARK_SECRET", raising=False)
    _bad(tmp_path, capsys, ["embed", str(small_model), str(tmp_path / "out.ply"), "--key-id", "k",
                            "--message", "1"], "no secret", "POINTMARK_SECRET")


def test_secret_file_is_used_and_never_printed(tmp_path, small_model, monkeypatch, capsys):
    monkeypatch.delenv("POINTMARK_SECRET", raising=False)
    (tmp_path / "key").write_text("s3cr3t-value-of-24-bytes\n")
    assert _embed(small_model, tmp_path / "o.ply", *SMALL, "--secret-file", str(tmp_path / "key"), "--json") == 0
    out = capsys.readouterr()
    assert "s3cr3t-value" not in out.out + out.err
    assert "key_fingerprint" not in json.loads(out.out)      # only ledgers hold (salted) fingerprints


def test_a_secret_given_where_a_path_belongs_is_not_echoed(tmp_path, small_model, monkeypatch, capsys):
    monkeypatch.delenv("POINTMARK_SECRET", raising=False)
    pasted = "Zq8-pasted-master-secret-value-41"
    assert main(["embed", str(small_model), str(tmp_path / "out.ply"), "--key-id", "k", "--message", "1",
                 "--secret-file", pasted]) == 2
    out = capsys.readouterr()
    assert "secret file" in out.err and "not shown" in out.err and len(out.err.strip().splitlines()) == 1
    assert pasted not in out.out + out.err and not (tmp_path / "out.ply").exists()


@pytest.mark.parametrize("secret", ["8bytes!!", "fifteen-bytes!!"])
def test_a_short_secret_is_refused(tmp_path, small_model, monkeypatch, capsys, secret):
    monkeypatch.setenv("POINTMARK_SECRET", secret)
    _bad(tmp_path, capsys, ["embed", str(small_model), str(tmp_path / "out.ply"), "--key-id", "k",
                            "--message", "1"], "POINTMARK_SECRET", "at least 16")


def test_console_script_is_installed():
    exe = ROOT / ".venv" / "bin" / "pointmark"
    if not exe.exists():
        pytest.skip("not running from the project's .venv")
    out = subprocess.run([str(exe), "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.startswith("pointmark ")


def test_the_command_line_pins_blas_and_openmp_to_one_thread():
    code = ("import pipeline.cli, threadpoolctl, json; "
            "print(json.dumps([i['num_threads'] for i in threadpoolctl.threadpool_info()]))")
    env = dict(os.environ, OMP_NUM_THREADS="4", OPENBLAS_NUM_THREADS="4", PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    counts = json.loads(out.stdout)
    assert counts and all(n == 1 for n in counts)


def test_embed_and_detect_with_the_convolutional_code(tmp_path, small_model, secret_env, capsys):
    coded = [*SMALL, "--set", "code=convolutional"]
    assert _embed(small_model, tmp_path / "out.ply", *coded, "--json") == 0
    res = json.loads(capsys.readouterr().out)
    assert res["params"]["code"] == "convolutional"
    assert 0 < res["distortion"]["mrms_rel_diag"] <= res["distortion"]["rmse_rel_diag"] * (1 + 1e-6)
    assert 0 <= res["distortion"]["msdm"] <= 1 and res["distortion"]["normal_deviation_deg"] > 0
    assert main(["detect", str(tmp_path / "out.ply"), "--original", str(small_model), "--key-id", "k",
                 "--json", *coded]) == 0
    det = json.loads(capsys.readouterr().out)
    assert det["detected"] and det["message"] == "c0ffee"


def test_evaluate_only_an_unknown_experiment_is_exit_2(tmp_path, secret_env, capsys):
    from tests.conftest import ROOT

    assert main(["evaluate", str(ROOT / "configs" / "evaluate-small.yaml"), "--only", "no-such"]) == 2
    assert "--only no-such: no such experiment" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["0", "-1", "two"])
def test_top_k_below_one_is_refused_by_the_parser(tmp_path, secret_env, capsys, value):
    with pytest.raises(SystemExit) as exc:
        main(["detect", str(tmp_path / "s.ply"), "--ledger", str(tmp_path), "--top-k", value])
    assert exc.value.code == 2
    assert f"argument --top-k: '{value}' is not a whole number of at least 1" in capsys.readouterr().err


def test_embedding_with_no_config_is_embedding_with_the_documented_default(tmp_path, secret_env, capsys):
    _ply(tmp_path / "m.ply", sphere_patch(21000, rng=4))
    written = {}
    for name, extra in (("none", []), ("default", ["--config", str(ROOT / "configs" / "default.yaml")])):
        out = tmp_path / f"{name}.ply"
        assert main(["embed", str(tmp_path / "m.ply"), str(out), "--key-id", "k", "--message", "c0ffee01",
                     "--json", *extra]) == 0
        written[name] = (out.read_bytes(), json.loads(capsys.readouterr().out)["params"])
    assert written["none"] == written["default"]
    params = written["none"][1]
    assert params["code"] == "tailbiting" and params["band_noise"] is None
    # 21,000 points: noise of 1 % spans over 2 spacings, so the band narrows at the same distance
    rate = params["chip_rate"]
    assert 3 <= rate < 10 and params["beta"] == pytest.approx(0.00115 * np.sqrt(10 / rate))


def _lidar_piece(source, path, n=15000):
    """The ``n`` points of a LAS/LAZ tile nearest its middle in x and y, written to ``path`` with its header."""
    import laspy

    tile = laspy.read(str(source))
    x, y = np.asarray(tile.x), np.asarray(tile.y)
    keep = np.sort(np.argsort((x - np.median(x)) ** 2 + (y - np.median(y)) ** 2, kind="stable")[:n])
    laspy.LasData(tile.header, points=tile.points[keep].copy()).write(str(path))
    return path


def test_a_lidar_tile_gets_the_survey_rule_by_default(shared_data, tmp_path, secret_env, capsys):
    import laspy

    # a 15,000-point piece of the Autzen tile (same header, units and scales): 4 clusters, not 28
    src = _lidar_piece(shared_data / "lidar" / "autzen_trim.laz", tmp_path / "autzen_piece.laz")
    out = tmp_path / "marked.laz"
    assert main(["embed", str(src), str(out), "--key-id", "k", "--message", "c0ffee01",
                 "--config", str(ROOT / "configs" / "default.yaml")]) == 0
    assert "survey rule (LAZ): amplitude per cluster, no point moved more than 1 cm" in capsys.readouterr().out
    a, b = laspy.read(str(src)), laspy.read(str(out))
    moved = np.linalg.norm(np.c_[a.x, a.y, a.z] - np.c_[b.x, b.y, b.z], axis=1)
    assert 0 < moved.max() <= 0.01 / 0.3048          # autzen is in feet: 1 cm is 0.0328 ft
    for name in a.point_format.dimension_names:
        if name not in ("X", "Y", "Z"):
            assert np.array_equal(np.asarray(a[name]), np.asarray(b[name])), name
    assert main(["detect", str(out), "--original", str(src), "--key-id", "k", "--expect", "c0ffee01",
                 "--json"]) == 0
    found = json.loads(capsys.readouterr().out)
    assert found["detected"] and found["bit_errors"] == 0


def test_detect_original_keeps_its_reference_in_a_store_and_checks_it(tmp_path, small_model, secret_env, capsys):
    assert _embed(small_model, tmp_path / "out.ply", *SMALL, "--json") == 0
    digests = json.loads(capsys.readouterr().out)["reference"]
    argv = ["detect", str(tmp_path / "out.ply"), "--original", str(small_model), "--key-id", "k", "--json",
            "--bases", str(tmp_path / "bases"), *SMALL]
    for _ in range(2):                       # built and kept, then built again and checked against the store
        assert main(argv) == 0
        assert json.loads(capsys.readouterr().out)["message"] == "c0ffee"
    (entry,) = (tmp_path / "bases").iterdir()
    cluster = next(entry.glob("cluster-0*.npz"))
    with np.load(cluster) as held:
        arrays = dict(held)
    arrays["basis"] = -arrays["basis"]
    np.savez(cluster, **arrays)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "reference mismatch: cluster 0 spectral basis" in err and len(err.strip().splitlines()) == 1
    assert len(digests["basis"]) == 3          # clusters of 1,200 cover the 3,000 points


def test_a_band_sized_for_noise_is_recorded_as_it_acted_and_read_back(tmp_path, secret_env, capsys):
    # 8,000 points: noise of 1 % is about 2 spacings, so clusters of 1,500 take a narrower band
    model = _ply(tmp_path / "dense.ply", sphere_patch(8000, rng=5))
    sets = [*SMALL, "--set", "cluster_size=1500", "--set", "band_noise=0.01"]
    assert _embed(model, tmp_path / "out.ply", *sets, "--json") == 0
    res = json.loads(capsys.readouterr().out)
    rate = res["params"]["chip_rate"]
    assert 3 <= rate < 10 and res["params"]["band_noise"] is None
    assert res["params"]["beta"] == pytest.approx(0.00115 * np.sqrt(10 / rate), rel=0.01)
    assert main(["detect", str(tmp_path / "out.ply"), "--original", str(model), "--key-id", "k", "--json",
                 *sets]) == 0
    det = json.loads(capsys.readouterr().out)
    assert det["detected"] and det["message"] == "c0ffee"
