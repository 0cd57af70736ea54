"""Readers that never guess (issue 16): a declared count that disagrees with the data is an error."""

import numpy as np
import pytest

from pipeline.io.ply import PlyError, read_ply, write_ply
from pipeline.io.pointcloud import InputError, check_distinct, check_output, read_points


def _vertices(n, seed=0):
    return np.random.default_rng(seed).uniform(-1, 1, (n, 3))


def _ply_bytes(pts, fmt="binary_little_endian", declared=None, faces=None, coord="double"):
    """A PLY whose header declares ``declared`` vertices (default: as many as given)."""
    declared = len(pts) if declared is None else declared
    head = ["ply", f"format {fmt} 1.0", f"element vertex {declared}",
            f"property {coord} x", f"property {coord} y", f"property {coord} z"]
    if faces is not None:
        head += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    head += ["end_header"]
    data = ("\n".join(head) + "\n").encode()
    t = "f8" if coord == "double" else "f4"
    if fmt == "ascii":
        data += "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in pts.astype(t).astype(float).tolist()).encode()
        if faces is not None:
            data += "".join(f"3 {a} {b} {c}\n" for a, b, c in faces).encode()
    else:
        e = "<" if fmt == "binary_little_endian" else ">"
        data += pts.astype(e + t).tobytes()
        if faces is not None:
            rec = np.zeros(len(faces), dtype=[("n", "u1"), ("v", e + "i4", (3,))])
            rec["n"], rec["v"] = 3, faces
            data += rec.tobytes()
    return data


FMTS = ["ascii", "binary_little_endian", "binary_big_endian"]


@pytest.mark.parametrize("fmt", FMTS)
def test_header_declaring_fewer_vertices_than_the_body_holds_is_an_error(fmt):
    pts = _vertices(40)
    with pytest.raises(PlyError, match="declares 30 vertices, the body holds 40"):
        read_ply(_ply_bytes(pts, fmt, declared=30))


@pytest.mark.parametrize("fmt", FMTS)
def test_header_declaring_more_vertices_than_the_body_holds_is_an_error(fmt):
    with pytest.raises(PlyError, match="truncated"):
        read_ply(_ply_bytes(_vertices(40), fmt, declared=41))


@pytest.mark.parametrize("fmt", FMTS)
def test_fewer_vertices_declared_in_a_mesh_is_an_error(fmt):
    pts, faces = _vertices(40), [(0, 1, 2), (2, 3, 4)]
    assert len(read_ply(_ply_bytes(pts, fmt, faces=faces)).faces()) == 2
    with pytest.raises(PlyError):
        read_ply(_ply_bytes(pts, fmt, declared=39, faces=faces))


@pytest.mark.parametrize("fmt", FMTS)
def test_bytes_or_lines_after_the_declared_records_are_an_error(fmt):
    data = _ply_bytes(_vertices(10), fmt, faces=[(0, 1, 2)])
    with pytest.raises(PlyError, match="follow|holds"):
        read_ply(data + (b"3 4 5 6\n" if fmt == "ascii" else b"\x03" + bytes(12)))
    with pytest.raises(PlyError):
        read_ply(data[:-3])


def test_binary_mesh_with_mixed_polygon_sizes_is_walked_exactly():
    pts = _vertices(10)
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty double x\nproperty double y\n"
            "property double z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n").encode()
    body = pts.astype("<f8").tobytes() + bytes([3]) + np.arange(3, dtype="<i4").tobytes() \
        + bytes([4]) + np.arange(4, dtype="<i4").tobytes()
    assert len(read_ply(head + body).vertices) == 10
    with pytest.raises(PlyError, match="bytes follow"):
        read_ply(head + body + b"\0")
    with pytest.raises(PlyError, match="truncated"):
        read_ply(head + body[:-1])


def test_a_huge_declared_count_fails_without_allocating():
    data = _ply_bytes(_vertices(5)).replace(b"element vertex 5", b"element vertex 99999999999999999")
    with pytest.raises(PlyError, match="truncated"):
        read_ply(data)


@pytest.mark.parametrize("line,value,match", [
    ("property uchar red", "300", "not an integer in"),
    ("property uchar red", "-1", "not an integer in"),
    ("property uchar red", "1.5", "not an integer in"),
    ("property float intensity", "1e300", "range of float32"),
])
def test_ascii_values_that_do_not_fit_their_type_are_an_error(line, value, match):
    name = line.split()[-1]
    data = (f"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
            f"{line}\nend_header\n0 0 0 1\n1 1 1 {value}\n").encode()
    with pytest.raises(PlyError, match=match) as exc:
        read_ply(data)
    assert name in str(exc.value)


def test_duplicate_property_or_element_names_are_an_error():
    base = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
    with pytest.raises(PlyError, match="declared twice"):
        read_ply((base + "property float x\nend_header\n0 0 0 0\n").encode())
    with pytest.raises(PlyError, match="declared twice"):
        read_ply((base + "element vertex 1\nproperty float x\nend_header\n0 0 0\n0\n").encode())


def test_strict_reader_still_round_trips_a_valid_mesh():
    pts, faces = _vertices(20), [(0, 1, 2), (3, 4, 5)]
    for fmt in FMTS:
        ply = read_ply(_ply_bytes(pts, fmt, faces=faces))
        again = read_ply(write_ply(ply, ply.points * 2))
        assert np.allclose(again.points, pts * 2) and again.faces().tolist() == [list(f) for f in faces]


def test_read_points_names_the_file_for_a_count_mismatch(tmp_path):
    path = tmp_path / "short.ply"
    path.write_bytes(_ply_bytes(_vertices(40), declared=35))
    with pytest.raises(InputError, match=r"short\.ply: the header declares 35 vertices, the body holds 40"):
        read_points(path)


def _las(path, n=300, scale=0.001):
    import laspy

    rng = np.random.default_rng(3)
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([scale] * 3)
    header.offsets = np.array([500000.0, 4000000.0, 100.0])
    las = laspy.LasData(header)
    las.x = 500000 + rng.uniform(0, 50, n)
    las.y = 4000000 + rng.uniform(0, 50, n)
    las.z = 100 + rng.uniform(0, 5, n)
    las.write(str(path))
    return path


def test_las_count_against_the_file_length(tmp_path):
    good = _las(tmp_path / "good.las")
    data = good.read_bytes()
    assert len(read_points(good).points) == 300
    record = 28  # point format 1
    cases = {
        "more.las": (data + bytes(2 * record), "declares 300 points, the file holds 302"),
        "tail.las": (data + b"\0\0\0", "3 bytes more"),
        "cut.las": (data[:-record], "truncated: the header declares 300 points"),
    }
    for name, (body, match) in cases.items():
        (tmp_path / name).write_bytes(body)
        with pytest.raises(InputError, match=match) as exc:
            read_points(tmp_path / name)
        assert name in str(exc.value) and "\n" not in str(exc.value)


def test_laz_with_an_absurd_point_count_is_refused_before_reading(tmp_path):
    good = _las(tmp_path / "good.laz")
    data = bytearray(good.read_bytes())
    data[107:111] = (2**32 - 1).to_bytes(4, "little")   # legacy point count of a LAS 1.2 header
    (tmp_path / "huge.laz").write_bytes(bytes(data))
    with pytest.raises(InputError, match="more than a .*LAZ file can hold"):
        read_points(tmp_path / "huge.laz")


def test_check_distinct_names_a_repeated_point(tmp_path):
    pts = _vertices(200)
    check_distinct("a.ply", pts)
    check_distinct("a.ply", np.vstack([pts, pts[:2]]))          # 2 of 202: rounding, accepted
    with pytest.raises(InputError, match=r"a\.ply: 200 of 400 points repeat .*point 1 = point 0"):
        check_distinct("a.ply", np.repeat(pts, 2, axis=0))
    with pytest.raises(InputError, match=r"3 of 203 points repeat .*point 200 = point 7"):
        check_distinct("a.ply", np.vstack([pts, pts[[7, 7, 9]]]))


def test_check_output_refuses_before_any_work(tmp_path):
    src = tmp_path / "in.ply"
    src.write_bytes(_ply_bytes(_vertices(5)))
    (tmp_path / "folder.ply").mkdir()
    (tmp_path / "afile").write_text("x")
    cases = {
        tmp_path / "folder.ply": "is a folder",
        tmp_path / "afile" / "out.ply": "is a file, not a folder",
        src: "refusing to overwrite the original",
        tmp_path / "." / "in.ply": "refusing to overwrite the original",
        tmp_path / "out.las": "output format las differs from the input format ply",
        tmp_path / "out.txt": "unknown point-cloud format",
    }
    for out, match in cases.items():
        with pytest.raises(InputError, match=match):
            check_output(src, out)
    link = tmp_path / "link.ply"
    link.symlink_to(src)
    with pytest.raises(InputError, match="overwrite the original"):
        check_output(src, link)
    check_output(src, tmp_path / "new" / "deeper" / "out.ply")   # folders are created on write
    check_output(src, tmp_path / "out.las", same_format=False)
