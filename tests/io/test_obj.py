"""OBJ: vertices are the points, faces decoded (fan, negative, v/vt/vn), the rest untouched."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.io.obj import ObjError, read_obj, write_obj
from pipeline.io.pointcloud import InputError, read_points, write_points

MESH = b"""# a quad, a pentagon and a triangle
mtllib m.mtl
v 0 0 0
v 1 0 0 1.0
v 1 1 0 0.1 0.2 0.3
v 0 1 0
vt 0 0
vn 0 0 1
g top
usemtl red
f 1/1/1 2/1/1 3/1/1 4/1/1
v 0.5 2 0
f -5 -4 -3 -2 -1
f 1//1 -4//1 5//1
l 1 2
"""


def test_faces_are_fan_triangulated_with_relative_indices():
    obj = read_obj(MESH)
    assert obj.points.shape == (5, 3)
    assert obj.faces().tolist() == [[0, 1, 2], [0, 2, 3],
                                    [0, 1, 2], [0, 2, 3], [0, 3, 4],
                                    [0, 1, 4]]


def test_write_rewrites_only_moved_vertex_coordinates():
    obj = read_obj(MESH)
    moved = obj.points.copy()
    moved[2] += [0.25, 0.0, -1e-12]
    out = write_obj(obj, moved)
    assert out == MESH.replace(b"v 1 1 0 0.1 0.2 0.3", b"v 1.25 1 -1e-12 0.1 0.2 0.3")
    assert write_obj(obj, obj.points) == MESH


@pytest.mark.parametrize("data,match", [
    (b"v 0 0 0\nv 1 0 0\nf 1 2 3\n", r"line 3: face vertex index 3 is out of range"),
    (b"v 0 0 0\nv 1 0 0\nv 1 1 0\nf -4 1 2\n", r"line 4: face vertex index -4 is out of range"),
    (b"v 0 0 0\nf 0 1 1\n", r"line 2: face vertex index 0"),
    (b"v 0 0\n", r"line 1: a vertex has 2 values"),
    (b"v 0 0 0 1 1\n", r"line 1: a vertex has 5 values"),
    (b"v 0 0 0\nv 1 0 0\nf 1 2\n", r"line 3: a face needs at least 3 vertices"),
    (b"v 0 0 zero\n", r"line 1: coordinate z \(a 4-character non-numeric value\) is not a number"),
    (b"v 0 0 0\nf a b c\n", r"line 2: a face vertex \(a 1-character non-numeric value\) is not an index"),
])
def test_bad_obj_lines_are_named(data, match):
    with pytest.raises(ObjError, match=match):
        read_obj(data)


def test_point_cloud_faces_and_file_round_trip(tmp_path):
    (tmp_path / "m.obj").write_bytes(MESH)
    cloud = read_points(tmp_path / "m.obj")
    assert cloud.format == "obj" and cloud.faces().shape == (6, 3)
    moved = cloud.points + np.random.default_rng(0).normal(scale=1e-4, size=cloud.points.shape)
    write_points(cloud, moved, tmp_path / "n.obj")
    back = read_points(tmp_path / "n.obj")
    assert np.array_equal(back.points, moved) and np.array_equal(back.faces(), cloud.faces())
    keep = [line for line in MESH.split(b"\n") if not line.startswith(b"v ")]
    assert [line for line in (tmp_path / "n.obj").read_bytes().split(b"\n") if not line.startswith(b"v ")] == keep


def test_obj_without_vertices_is_refused(tmp_path):
    (tmp_path / "empty.obj").write_text("# nothing\nmtllib a.mtl\n")
    with pytest.raises(InputError, match=r"empty\.obj: the file holds no points"):
        read_points(tmp_path / "empty.obj")
