"""glTF and GLB: positions moved in place, every other byte kept, refusals named, the validator content.

Each file is read, its points moved by a known small displacement, written
and read back.  Outside the POSITION accessors' bytes the buffers are
identical byte for byte, and the JSON holds the same values but for the
POSITION ``min``/``max``.  Generated files cover a mesh on two nodes, an
external ``.bin``, a skin, a morph target, interleaved vertices, one buffer
view shared by two attributes and KHR_mesh_quantization.
"""

from __future__ import annotations

import base64
import json
import struct

import numpy as np
import pytest

from pipeline.io import gltf_tools
from pipeline.io.gltf import glb_from_mesh, read_gltf
from pipeline.io.pointcloud import InputError, read_points, write_points

REAL = ["DamagedHelmet.glb", "ShapeCollection.glb", "chr_knight.glb", "TwoCubes.glb", "DenseSphere.glb",
        "BoxMeshopt.glb"]
REFUSED = {"DenseSphere.glb": "KHR_draco_mesh_compression", "BoxMeshopt.glb": "EXT_meshopt_compression"}


def _grid(n=12):
    """(n*n, 3) float32 vertices of a bumpy sheet and its (f, 3) uint16 triangles."""
    u, v = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    points = np.column_stack([u.ravel(), v.ravel(), 0.2 * np.sin(3 * u.ravel()) * np.cos(2 * v.ravel())])
    k = np.arange(n * n).reshape(n, n)[:-1, :-1].ravel()
    faces = np.concatenate([np.column_stack([k, k + 1, k + n]), np.column_stack([k + 1, k + n + 1, k + n])])
    return points.astype("<f4"), faces.astype("<u2")


def _doc(views, accessors, mesh, nodes, **extra):
    return {"asset": {"version": "2.0", "generator": "pointmark tests"}, "scene": 0,
            "scenes": [{"nodes": [i for i, n in enumerate(nodes) if not n.pop("child", False)]}],
            "nodes": nodes, "meshes": [mesh], "bufferViews": views, "accessors": accessors, **extra}


def _vec3(view, count, values, offset=0, **kw):
    return {"bufferView": view, "byteOffset": offset, "componentType": 5126, "count": count, "type": "VEC3",
            "min": values.min(axis=0).tolist(), "max": values.max(axis=0).tolist(), **kw}


def generated(kind):
    """(doc, blob) of a small generated glTF of the given kind."""
    points, faces = _grid()
    n = len(points)
    normals = np.tile(np.array([0, 0, 1], dtype="<f4"), (n, 1))
    index = faces.tobytes()
    views = [{"buffer": 0, "byteOffset": 0, "byteLength": len(index), "target": 34963}]
    accessors = [{"bufferView": 0, "componentType": 5123, "count": faces.size, "type": "SCALAR"}]
    blob = bytearray(index)
    attributes = {}
    nodes = [{"mesh": 0, "translation": [1.0, 2.0, 3.0], "rotation": [0.0, 0.3826834, 0.0, 0.9238795]}]
    extra = {}

    def add(data, stride=None):
        blob.extend(b"\0" * (-len(blob) % 4))
        views.append({"buffer": 0, "byteOffset": len(blob), "byteLength": len(data), "target": 34962,
                      **({"byteStride": stride} if stride else {})})
        blob.extend(data)
        return len(views) - 1

    if kind == "interleaved":
        view = add(np.hstack([points, normals]).tobytes(), stride=24)
        accessors += [_vec3(view, n, points), _vec3(view, n, normals, offset=12)]
    elif kind == "shared-view":                # POSITION and NORMAL one after the other in one view
        view = add(points.tobytes() + normals.tobytes(), stride=12)      # a shared vertex view needs a stride
        accessors += [_vec3(view, n, points), _vec3(view, n, normals, offset=points.nbytes)]
    elif kind == "quantized":                  # KHR_mesh_quantization: normalized int16, scale in the node
        q = np.rint(points / 1.5 * 32767).astype("<i2")
        accessors += [{**_vec3(add(np.hstack([q, np.zeros((n, 1), "<i2")]).tobytes(), stride=8), n, q),
                       "componentType": 5122, "normalized": True}, _vec3(add(normals.tobytes()), n, normals)]
        nodes[0]["scale"] = [1.5, 1.5, 1.5]
        extra = {"extensionsUsed": ["KHR_mesh_quantization"], "extensionsRequired": ["KHR_mesh_quantization"]}
    else:
        accessors += [_vec3(add(points.tobytes()), n, points), _vec3(add(normals.tobytes()), n, normals)]
    attributes = {"POSITION": 1, "NORMAL": 2}
    mesh = {"primitives": [{"attributes": attributes, "indices": 0, "mode": 4}]}
    if kind == "instanced":
        nodes.append({"mesh": 0, "translation": [-4.0, 0.0, 0.0], "scale": [2.0, 2.0, 2.0]})
    elif kind == "skinned":
        joints = np.zeros((n, 4), dtype="u1")
        weights = np.tile(np.array([1, 0, 0, 0], dtype="<f4"), (n, 1))
        inverse = np.eye(4, dtype="<f4").reshape(1, 16)
        accessors += [{"bufferView": add(joints.tobytes()), "componentType": 5121, "count": n, "type": "VEC4"},
                      {"bufferView": add(weights.tobytes()), "componentType": 5126, "count": n, "type": "VEC4"},
                      {"bufferView": add(inverse.tobytes()), "componentType": 5126, "count": 1, "type": "MAT4"}]
        views[-1].pop("target")
        attributes.update(JOINTS_0=3, WEIGHTS_0=4)
        nodes[0]["skin"] = 0                   # its translation is ignored (the validator warns, as on input)
        nodes.append({"translation": [0.0, 1.0, 0.0]})
        extra["skins"] = [{"joints": [1], "inverseBindMatrices": 5}]
    elif kind == "morph":
        delta = np.tile(np.array([0, 0, 0.25], dtype="<f4"), (n, 1))
        accessors.append(_vec3(add(delta.tobytes()), n, delta))
        mesh["primitives"][0]["targets"] = [{"POSITION": 3}]
        mesh["weights"] = [0.5]
    blob.extend(b"\0" * (-len(blob) % 4))
    return _doc(views, accessors, mesh, nodes, buffers=[{"byteLength": len(blob)}], **extra), bytes(blob)


def _write_glb(path, doc, blob):
    """A GLB written with pygltflib (not with our own writer)."""
    import pygltflib

    gltf = pygltflib.GLTF2.from_dict(doc)
    gltf.set_binary_blob(blob)
    gltf.save_binary(str(path))
    return path


def make(tmp_path, kind):
    doc, blob = generated("plain" if kind in ("external", "embedded") else kind)
    if kind == "external":
        (tmp_path / "data.bin").write_bytes(blob)
        doc["buffers"][0]["uri"] = "data.bin"
        path = tmp_path / f"{kind}.gltf"
        path.write_text(json.dumps(doc, indent=1))
        return path
    if kind == "embedded":
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode()
        path = tmp_path / f"{kind}.gltf"
        path.write_text(json.dumps(doc))
        return path
    return _write_glb(tmp_path / f"{kind}.glb", doc, blob)


def _position_ranges(gltf):
    """{buffer: (bytes,) bool mask of the POSITION accessors' bytes}."""
    masks = {i: np.zeros(len(b), dtype=bool) for i, b in enumerate(gltf.buffers)}
    for acc_index in {s.accessor for s in gltf.slots}:
        acc = gltf.doc["accessors"][acc_index]
        view = gltf.doc["bufferViews"][acc["bufferView"]]
        size = {5126: 4, 5122: 2, 5123: 2, 5120: 1, 5121: 1}[acc["componentType"]]
        stride = view.get("byteStride") or 3 * size
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        for i in range(acc["count"]):
            masks[view["buffer"]][start + i * stride:start + i * stride + 3 * size] = True
    return masks


def _without_bounds(gltf):
    doc = json.loads(json.dumps(gltf.doc))
    for s in gltf.slots:
        acc = doc["accessors"][s.accessor]
        acc.pop("min", None), acc.pop("max", None)
    for b in doc.get("buffers", []):
        b.pop("uri", None)
    return doc


def round_trip(source, target, sigma=1e-3):
    """Move every point by ~sigma x diag, write, read back; assert what changed and what did not."""
    cloud = read_points(source, distinct=True)
    diag = np.linalg.norm(np.ptp(cloud.points, axis=0))
    moved = cloud.points + np.random.default_rng(1).normal(scale=sigma * diag, size=cloud.points.shape)
    write_points(cloud, moved, target)
    back = read_points(target)
    before, after = cloud.native, back.native
    assert _without_bounds(after) == _without_bounds(before)
    for i, mask in _position_ranges(before).items():
        old, new = np.frombuffer(before.buffers[i], np.uint8), np.frombuffer(after.buffers[i], np.uint8)
        assert len(old) == len(new)
        assert np.array_equal(old[~mask], new[~mask]), f"buffer {i}: bytes outside POSITION changed"
        assert mask.sum() == 0 or not np.array_equal(old[mask], new[mask])
    assert back.points.shape == cloud.points.shape
    return cloud, moved, back


@pytest.mark.parametrize("name", REAL)
def test_real_files_are_marked_in_place_or_refused_in_one_line(shared_data, tmp_path, name):
    source = shared_data / "gltf" / name
    if name in REFUSED:
        with pytest.raises(InputError) as info:
            read_points(source, distinct=True)
        message = str(info.value)
        assert REFUSED[name] in message and "\n" not in message and str(source) in message
        assert len(read_points(source).points) > 0          # a suspect so compressed is still read
        return
    cloud, moved, back = round_trip(source, tmp_path / name)
    diag = np.linalg.norm(np.ptp(cloud.points, axis=0))
    if name != "ShapeCollection.glb":                       # its instanced mesh takes the mean of two
        assert np.abs(back.points - moved).max() < 1e-6 * diag
    if name == "DamagedHelmet.glb":
        assert len(cloud.points) == 8661 and len(cloud.faces()) == 15452    # 14,556 vertices, seams welded


def test_a_mesh_on_seven_nodes_gives_one_point_set_per_instance(shared_data):
    gltf = read_points(shared_data / "gltf" / "ShapeCollection.glb").native
    accessors = [s.accessor for s in gltf.slots]
    assert len(gltf.slots) == 7 and len(set(accessors)) == 6


KINDS = ["plain", "instanced", "external", "embedded", "skinned", "morph", "interleaved", "shared-view", "quantized"]


@pytest.mark.parametrize("kind", KINDS)
def test_generated_files_keep_every_other_byte(tmp_path, kind):
    source = make(tmp_path, kind)
    cloud, moved, back = round_trip(source, tmp_path / "out" / f"copy{source.suffix}", sigma=2e-3)
    step = 1.5 / 32767 if kind == "quantized" else 1e-6
    if kind != "instanced":
        assert np.abs(back.points - moved).max() < 2 * step
    if kind == "external":                     # the original's .bin is untouched; the copy embeds its buffer
        text = json.loads((tmp_path / "out" / "copy.gltf").read_text())
        assert text["buffers"][0]["uri"].startswith("data:application/octet-stream;base64,")


def test_world_space_transforms_instances_and_bind_pose(tmp_path):
    local, _ = _grid()
    plain = read_points(make(tmp_path, "plain")).points
    assert np.allclose(np.sort(plain[:, 1]), np.sort(local[:, 1] + 2.0), atol=1e-6)    # translated
    assert len(read_points(make(tmp_path, "instanced")).points) == 2 * len(local)
    skinned = read_points(make(tmp_path, "skinned")).points    # the skinned node's transform is ignored
    assert np.allclose(skinned, local, atol=0)
    morph = read_points(make(tmp_path, "morph")).points        # targets' deltas are not applied
    assert np.allclose(np.sort(morph[:, 1]), np.sort(local[:, 1] + 2.0), atol=1e-6)


def test_quantized_positions_stay_integers_with_integer_bounds(tmp_path):
    source = make(tmp_path, "quantized")
    round_trip(source, tmp_path / "q.glb")
    acc = read_gltf((tmp_path / "q.glb").read_bytes(), tmp_path / "q.glb").doc["accessors"][1]
    assert acc["componentType"] == 5122 and all(isinstance(v, int) for v in acc["min"] + acc["max"])


def test_glb_chunks_are_padded_and_declare_the_file_length(tmp_path):
    data = glb_from_mesh(*_grid())
    assert data[:4] == b"glTF" and struct.unpack_from("<I", data, 8)[0] == len(data) and len(data) % 4 == 0
    (tmp_path / "m.glb").write_bytes(data)
    assert len(read_points(tmp_path / "m.glb").faces()) == 2 * 11 * 11


@pytest.mark.parametrize("bad, why", [(b"glTF\x01\0\0\0\x0c\0\0\0", "version 1"),
                                      (b"glTF\x02\0\0\0\xff\0\0\0", "declares 255 bytes"),
                                      (b"GLTF" + bytes(16), "no 'glTF' magic")])
def test_broken_glb_is_one_line_naming_the_file(tmp_path, bad, why):
    path = tmp_path / "bad.glb"
    path.write_bytes(bad)
    with pytest.raises(InputError, match=why) as info:
        read_points(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


needs_tools = pytest.mark.skipif(not gltf_tools.tools_available(),
                                 reason="node, gltf-validator and gltf-transform not installed (make setup)")


def _problems(path):
    return {(code, pointer) for code, severity, pointer in gltf_tools.validate(path) if severity <= 1}


@needs_tools
def test_the_validator_finds_nothing_new_in_written_files(shared_data, tmp_path):
    sources = [shared_data / "gltf" / n for n in REAL if n not in REFUSED]
    sources += [make(tmp_path, k) for k in KINDS]
    for source in sources:
        target = tmp_path / "out" / f"{source.stem}-copy{source.suffix}"
        round_trip(source, target)
        assert _problems(target) <= _problems(source), source.name


@needs_tools
def test_tool_attacks_chain_in_an_evaluation(tmp_path):
    from pipeline.orchestrate.evaluate import parse_chain
    from pipeline.surface import apply_chain

    points, faces = _grid(20)
    chain = parse_chain("gltf-weld+gltf-simplify:0.5+gltf-draco:11")
    assert chain[1] == ("gltf-simplify", 0.5) and chain[2] == ("gltf-draco", 11.0)
    out = apply_chain(points.astype(np.float64), chain, 0, faces=faces.astype(np.int64))
    assert 0 < len(out) < len(points) and np.abs(out).max() < 1.5
