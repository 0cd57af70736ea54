"""Issue 16: every bad file and bad setting of the hardening table gets a clear answer.

Each test is one row of the issue's table: exit status 2, one stderr line
naming the file (or option, or key) and the problem, and nothing written; or
the documented correct result.
"""

import json

import numpy as np
import pytest

from pipeline import config as config_mod
from pipeline.cli import main
from pipeline.io.pointcloud import read_points
from pipeline.kernels import keys, modulation, resampling
from pipeline.watermark import distortion, embed
from tests.conftest import sphere_patch

SMALL = ["--set", "n_bits=24", "--set", "cluster_size=1200", "--set", "n_clusters=2"]
SECRET = "test-secret-not-for-production"


def _ply(path, pts, coord="double", fmt="binary_little_endian", declared=None):
    t = {"double": "<f8", "float": "<f4"}[coord]
    head = (f"ply\nformat {fmt} 1.0\nelement vertex {len(pts) if declared is None else declared}\n"
            f"property {coord} x\nproperty {coord} y\nproperty {coord} z\nend_header\n").encode()
    if fmt == "ascii":
        body = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in np.asarray(pts, dtype=t).astype(float).tolist())
        path.write_bytes(head + body.encode())
    else:
        path.write_bytes(head + np.asarray(pts, dtype=t).tobytes())
    return path


def _embed_argv(src, out, message="c0ffee", *extra):
    return ["embed", str(src), str(out), "--key-id", "k", "--message", message, *SMALL, *extra]


def _refused(tmp_path, capsys, argv, *needles, out=None):
    """Exit 2, exactly one stderr line holding every needle, no output and no temporary file."""
    before = {p for p in tmp_path.rglob("*")}
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("pointmark: error: "), err
    for needle in needles:
        assert needle in lines[0], lines[0]
    after = {p for p in tmp_path.rglob("*")}
    assert after == before, sorted(map(str, after - before))
    if out is not None:
        assert not out.is_file()
    return lines[0]


# -- PLY header count against the body ----------------------------------------------------------

@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_ply_declaring_fewer_vertices_than_the_body_is_refused(tmp_path, secret_env, capsys, fmt):
    src = _ply(tmp_path / "short.ply", sphere_patch(3000), fmt=fmt, declared=2500)
    _refused(tmp_path, capsys, _embed_argv(src, tmp_path / "out.ply"),
             "short.ply", "declares 2500 vertices, the body holds 3000")
    _refused(tmp_path, capsys, ["detect", str(src), "--original", str(src), "--key-id", "k"],
             "short.ply", "declares 2500 vertices")


# -- every point present twice -------------------------------------------------------------------

def test_every_point_twice_is_refused_before_embedding(tmp_path, secret_env, capsys):
    src = _ply(tmp_path / "twice.ply", np.repeat(sphere_patch(3000), 2, axis=0))
    _refused(tmp_path, capsys, _embed_argv(src, tmp_path / "out.ply"),
             "twice.ply", "3000 of 6000 points repeat", "point 1 = point 0", "remove duplicate points")


def test_a_few_repeated_points_from_rounding_are_watermarked(tmp_path, secret_env, capsys):
    pts = sphere_patch(3000)
    pts[[10, 20, 30]] = pts[[11, 21, 31]]      # 3 of 3000, as a coarse grid produces
    src = _ply(tmp_path / "few.ply", pts)
    assert main(_embed_argv(src, tmp_path / "marked.ply")) == 0
    capsys.readouterr()
    assert main(["detect", str(tmp_path / "marked.ply"), "--original", str(src), "--key-id", "k",
                 "--json", *SMALL]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["detected"] and res["message"] == "c0ffee"


def test_spacing_ignores_repeated_points():
    pts = sphere_patch(500)
    single = resampling.nearest_spacing(pts)
    doubled = resampling.nearest_spacing(np.repeat(pts, 2, axis=0))
    assert (doubled > 0).all()
    assert np.allclose(doubled, np.repeat(single, 2))


def test_a_copy_with_every_point_twice_still_detects(tmp_path, secret_env, capsys):
    src = _ply(tmp_path / "model.ply", sphere_patch(3000))
    assert main(_embed_argv(src, tmp_path / "marked.ply")) == 0
    marked = read_points(tmp_path / "marked.ply").points
    order = np.random.default_rng(4).permutation(2 * len(marked))
    _ply(tmp_path / "doubled.ply", np.repeat(marked, 2, axis=0)[order])
    capsys.readouterr()
    assert main(["detect", str(tmp_path / "doubled.ply"), "--original", str(src), "--key-id", "k",
                 "--json", *SMALL]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["detected"] and res["message"] == "c0ffee"


# -- collinear points stored as float32 ------------------------------------------------------------

@pytest.mark.parametrize("offset", [0.0, 1000.0])
def test_collinear_float32_points_are_refused_like_float64(tmp_path, secret_env, capsys, offset):
    t = np.random.default_rng(0).uniform(0, 10, 3000)
    line = np.column_stack([t, 2 * t + 1, 3 - t]) + offset
    src = _ply(tmp_path / "line32.ply", line, coord="float")
    _refused(tmp_path, capsys, _embed_argv(src, tmp_path / "out.ply"), "line32.ply", "collinear")


def test_collinear_points_on_a_las_grid_are_refused(tmp_path, secret_env, capsys):
    import laspy

    t = np.random.default_rng(0).uniform(0, 10, 3000)
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.array([1000.0, 1000.0, 0.0])
    las = laspy.LasData(header)
    las.x, las.y, las.z = 1000 + t, 1000 + 2 * t, 3 - t
    las.write(str(tmp_path / "line.las"))
    _refused(tmp_path, capsys, _embed_argv(tmp_path / "line.las", tmp_path / "out.las"), "line.las", "collinear")


# -- distortion after rounding to the output's precision ------------------------------------------

def _unrounded_distortion(points):
    cfg = config_mod.load_config(None, SMALL[1::2])
    material = keys.derive_key_material(SECRET.encode(), "k")
    marked, _ = embed(points, material, modulation.hex_to_bits("c0ffee", 24), config_mod.watermark_params(cfg))
    return distortion(points, marked)


def _check_reported_distortion(tmp_path, capsys, src, out, *extra):
    assert main(_embed_argv(src, out, "c0ffee", "--json", *extra)) == 0
    reported = json.loads(capsys.readouterr().out)["distortion"]
    original = read_points(src).points
    stored = distortion(original, read_points(out).points)
    for key in ("rmse_rel_diag", "hausdorff_rel_diag", "surface_rmse_rel_diag"):
        assert reported[key] == pytest.approx(stored[key], rel=1e-9)
    before = _unrounded_distortion(original)
    assert abs(reported["rmse_rel_diag"] - before["rmse_rel_diag"]) > 0.01 * before["rmse_rel_diag"]
    return reported


def test_distortion_of_a_1e7_offset_ply_float_is_after_rounding(tmp_path, secret_env, capsys):
    # a 2 km object 10,000 km from the origin, in float32: 1 m steps
    pts = sphere_patch(3000) * 1000.0 + 1e7
    src = _ply(tmp_path / "geo.ply", pts, coord="float")
    _check_reported_distortion(tmp_path, capsys, src, tmp_path / "out.ply")


def test_distortion_of_a_las_with_1cm_scale_is_after_rounding(tmp_path, secret_env, capsys):
    import laspy

    pts = sphere_patch(3000) * 2.0 + [637000.0, 851000.0, 400.0]
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([0.01, 0.01, 0.01])
    header.offsets = np.array([637000.0, 851000.0, 400.0])
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts.T
    las.write(str(tmp_path / "scan.las"))
    model_rule = ["--set", "amplitude=model", "--set", "max_displacement=null"]    # not the survey rule
    _check_reported_distortion(tmp_path, capsys, tmp_path / "scan.las", tmp_path / "out.las", *model_rule)
    assert main(["detect", str(tmp_path / "out.las"), "--original", str(tmp_path / "scan.las"),
                 "--key-id", "k", "--json", *SMALL, *model_rule]) == 0
    assert json.loads(capsys.readouterr().out)["detected"]


# -- the payload -------------------------------------------------------------------------------------

@pytest.mark.parametrize("message,needle", [
    ("-1", "not hexadecimal"), (" de_ad ", "not hexadecimal"), ("de ad", "not hexadecimal"),
    ("+ff", "not hexadecimal"), ("1_0", "not hexadecimal"), ("0x", "empty"), ("", "empty"),
    ("c0ffee00", "more than the 6"), ("0xdeadbeef0", "more than the 6"),
])
def test_payloads_that_are_not_plain_hex_are_refused(tmp_path, secret_env, capsys, message, needle):
    src = _ply(tmp_path / "model.ply", sphere_patch(3000))
    _refused(tmp_path, capsys, ["embed", str(src), str(tmp_path / "out.ply"), "--key-id", "k",
                                f"--message={message}", *SMALL], "--message", needle)


def test_hex_parsing_is_strict_and_pads_short_numbers():
    assert modulation.bits_to_hex(modulation.hex_to_bits("0xC0FFEE", 24)) == "c0ffee"
    assert modulation.bits_to_hex(modulation.hex_to_bits("dead", 32)) == "0000dead"
    assert modulation.hex_to_bits("3ff", 10).tolist() == [1] * 10
    for bad in ["-1", " de_ad ", "dead\n", "٣", "0x-1", "0x 1", "ff ", "1.0", "0xx1"]:
        with pytest.raises(ValueError):
            modulation.hex_to_bits(bad, 32)
    with pytest.raises(ValueError, match="needs 11 bits"):
        modulation.hex_to_bits("7ff", 10)


# -- output paths, checked before any work ------------------------------------------------------------

def _output_cases(tmp_path):
    junk = tmp_path / "junk.ply"
    junk.write_bytes(b"this is not a point cloud")   # would fail if it were read first
    (tmp_path / "dir.ply").mkdir()
    (tmp_path / "plain").write_text("a file")
    return junk, [
        (tmp_path / "dir.ply", "is a folder"),
        (tmp_path / "plain" / "out.ply", "is a file, not a folder"),
        (junk, "refusing to overwrite the original"),
    ]


def test_bad_output_paths_are_refused_before_the_input_is_read(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("POINTMARK_SECRET", raising=False)   # nor the config, nor the secret
    junk, cases = _output_cases(tmp_path)
    cases.append((tmp_path / "out.pcd", "output format pcd differs from the input format ply"))
    for out, needle in cases:
        line = _refused(tmp_path, capsys, _embed_argv(junk, out), str(out), needle)
        assert "not a PLY" not in line and "secret" not in line


def test_bad_attack_outputs_are_refused_before_the_input_is_read(tmp_path, capsys):
    junk, cases = _output_cases(tmp_path)
    for out, needle in cases:
        _refused(tmp_path, capsys, ["attack", str(junk), str(out), "--attack", "noise:0.5%"], str(out), needle)


def test_attack_may_change_the_format(tmp_path, capsys):
    src = _ply(tmp_path / "model.ply", sphere_patch(500))
    assert main(["attack", str(src), str(tmp_path / "noisy.xyz"), "--attack", "shuffle"]) == 0
    assert len(read_points(tmp_path / "noisy.xyz").points) == 500


def test_output_through_a_link_to_the_input_is_refused(tmp_path, secret_env, capsys):
    src = _ply(tmp_path / "model.ply", sphere_patch(3000))
    (tmp_path / "link.ply").symlink_to(src)
    _refused(tmp_path, capsys, _embed_argv(src, tmp_path / "link.ply"), "link.ply", "overwrite the original")
    assert read_points(src).points.shape == (3000, 3)


# -- configuration -------------------------------------------------------------------------------------

@pytest.mark.parametrize("text,needles", [
    ("watermark:\n  beta: .nan\n", ["watermark.beta", "not a finite number"]),
    ("watermark:\n  valence: .inf\n", ["watermark.valence", "not a finite number"]),
    ("watermark:\n  seeds: [[0, 0, .nan]]\n", ["watermark.seeds.0.2", "not a finite number"]),
    ("detection:\n  ridge: -.inf\n", ["detection.ridge", "not a finite number"]),
    ("detection:\n  p_threshold: 1\n", ["detection.p_threshold", "greater than or equal to the maximum of 1"]),
    ("detection:\n  p_threshold: 0\n", ["detection.p_threshold"]),
    ("watermark:\n  beta: 0.002\n    n_bits: 8\n", ["not valid YAML", "line 3"]),
    ("watermark: [unclosed\n", ["not valid YAML", "line 2"]),
    ("watermark:\n\tbeta: 1\n", ["not valid YAML", "line 2"]),
    ("a: &a [*a]\n", ["alias refers to itself"]),
    ("watermark:\n  1: 2\n", ["watermark", "is not a string"]),
])
def test_bad_configs_give_one_line(tmp_path, capsys, text, needles):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text)
    _refused(tmp_path, capsys, ["validate", str(cfg)], "bad.yaml", *needles)


def test_beta_nan_is_refused_before_anything_is_written(tmp_path, secret_env, capsys):
    src = _ply(tmp_path / "model.ply", sphere_patch(3000))
    cfg = tmp_path / "nan.yaml"
    cfg.write_text("watermark:\n  beta: .nan\n")
    _refused(tmp_path, capsys, _embed_argv(src, tmp_path / "out.ply", "c0ffee", "--config", str(cfg)),
             "watermark.beta", "not a finite number", out=tmp_path / "out.ply")
    _refused(tmp_path, capsys, _embed_argv(src, tmp_path / "out.ply", "c0ffee", "--set", "beta=.nan"),
             "watermark.beta", "not a finite number")


def test_alias_bombs_and_binary_configs_are_refused(tmp_path, capsys):
    lines = ["a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for i in range(1, 9):
        lines.append(f"{'abcdefghij'[i]}: &{'abcdefghij'[i]} [" + ", ".join([f"*{'abcdefghij'[i - 1]}"] * 10) + "]")
    (tmp_path / "bomb.yaml").write_text("\n".join(lines) + "\n")
    _refused(tmp_path, capsys, ["validate", str(tmp_path / "bomb.yaml")], "bomb.yaml", "more than")
    (tmp_path / "bin.yaml").write_bytes(b"\xff\xfe\x00garbage")
    _refused(tmp_path, capsys, ["validate", str(tmp_path / "bin.yaml")], "bin.yaml", "UTF-8")


def test_set_into_a_section_that_is_not_a_mapping(tmp_path, capsys):
    cfg = tmp_path / "flat.yaml"
    cfg.write_text("watermark: 3\n")
    _refused(tmp_path, capsys, ["embed", "in.ply", str(tmp_path / "o.ply"), "--key-id", "k", "--message", "1",
                                "--config", str(cfg), "--set", "beta=0.1"], "--set beta", "not a mapping")
    _refused(tmp_path, capsys, ["embed", "in.ply", str(tmp_path / "o.ply"), "--key-id", "k", "--message", "1",
                                "--set", "beta=[0"], "--set beta", "not valid YAML")
