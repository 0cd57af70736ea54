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


def _geo_keys(pairs):
    from laspy.vlrs.known import GeoKeyDirectoryVlr, GeoKeyEntryStruct, GeoKeysHeaderStructs

    vlr = GeoKeyDirectoryVlr()
    head = GeoKeysHeaderStructs()
    head.key_directory_version, head.key_revision, head.number_of_keys = 1, 1, len(pairs)
    vlr.geo_keys_header, vlr.geo_keys = head, []
    for key, value in pairs:
        entry = GeoKeyEntryStruct()
        entry.id, entry.count, entry.value_offset = key, 1, value
        vlr.geo_keys.append(entry)
    return vlr


WKT1_FEET = ('PROJCS["NAD83 / Texas", GEOGCS["NAD83", DATUM["NAD83", SPHEROID["GRS 1980",6378137,298.257222101]], '
             'UNIT["degree",0.0174532925199433]], PROJECTION["Lambert_Conformal_Conic_2SP"], '
             'UNIT["US survey foot",0.304800609601219]], VERT_CS["NAVD88", UNIT["metre",1]]')
WKT1_GEOG = 'GEOGCS["WGS 84", DATUM["WGS_1984", SPHEROID["WGS 84",6378137,298.257223563]], UNIT["degree",0.0174532925199433]]'
WKT2_FEET = ('PROJCRS["NAD83 / Texas", BASEGEOGCRS["NAD83", DATUM["NAD83", ELLIPSOID["GRS 1980",6378137,298.257222101,'
             'LENGTHUNIT["metre",1]]], ANGLEUNIT["degree",0.0174532925199433]], CONVERSION["x", METHOD["LCC"], '
             'PARAMETER["False easting",600000,LENGTHUNIT["metre",1]]], CS[Cartesian,2], '
             'AXIS["easting",east,ORDER[1],LENGTHUNIT["US survey foot",0.304800609601219]], '
             'AXIS["northing",north,ORDER[2],LENGTHUNIT["US survey foot",0.304800609601219]]]')
WKT2_GEOG = ('GEOGCRS["WGS 84", DATUM["World Geodetic System 1984", ELLIPSOID["WGS 84",6378137,298.257223563,'
             'LENGTHUNIT["metre",1]]], CS[ellipsoidal,2], AXIS["latitude",north,ANGLEUNIT["degree",0.0174532925199433]], '
             'AXIS["longitude",east,ANGLEUNIT["degree",0.0174532925199433]]]')


@pytest.mark.parametrize("crs, where, unit, geographic", [
    ([(1024, 1), (3072, 32633), (3076, 9001)], "vlr", 1.0, False),
    ([(1024, 1), (3072, 2277), (3076, 9003)], "vlr", 1200 / 3937, False),
    ([(1024, 2), (2048, 4326), (2054, 9102)], "vlr", None, True),
    ([(2048, 4326), (2054, 9102)], "vlr", None, True),                  # no model type: geographic keys alone
    (WKT1_FEET, "vlr", 0.304800609601219, False),
    (WKT1_GEOG, "vlr", None, True),
    (WKT2_FEET, "vlr", 0.304800609601219, False),
    (WKT2_FEET, "evlr", 0.304800609601219, False),                      # LAS 1.4: the WKT in an extended record
    (WKT2_GEOG, "evlr", None, True),
])
def test_las_units_come_from_geotiff_keys_or_wkt_and_geographic_has_none(tmp_path, crs, where, unit, geographic):
    import laspy
    from laspy.vlrs.known import WktCoordinateSystemVlr
    from laspy.vlrs.vlrlist import VLRList

    from pipeline.io.pointcloud import units_of

    header = laspy.LasHeader(point_format=6, version="1.4")
    vlr = WktCoordinateSystemVlr(crs) if isinstance(crs, str) else _geo_keys(crs)
    if where == "vlr":
        header.vlrs.append(vlr)
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.arange(5.0), np.arange(5.0), np.arange(5.0)
    if where == "evlr":
        las.evlrs = VLRList([vlr])
    las.write(str(tmp_path / "a.las"))
    for units in (units_of(tmp_path / "a.las"), read_points(tmp_path / "a.las").units()):
        assert units.geographic is geographic
        assert units.unit_m == (pytest.approx(unit) if unit else None)
