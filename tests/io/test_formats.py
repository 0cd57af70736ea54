"""Every format: read, move the points by a known small displacement, write, read back.

The output may differ from the input only in the moved coordinates: every
other field is bitwise identical (binary formats) or every other token and
line is identical (text formats), and the coordinates equal what was written
at the file's precision (double exact, float32 rounded, LAS to its scale).
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from pipeline.io.ply import read_ply
from pipeline.io.pointcloud import FORMATS, InputError, read_points, write_array, write_points

N = 240
OFFSET = np.array([5.0e5, 4.0e6, 120.0])  # survey-sized coordinates: float32 would lose them


def displaced(points, seed=0, sigma=1e-3):
    """(n, 3) points with every other point moved by about ``sigma``; the rest unchanged."""
    rng = np.random.default_rng(seed)
    delta = rng.normal(scale=sigma, size=points.shape)
    delta[1::2] = 0.0
    return points + delta


def round_trip(src, tmp_path, seed=0, sigma=1e-3):
    """Read ``src``, displace, write ``out.<suffix>``, read back; (before, moved, after)."""
    cloud = read_points(src)
    moved = displaced(cloud.points, seed, sigma)
    out = tmp_path / f"out{src.suffix}"
    write_points(cloud, moved, out)
    return cloud, moved, read_points(out)


def _fields_bitwise_equal(a, b, skip=("x", "y", "z")):
    assert a.dtype == b.dtype
    for name in a.dtype.names:
        if name not in skip:
            assert a[name].tobytes() == b[name].tobytes(), name


# ----------------------------------------------------------------------------- PLY

def _ply_file(path, fmt, coord):
    rng = np.random.default_rng(3)
    e = "<" if fmt != "binary_big_endian" else ">"
    ct = {"float": "f4", "double": "f8"}[coord]
    props = [("x", coord, ct), ("y", coord, ct), ("z", coord, ct), ("nx", "float", "f4"),
             ("red", "uchar", "u1"), ("intensity", "float", "f4"), ("label", "int", "i4")]
    v = np.zeros(N, dtype=[(p, e + t) for p, _, t in props])
    xyz = OFFSET * 1e-2 + rng.uniform(0, 10, (N, 3))  # float32-safe magnitudes
    for i, a in enumerate("xyz"):
        v[a] = xyz[:, i]
    v["nx"], v["intensity"] = rng.normal(size=N), rng.uniform(0, 1000, N)
    v["red"], v["label"] = rng.integers(0, 256, N), rng.integers(-5, 5, N)
    head = ["ply", f"format {fmt} 1.0", "comment made by a test", f"element vertex {N}"]
    head += [f"property {t} {p}" for p, t, _ in props]
    head += ["element face 2", "property list uchar int vertex_indices", "end_header"]
    if fmt == "ascii":
        body = "".join(" ".join(_ply_token(v[p][i], t) for p, _, t in props) + "\n" for i in range(N)).encode()
        tail = b"3 0 1 2\n3 2 1 3\n"
    else:
        body = v.tobytes()
        face = np.array([(3, (0, 1, 2)), (3, (2, 1, 3))], dtype=[("n", "u1"), ("v", e + "i4", (3,))])
        tail = face.tobytes()
    path.write_bytes(("\n".join(head) + "\n").encode() + body + tail)
    return path


def _ply_token(value, t):
    if t == "f4":
        return "%.6g" % value  # as most exporters write: not the writer's own %.9g
    if t == "f8":
        return repr(float(value))
    return str(int(value))


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("coord", ["float", "double"])
def test_ply_round_trip_changes_only_coordinates(tmp_path, fmt, coord):
    src = _ply_file(tmp_path / "in.ply", fmt, coord)
    cloud, moved, back = round_trip(src, tmp_path)
    _fields_bitwise_equal(cloud.native.vertices, back.native.vertices)
    assert back.native.header == cloud.native.header
    assert back.faces().tolist() == [[0, 1, 2], [2, 1, 3]]
    expect = moved.astype(np.float32).astype(np.float64) if coord == "float" else moved
    assert np.array_equal(back.points, expect)
    if fmt != "ascii":
        assert back.native.tail == cloud.native.tail


def test_real_ascii_ply_mesh_round_trip(shared_data, tmp_path):
    cloud, moved, back = round_trip(shared_data / "meshes" / "bun_zipper.ply", tmp_path, sigma=1e-5)
    assert cloud.native.vertices.dtype.names == ("x", "y", "z", "confidence", "intensity")
    _fields_bitwise_equal(cloud.native.vertices, back.native.vertices)
    assert np.array_equal(back.faces(), cloud.faces()) and len(cloud.faces()) == 69451
    assert np.array_equal(back.points, moved.astype(np.float32).astype(np.float64))


@pytest.mark.xfail(strict=True, reason="pipeline/io/ply.py rewrites every ASCII vertex value with %.9g or "
                   "%.17g: values stay bitwise equal at their type, but a float token '123.4' comes "
                   "back as '123.400002'")
def test_ascii_ply_keeps_non_coordinate_tokens(tmp_path):
    src = _ply_file(tmp_path / "in.ply", "ascii", "double")
    round_trip(src, tmp_path)
    is_vertex = lambda line: len(line.split()) == 7  # noqa: E731
    assert_only_coordinates_changed(src, tmp_path / "out.ply", (0, 1, 2), header_lines=13, point_line=is_vertex)


# ----------------------------------------------------------------------------- splat PLY

SPLAT_PROPS = (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
               + [f"f_rest_{i}" for i in range(45)] + ["opacity"] + [f"scale_{i}" for i in range(3)]
               + [f"rot_{i}" for i in range(4)])


def _splat_file(path, n=400):
    rng = np.random.default_rng(7)
    values = rng.normal(size=(n, len(SPLAT_PROPS))).astype("<f4")
    values[:, :3] = rng.uniform(-20, 20, (n, 3))
    bits = values.view("<u4")
    bits[0, 10] = 0x7FC01234          # a NaN with a payload
    bits[1, 11] = 0x80000000          # -0.0
    bits[2, 12] = 0x00000001          # the smallest subnormal
    bits[3, 13] = 0x7F800000          # +inf
    head = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    head += [f"property float {p}" for p in SPLAT_PROPS] + ["end_header"]
    path.write_bytes(("\n".join(head) + "\n").encode() + values.tobytes())
    return values


def test_gaussian_splat_ply_keeps_every_other_property_bit_for_bit(tmp_path):
    values = _splat_file(tmp_path / "scene.ply")
    assert len(SPLAT_PROPS) == 62
    cloud, moved, back = round_trip(tmp_path / "scene.ply", tmp_path)
    out = read_ply((tmp_path / "out.ply").read_bytes())
    after = np.stack([out.vertices[p] for p in SPLAT_PROPS], axis=1).view("<u4")
    assert np.array_equal(after[:, 3:], values.view("<u4")[:, 3:])
    assert np.array_equal(back.points, moved.astype(np.float32).astype(np.float64))
    size = len((tmp_path / "scene.ply").read_bytes())
    assert len((tmp_path / "out.ply").read_bytes()) == size


# ----------------------------------------------------------------------------- PCD

def _pcd_file(path, encoding, coord="F 8", offset=OFFSET):
    from pipeline.io.pcd import _to_columns, lzf_compress

    rng = np.random.default_rng(5)
    kind, size = coord.split()
    ct = {"4": "<f4", "8": "<f8"}[size]
    dtype = np.dtype([("x", ct), ("y", ct), ("z", ct), ("rgb", "<u4"), ("intensity", "<f4"),
                      ("label", "<u2"), ("desc", "<f4", (3,)), ("_", "u1")])
    rec = np.zeros(N, dtype=dtype)
    xyz = offset + rng.uniform(0, 50, (N, 3))
    for i, a in enumerate("xyz"):
        rec[a] = xyz[:, i]
    rec["rgb"], rec["intensity"] = rng.integers(0, 2**24, N), rng.uniform(0, 1, N)
    rec["label"], rec["desc"] = rng.integers(0, 9, N), rng.normal(size=(N, 3))
    head = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z rgb intensity label desc _\n"
            f"SIZE {size} {size} {size} 4 4 2 4 1\nTYPE {kind} {kind} {kind} U F U F U\nCOUNT 1 1 1 1 1 1 3 1\n"
            f"WIDTH {N}\nHEIGHT 1\nVIEWPOINT 1 2 3 1 0 0 0\nPOINTS {N}\nDATA {encoding}\n").encode()
    if encoding == "ascii":
        body = "".join(_pcd_line(r) for r in rec).encode()
    elif encoding == "binary":
        body = rec.tobytes()
    else:
        raw = _to_columns(rec)
        packed = lzf_compress(raw)
        body = np.array([len(packed), len(raw)], dtype="<u4").tobytes() + packed
    path.write_bytes(head + body)
    return rec


def _pcd_line(r):
    xyz = [repr(float(r[a])) for a in "xyz"]
    rest = [str(int(r["rgb"])), "%.6g" % r["intensity"], str(int(r["label"]))]
    return " ".join(xyz + rest + ["%.7g" % d for d in r["desc"]] + ["0"]) + "\n"


@pytest.mark.parametrize("encoding", ["ascii", "binary", "binary_compressed"])
@pytest.mark.parametrize("coord", ["F 8", "F 4"])
def test_pcd_round_trip_keeps_fields_types_and_header(tmp_path, encoding, coord):
    offset = OFFSET if coord == "F 8" else OFFSET * 1e-3
    _pcd_file(tmp_path / "in.pcd", encoding, coord, offset)
    cloud, moved, back = round_trip(tmp_path / "in.pcd", tmp_path)
    assert back.native.header == cloud.native.header
    assert back.native.fields == cloud.native.fields
    expect = moved if coord == "F 8" else moved.astype(np.float32).astype(np.float64)
    assert np.array_equal(back.points, expect)
    if encoding == "ascii":
        assert_only_coordinates_changed(tmp_path / "in.pcd", tmp_path / "out.pcd", (0, 1, 2), header_lines=11)
    else:
        _fields_bitwise_equal(cloud.native.records, back.native.records)


def test_pcd_double_at_4e6_comes_back_exact(tmp_path):
    """The issue's case: open3d wrote float32 and a y of 4e6 came back 0.096 off."""
    _pcd_file(tmp_path / "in.pcd", "binary")
    cloud = read_points(tmp_path / "in.pcd")
    assert cloud.points[:, 1].min() >= 4e6
    moved = cloud.points + [0.0, 1e-7, 0.0]
    write_points(cloud, moved, tmp_path / "out.pcd")
    assert np.array_equal(read_points(tmp_path / "out.pcd").points, moved)


# ----------------------------------------------------------------------------- text formats

_SEP = re.compile(rb"(\s+)")


def assert_only_coordinates_changed(src, out, cols, header_lines=0, point_line=None):
    """Line by line: non-point lines identical, point lines identical but for tokens ``cols``."""
    before = src.read_bytes().split(b"\n")
    after = out.read_bytes().split(b"\n")
    assert len(before) == len(after)
    point_line = point_line or (lambda line: bool(line.strip()) and not line.lstrip().startswith(b"#"))
    changed = 0
    for i, (a, b) in enumerate(zip(before, after)):
        if i < header_lines or not point_line(a):
            assert a == b, f"line {i + 1} changed"
            continue
        pa, pb = _SEP.split(a), _SEP.split(b)
        assert len(pa) == len(pb), f"line {i + 1}"
        first = 2 if pa[0] == b"" else 0
        coord_parts = {first + 2 * c for c in cols}
        assert [p for k, p in enumerate(pa) if k not in coord_parts] == \
               [p for k, p in enumerate(pb) if k not in coord_parts], f"line {i + 1}"
        changed += a != b
    assert changed > 0


def _xyz_file(path, rng):
    pts = OFFSET + rng.uniform(0, 50, (N, 3))
    lines = ["# scanned 2026-11-01, units m", ""]
    lines += [f"{x:.6f} {y:.6f}  {z:.6f} {rng.integers(0, 256)} 17 200\t0.125" for x, y, z in pts]
    path.write_text("\n".join(lines) + "\n")


def _pts_file(path, rng):
    lines = []
    for block in (N // 2, N - N // 2):
        pts = OFFSET + rng.uniform(0, 50, (block, 3))
        lines.append(str(block))
        lines += [f"{x:.4f} {y:.4f} {z:.4f} {-rng.integers(0, 2000)} {rng.integers(0, 256)} 12 250"
                  for x, y, z in pts]
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode())


@pytest.mark.parametrize("suffix,make", [(".xyz", _xyz_file), (".pts", _pts_file)])
def test_text_round_trip_rewrites_only_coordinate_tokens(tmp_path, suffix, make):
    make(tmp_path / f"in{suffix}", np.random.default_rng(11))
    cloud, moved, back = round_trip(tmp_path / f"in{suffix}", tmp_path)
    assert np.array_equal(back.points, moved)
    if suffix == ".pts":
        count_line = lambda line: len(line.split()) > 1  # noqa: E731 - the count lines are kept verbatim
        assert_only_coordinates_changed(tmp_path / "in.pts", tmp_path / "out.pts", (0, 1, 2), point_line=count_line)
    else:
        assert_only_coordinates_changed(tmp_path / "in.xyz", tmp_path / "out.xyz", (0, 1, 2))
    unmoved = (tmp_path / f"in{suffix}").read_bytes().split(b"\n")[cloud.native.rows[1]]
    assert (tmp_path / f"out{suffix}").read_bytes().split(b"\n")[cloud.native.rows[1]] == unmoved


def _obj_file(path, rng):
    pts = OFFSET + rng.uniform(0, 50, (N, 3))
    lines = ["# exported by a test", "mtllib scene.mtl", "o thing", "g body"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f} 0.5 0.25 1" for x, y, z in pts]
    lines += [f"vt {u:.4f} {v:.4f}" for u, v in rng.uniform(0, 1, (N, 2))]
    lines += ["vn 0 0 1", "usemtl red", "s off"]
    lines += [f"f {i}/{i}/1 {i + 1}/{i + 1}/1 {i + 2}/{i + 2}/1 {i + 3}/{i + 3}/1" for i in range(1, N - 3, 4)]
    lines += ["f -1//1 -2//1 -3//1", "l 1 2 3"]
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode())


def test_obj_round_trip_rewrites_only_vertex_coordinates(tmp_path):
    _obj_file(tmp_path / "in.obj", np.random.default_rng(13))
    cloud, moved, back = round_trip(tmp_path / "in.obj", tmp_path)
    assert np.array_equal(back.points, moved)
    assert np.array_equal(back.faces(), cloud.faces())
    assert len(cloud.faces()) == 2 * len(range(1, N - 3, 4)) + 1
    v_line = lambda line: line.startswith(b"v ")  # noqa: E731
    assert_only_coordinates_changed(tmp_path / "in.obj", tmp_path / "out.obj", (1, 2, 3), point_line=v_line)


# ----------------------------------------------------------------------------- LAS / LAZ

def _las_file(path):
    import laspy

    rng = np.random.default_rng(17)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([637000.0, 851000.0, 400.0])
    las = laspy.LasData(header)
    las.x = 637000 + rng.uniform(0, 100, N)
    las.y = 851000 + rng.uniform(0, 100, N)
    las.z = 400 + rng.uniform(0, 20, N)
    las.intensity = rng.integers(0, 60000, N).astype(np.uint16)
    las.classification = rng.integers(0, 20, N).astype(np.uint8)
    las.gps_time = rng.uniform(0, 1e6, N)
    las.red, las.green, las.blue = (rng.integers(0, 65535, N).astype(np.uint16) for _ in range(3))
    las.write(str(path))


def _assert_las_round_trip(cloud, moved, back):
    a, b = cloud.native, back.native
    assert b.header.point_format.id == a.header.point_format.id and b.header.version == a.header.version
    assert np.array_equal(b.header.scales, a.header.scales) and np.array_equal(b.header.offsets, a.header.offsets)
    _fields_bitwise_equal(a.points.array, b.points.array, skip=("X", "Y", "Z"))
    ints = np.round((moved - a.header.offsets) / a.header.scales).astype(np.int64)
    stored = np.column_stack([np.asarray(b.points.array[k], dtype=np.int64) for k in "XYZ"])
    assert np.array_equal(stored, ints)
    assert (ints != np.column_stack([np.asarray(a.points.array[k], dtype=np.int64) for k in "XYZ"])).any()


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_round_trip_changes_only_xyz_to_scale(tmp_path, suffix):
    _las_file(tmp_path / f"in{suffix}")
    _assert_las_round_trip(*round_trip(tmp_path / f"in{suffix}", tmp_path))


@pytest.mark.parametrize("name", ["lidar/autzen_trim.laz", "lidar/vegetation_1_3.las"])
def test_real_lidar_round_trip(shared_data, tmp_path, name):
    _assert_las_round_trip(*round_trip(shared_data / name, tmp_path, sigma=0.05))


# ----------------------------------------------------------------------------- new files

@pytest.mark.parametrize("fmt", ["pcd", "xyz", "pts", "obj"])
def test_write_array_keeps_float64(tmp_path, fmt):
    pts = OFFSET + np.random.default_rng(19).normal(size=(50, 3))
    path = write_array(tmp_path, "asset", pts, fmt)
    assert path.suffix == f".{fmt}" and FORMATS[path.suffix] == fmt
    assert np.array_equal(read_points(path).points, pts)


def test_point_count_must_match_on_write(tmp_path):
    write_array(tmp_path, "a", np.arange(15.0).reshape(5, 3), "xyz")
    cloud = read_points(tmp_path / "a.xyz")
    with pytest.raises(InputError, match=r"b\.xyz: 4 points given, the file holds 5"):
        write_points(cloud, cloud.points[:4], tmp_path / "b.xyz")
    assert not (tmp_path / "b.xyz").exists()
