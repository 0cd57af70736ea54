import numpy as np
import pytest

from pipeline.io.ply import PlyError, read_ply, write_ply


def _ply(fmt, coord="float", n=5, extra=True):
    rng = np.random.default_rng(0)
    props = [("x", coord), ("y", coord), ("z", coord)] + ([("red", "uchar"), ("intensity", "float")] if extra else [])
    np_t = {"float": "f4", "double": "f8", "uchar": "u1"}
    e = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "<"}[fmt]
    dtype = np.dtype([(p, e + np_t[t]) for p, t in props])
    v = np.zeros(n, dtype=dtype)
    for p, t in props:
        v[p] = rng.uniform(0, 200, n).astype(np_t[t])
    head = ["ply", f"format {fmt} 1.0", "comment made by a test", f"element vertex {n}"]
    head += [f"property {t} {p}" for p, t in props]
    head += ["element face 1", "property list uchar int vertex_indices", "end_header"]
    header = ("\n".join(head) + "\n").encode()
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(v[p][i])) if np_t[t][0] == "f" else str(int(v[p][i]))
                                for p, t in props) + "\n" for i in range(n)).encode()
        tail = b"3 0 1 2\n"
    else:
        body = v.tobytes()
        tail = np.array([3], dtype="u1").tobytes() + np.array([0, 1, 2], dtype=e + "i4").tobytes()
    return header + body + tail, v


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
@pytest.mark.parametrize("coord", ["float", "double"])
def test_round_trip_keeps_properties_types_order_and_faces(fmt, coord):
    data, v = _ply(fmt, coord)
    ply = read_ply(data)
    assert np.allclose(ply.points[:, 0], v["x"].astype(np.float64), rtol=1e-6)
    moved = ply.points + 0.5
    again = read_ply(write_ply(ply, moved))
    assert again.vertices.dtype.names == v.dtype.names
    assert again.vertices.dtype["x"].itemsize == (4 if coord == "float" else 8)
    assert np.array_equal(again.vertices["red"], ply.vertices["red"])
    assert np.allclose(again.points, moved, rtol=1e-6)
    assert again.faces().tolist() == [[0, 1, 2]]
    assert "comment made by a test" in again.header


def test_truncated_binary_is_reported():
    data, _ = _ply("binary_little_endian", n=50)
    with pytest.raises(PlyError, match="truncated"):
        read_ply(data[: len(data) // 2])


@pytest.mark.parametrize("data,match", [
    (b"hello world", "not a PLY"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\nend_header\n", "lacks x, y or z"),
    (b"ply\nformat weird 1.0\nend_header\n", "unknown PLY format"),
])
def test_corrupt_headers_are_reported(data, match):
    with pytest.raises(PlyError, match=match):
        read_ply(data)
