"""PCD reader and writer: strict counts, every field kept, LZF that PCL's readers accept."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.io.pcd import PcdError, lzf_compress, lzf_decompress, read_pcd, write_pcd
from pipeline.io.pointcloud import InputError, read_points

HEAD = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 8 8 8 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
        "WIDTH {w}\nHEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {enc}\n")


def _head(n, enc, w=None, h=1):
    return HEAD.format(w=n if w is None else w, h=h, n=n, enc=enc).encode()


def _records(n):
    rec = np.zeros(n, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("intensity", "<f4")])
    rec["y"] = 4e6 + np.arange(n)
    rec["intensity"] = np.arange(n) / 7
    return rec


@pytest.mark.parametrize("data,match", [
    (_head(3, "binary") + _records(3).tobytes()[:-1], r"POINTS 3 x 28 bytes = 84 bytes of data, the body has 83"),
    (_head(3, "binary") + _records(4).tobytes(), r"the body has 112"),
    (_head(3, "ascii") + b"1 2 3 4\n5 6 7 8\n", r"POINTS 3 disagrees with the 2 data lines"),
    (_head(1, "ascii") + b"1 2 3 4\n5 6 7 8\n", r"POINTS 1 disagrees with the 2 data lines"),
    (_head(2, "ascii") + b"1 2 3 4\n5 6 7\n", r"line 13: 3 values, the fields need 4"),
    (_head(2, "ascii") + b"1 2 3 4\n5 six 7 8\n", r"line 13: coordinate y \(a 3-character non-numeric value\) is not a number"),
    (_head(4, "binary", w=2, h=3) + _records(4).tobytes(), r"WIDTH x HEIGHT = 2 x 3 disagrees with POINTS 4"),
    (_head(1, "binary_lzf"), r"unknown DATA encoding 'binary_lzf'"),
    (b"VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nWIDTH 1\nPOINTS 1\nDATA ascii\n1 2\n", r"exactly one field 'z'"),
    (b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F X\nWIDTH 1\nPOINTS 1\nDATA ascii\n1 2 3\n", r"unsupported TYPE 'X'"),
    (b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nPOINTS 1\n", r"no DATA line"),
])
def test_counts_and_headers_that_disagree_are_errors(data, match):
    with pytest.raises(PcdError, match=match):
        read_pcd(data)


def test_compressed_sizes_must_agree(tmp_path):
    rec = _records(10)
    raw = b"".join(rec[k].tobytes() for k in rec.dtype.names)
    packed = lzf_compress(raw)
    sizes = np.array([len(packed), len(raw) - 4], dtype="<u4").tobytes()
    with pytest.raises(PcdError, match="unpacks to 276 bytes, POINTS 10 x 28 bytes = 280"):
        read_pcd(_head(10, "binary_compressed") + sizes + packed)
    sizes = np.array([len(packed) + 1, len(raw)], dtype="<u4").tobytes()
    with pytest.raises(PcdError, match="declares"):
        read_pcd(_head(10, "binary_compressed") + sizes + packed)
    (tmp_path / "bad.pcd").write_bytes(_head(11, "binary") + rec.tobytes())
    with pytest.raises(InputError, match=r"bad\.pcd: POINTS 11"):
        read_points(tmp_path / "bad.pcd")


@pytest.mark.parametrize("data", [
    b"", b"x", b"ab" * 50, b"a" * 1000, bytes(range(256)) * 9,
    np.random.default_rng(0).bytes(5000),
    np.tile(np.float32(3.5), 3000).tobytes() + bytes(700) + np.random.default_rng(1).bytes(100),
    np.random.default_rng(2).integers(0, 2, 20000, dtype=np.uint8).tobytes(),
])
def test_lzf_round_trip(data):
    packed = lzf_compress(data)
    assert lzf_decompress(packed, len(data)) == data


def test_lzf_compresses_constant_columns():
    data = np.zeros(10000, dtype="<u4").tobytes() + np.full(10000, 7, dtype="<u2").tobytes()
    assert len(lzf_compress(data)) < len(data) // 50


def test_lzf_reference_vectors():
    # liblzf's encoding of 'aaaaaaaaaa': literal 'a', then a back reference of 9 at distance 1
    assert lzf_decompress(b"\x00a\xe0\x00\x00", 10) == b"a" * 10
    with pytest.raises(PcdError, match="back reference before the start"):
        lzf_decompress(b"\x20\x05", 3)
    with pytest.raises(PcdError, match="decodes to 1 bytes"):
        lzf_decompress(b"\x00a", 2)


def _open3d_cloud(n=500):
    import open3d as o3d

    rng = np.random.default_rng(3)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(rng.normal(size=(n, 3)) * 10))
    pc.colors = o3d.utility.Vector3dVector(np.tile([[0.2, 0.4, 0.6]], (n, 1)))
    pc.normals = o3d.utility.Vector3dVector(rng.normal(size=(n, 3)))
    return pc


@pytest.mark.parametrize("kwargs", [{"write_ascii": True}, {}, {"compressed": True}])
def test_reads_open3d_files_and_open3d_reads_ours(tmp_path, kwargs):
    import open3d as o3d

    pc = _open3d_cloud()
    assert o3d.io.write_point_cloud(str(tmp_path / "in.pcd"), pc, **kwargs)
    pcd = read_pcd((tmp_path / "in.pcd").read_bytes())
    assert [f[0] for f in pcd.fields] == ["x", "y", "z", "normal_x", "normal_y", "normal_z", "rgb"]
    assert np.allclose(pcd.points, np.asarray(pc.points), atol=1e-5)
    moved = pcd.points + 0.25
    (tmp_path / "out.pcd").write_bytes(write_pcd(pcd, moved))
    back = o3d.io.read_point_cloud(str(tmp_path / "out.pcd"))
    before = o3d.io.read_point_cloud(str(tmp_path / "in.pcd"))
    assert np.array_equal(np.asarray(back.points), moved.astype(np.float32).astype(np.float64))
    assert np.array_equal(np.asarray(back.colors), np.asarray(before.colors))
    assert np.array_equal(np.asarray(back.normals), np.asarray(before.normals))


def test_organised_cloud_and_padding_fields_are_kept():
    dtype = np.dtype([("x", "<f4"), ("pad1", "u1", (3,)), ("y", "<f4"), ("z", "<f4"), ("pad2", "u1")])
    rec = np.zeros(6, dtype=dtype)
    rec["pad1"], rec["pad2"] = 0xAB, 0xCD
    rec["x"] = np.arange(6)
    head = (b"FIELDS x _ y z _\nSIZE 4 1 4 4 1\nTYPE F U F F U\nCOUNT 1 3 1 1 1\nWIDTH 3\nHEIGHT 2\n"
            b"POINTS 6\nDATA binary\n")
    pcd = read_pcd(head + rec.tobytes())
    out = write_pcd(pcd, pcd.points + 1)
    assert out[:len(head)] == head
    again = np.frombuffer(out[len(head):], dtype=dtype)
    assert (again["pad1"] == 0xAB).all() and (again["pad2"] == 0xCD).all()
    assert np.array_equal(again["x"], np.arange(6, dtype="<f4") + 1)


def test_an_ascii_float32_field_beyond_its_range_is_one_clean_error(tmp_path):
    import warnings

    from pipeline.io.pointcloud import InputError, read_points

    path = tmp_path / "big.pcd"
    path.write_text("VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n"
                    "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n1e308 0 0\n1 1 1\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="beyond float32's range"):
            read_points(path)
