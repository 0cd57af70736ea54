import numpy as np
import pytest

from pipeline.io.pointcloud import InputError, read_points, write_points


def _write_ascii_ply(path, pts):
    head = f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\nproperty double x\nproperty double y\nproperty double z\nend_header\n"
    path.write_text(head + "".join(f"{float(a)!r} {float(b)!r} {float(c)!r}\n" for a, b, c in pts))


def test_missing_file_is_named(tmp_path):
    with pytest.raises(InputError, match=r"nope\.ply: no such file"):
        read_points(tmp_path / "nope.ply")


def test_non_finite_coordinates_are_refused(tmp_path):
    pts = np.random.default_rng(0).normal(size=(20, 3))
    pts[4, 1] = np.nan
    pts[9, 2] = np.inf
    _write_ascii_ply(tmp_path / "bad.ply", pts)
    with pytest.raises(InputError, match=r"bad\.ply: 2 points have NaN or infinite"):
        read_points(tmp_path / "bad.ply")


def test_unknown_format_is_refused(tmp_path):
    (tmp_path / "a.stl").write_text("solid a\nendsolid a\n")
    with pytest.raises(InputError, match="unknown point-cloud format"):
        read_points(tmp_path / "a.stl")


def test_original_is_never_overwritten(tmp_path):
    pts = np.random.default_rng(0).normal(size=(20, 3))
    _write_ascii_ply(tmp_path / "a.ply", pts)
    cloud = read_points(tmp_path / "a.ply")
    before = (tmp_path / "a.ply").read_bytes()
    with pytest.raises(InputError, match="refusing to overwrite"):
        write_points(cloud, pts + 1, tmp_path / "a.ply")
    assert (tmp_path / "a.ply").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.ply"]  # no temporary left


@pytest.mark.parametrize("suffix", [".pcd", ".xyz", ".pts"])
def test_open3d_formats_round_trip_in_order(tmp_path, suffix):
    import open3d as o3d

    pts = np.random.default_rng(1).normal(size=(100, 3))
    src = tmp_path / f"in{suffix}"
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    assert o3d.io.write_point_cloud(str(src), pc, write_ascii=True)
    cloud = read_points(src)
    assert np.allclose(cloud.points, pts, atol=1e-6)
    write_points(cloud, cloud.points * 2, tmp_path / f"out{suffix}")
    assert np.allclose(read_points(tmp_path / f"out{suffix}").points, pts * 2, atol=1e-5)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_keeps_scale_offset_and_records(tmp_path, suffix):
    import laspy

    rng = np.random.default_rng(2)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([637000.0, 851000.0, 400.0])
    las = laspy.LasData(header)
    las.x = 637000 + rng.uniform(0, 100, 500)
    las.y = 851000 + rng.uniform(0, 100, 500)
    las.z = 400 + rng.uniform(0, 20, 500)
    las.intensity = rng.integers(0, 60000, 500).astype(np.uint16)
    las.write(str(tmp_path / f"in{suffix}"))
    cloud = read_points(tmp_path / f"in{suffix}")
    write_points(cloud, cloud.points + [0.01, 0.0, 0.0], tmp_path / f"out{suffix}")
    out = laspy.read(str(tmp_path / f"out{suffix}"))
    assert np.allclose(out.header.scales, header.scales) and np.allclose(out.header.offsets, header.offsets)
    assert np.array_equal(out.intensity, las.intensity)
    assert np.allclose(out.x, np.asarray(las.x) + 0.01, atol=0.0011)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_written_and_read_back_in_chunks_is_the_same_file(tmp_path, suffix, monkeypatch):
    import laspy

    from pipeline.io import pointcloud

    rng = np.random.default_rng(3)
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([5.0e5, 4.0e6, 0.0])
    las = laspy.LasData(header)
    las.x, las.y = 5.0e5 + rng.uniform(0, 50, 1000), 4.0e6 + rng.uniform(0, 50, 1000)
    las.z = rng.uniform(0, 5, 1000)
    las.gps_time = np.arange(1000) * 0.5
    las.write(str(tmp_path / f"in{suffix}"))
    cloud = read_points(tmp_path / f"in{suffix}")
    moved = cloud.points + rng.normal(0, 0.01, cloud.points.shape)
    write_points(cloud, moved, tmp_path / f"whole{suffix}")
    monkeypatch.setattr(pointcloud, "LAS_CHUNK", 97)          # 11 chunks, the last one short
    write_points(cloud, moved, tmp_path / f"chunks{suffix}")
    assert (tmp_path / f"chunks{suffix}").read_bytes() == (tmp_path / f"whole{suffix}").read_bytes()
    back = pointcloud.read_coordinates(tmp_path / f"chunks{suffix}")
    assert np.array_equal(back, read_points(tmp_path / f"whole{suffix}").points)
    assert np.abs(back - moved).max() <= 0.0005 + 1e-9            # the file's 1 mm scale, rounded
