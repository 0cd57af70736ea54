"""glTF and GLB: positions moved in place, every other byte kept, refusals named, the validator content.

Each file is read, its points moved by a known small displacement, written
and read back, and compared byte for byte: the JSON text outside the
POSITION accessors' ``min``/``max`` arrays (and a changed buffer's URI), each
buffer outside the POSITION bytes, and a GLB's header and chunks but for the
lengths.  Generated files cover a mesh on two nodes, an external ``.bin``, a
skin, a morph target, interleaved vertices, one buffer view shared by two
attributes, KHR_mesh_quantization, and hand-spelled JSON (indented, odd
number spellings, non-ASCII text, ``min``/``max`` keys in extras, a data
URI's own media type, a GLB with extra padding and an unknown chunk).
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


def _spelled(doc):
    """JSON text no serialiser writes: indented, numbers spelled oddly, non-ASCII, min/max in extras."""
    doc["asset"]["generator"] = "pointmark tésts ✓"
    doc["accessors"][1]["extras"] = {"min": [9, 9, 9], "max": [9, 9, 9], "note": "\"min\": [0]"}
    doc["extras"] = {"accessors": [{"min": [1, 2, 3]}]}
    text = json.dumps(doc, indent=3, ensure_ascii=False)
    return text.replace("[\n            1.0,\n            2.0,\n            3.0\n         ]", "[1E0, 2.00,3]")


def make(tmp_path, kind):
    doc, blob = generated("plain" if kind in ("external", "embedded", "spelled", "spelled-glb") else kind)
    if kind == "spelled":
        doc["buffers"][0]["uri"] = "data:application/gltf-buffer;base64," + base64.b64encode(blob).decode()
        path = tmp_path / f"{kind}.gltf"
        path.write_bytes(_spelled(doc).encode("utf-8") + b"\n\n")
        return path
    if kind == "spelled-glb":                  # 7 spaces past the JSON, an unknown chunk after the BIN
        text = _spelled(doc).encode("utf-8") + b"\n"
        text += b" " * (-len(text) % 4 + 4)
        chunks = [struct.pack("<II", len(text), 0x4E4F534A) + text, struct.pack("<II", len(blob), 0x004E4942) + blob,
                  struct.pack("<II", 8, 0x12345678) + b"extra!\0\0"]
        body = b"".join(chunks)
        path = tmp_path / f"{kind}.glb"
        path.write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)
        return path
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


def _spans(text, at=0, path=(), out=None):
    """{path: (start, end)} of every value in the JSON text, found by a scanner of the test's own."""
    out = {} if out is None else out
    decoder = json.JSONDecoder()

    def skip(i):
        while text[i] in " \t\r\n":
            i += 1
        return i

    start = at = skip(at)
    if text[at] in "{[":
        close, k = "}" if text[at] == "{" else "]", 0
        at = skip(at + 1)
        while text[at] != close:
            if close == "}":
                key, at = decoder.raw_decode(text, at)
                at = skip(skip(at) + 1)
            else:
                key, k = k, k + 1
            at = skip(_spans(text, at, path + (key,), out)[path + (key,)][1])
            if text[at] == ",":
                at = skip(at + 1)
        end = at + 1
    else:
        end = decoder.raw_decode(text, at)[1]
    out[path] = (start, end)
    return out


def _outside(text, spans):
    """The pieces of ``text`` between the given (start, end) spans."""
    pieces, at = [], 0
    for start, end in sorted(spans):
        pieces.append(text[at:start])
        at = end
    return pieces + [text[at:]]


def _stored(gltf, index):
    """(count, 3) POSITION values of accessor ``index`` as stored."""
    acc = gltf.doc["accessors"][index]
    view = gltf.doc["bufferViews"][acc["bufferView"]]
    dtype = np.dtype({5126: "<f4", 5122: "<i2", 5123: "<u2", 5120: "i1", 5121: "u1"}[acc["componentType"]])
    start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
    return np.ndarray((acc["count"], 3), dtype=dtype, buffer=gltf.buffers[view["buffer"]], offset=start,
                      strides=(view.get("byteStride") or 3 * dtype.itemsize, dtype.itemsize))


def _json_and_rest(raw, glb):
    """(JSON text, the bytes after the JSON chunk) of a file, checking a GLB's header and JSON chunk."""
    if not glb:
        return raw.decode("utf-8"), b""
    length = struct.unpack_from("<I", raw, 12)[0]
    assert struct.unpack_from("<I", raw, 8)[0] == len(raw) and len(raw) % 4 == 0 and length % 4 == 0
    return raw[20:20 + length].decode("utf-8"), raw[20 + length:]


def assert_same_bytes(source, target, before, after):
    """Every byte of ``target`` but POSITION data, its min/max and a changed buffer's URI is ``source``'s."""
    old_raw, new_raw = source.read_bytes(), target.read_bytes()
    glb = before.container == "glb"
    old_text, old_rest = _json_and_rest(old_raw, glb)
    new_text, new_rest = _json_and_rest(new_raw, glb)
    if glb:                                    # magic, version and the JSON chunk's type
        assert new_raw[:8] == old_raw[:8] and new_raw[16:20] == old_raw[16:20]
    masks = _position_ranges(before)
    accessors = sorted({s.accessor for s in before.slots})
    changed = {before.doc["accessors"][a]["bufferView"] for a in accessors}
    changed = {before.doc["bufferViews"][v]["buffer"] for v in changed}
    keys = [("accessors", a, k) for a in accessors for k in ("min", "max") if k in before.doc["accessors"][a]]
    keys += [("buffers", b, "uri") for b in changed if "uri" in before.doc["buffers"][b]]
    old_spans, new_spans = _spans(old_text), _spans(new_text)
    old_pieces = _outside(old_text, [old_spans[k] for k in keys])
    new_pieces = _outside(new_text, [new_spans[k] for k in keys])
    old_pieces[-1], new_pieces[-1] = old_pieces[-1].rstrip(" "), new_pieces[-1].rstrip(" ")  # GLB padding
    assert new_pieces == old_pieces, "the JSON text changed outside POSITION min/max"
    digits = str.maketrans("", "", "-+.0123456789eE")
    for key in keys[:2 * len(accessors)]:      # min/max: the numbers of the data, the spacing kept
        (a, b), (c, d) = old_spans[key], new_spans[key]
        assert new_text[c:d].translate(digits) == old_text[a:b].translate(digits)
        values = getattr(_stored(after, key[1]), key[2])(axis=0).tolist()
        assert json.loads(new_text[c:d]) == values
    assert len(new_rest) == len(old_rest)      # the chunks after the JSON: headers and data
    rest_mask = np.zeros(len(old_rest), dtype=bool)
    if before.bin_at is not None and 0 in masks and "uri" not in before.doc["buffers"][0]:
        at = before.bin_at - (len(old_raw) - len(old_rest))
        rest_mask[at:at + len(masks[0])] = masks[0]
    old, new = np.frombuffer(old_rest, np.uint8), np.frombuffer(new_rest, np.uint8)
    assert np.array_equal(old[~rest_mask], new[~rest_mask]), "GLB bytes after the JSON chunk changed"
    for i, mask in masks.items():              # each buffer, the data URIs' and external files' too
        old, new = np.frombuffer(before.buffers[i], np.uint8), np.frombuffer(after.buffers[i], np.uint8)
        assert len(old) == len(new)
        assert np.array_equal(old[~mask], new[~mask]), f"buffer {i}: bytes outside POSITION changed"
        assert mask.sum() == 0 or not np.array_equal(old[mask], new[mask])


def round_trip(source, target, sigma=1e-3):
    """Move every point by ~sigma x diag, write, read back; assert what changed and what did not."""
    cloud = read_points(source, distinct=True)
    diag = np.linalg.norm(np.ptp(cloud.points, axis=0))
    moved = cloud.points + np.random.default_rng(1).normal(scale=sigma * diag, size=cloud.points.shape)
    write_points(cloud, moved, target)
    back = read_points(target)
    assert_same_bytes(source, target, cloud.native, back.native)
    assert back.points.shape == cloud.points.shape
    return cloud, moved, back


def test_a_write_that_moves_nothing_gives_the_original_bytes(tmp_path):
    source = tmp_path / "m.glb"
    source.write_bytes(glb_from_mesh(*_grid()))
    cloud = read_points(source, distinct=True)
    write_points(cloud, cloud.points, tmp_path / "out.glb")
    assert (tmp_path / "out.glb").read_bytes() == source.read_bytes()


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
    assert np.abs(back.points - moved).max() < 1e-6 * diag  # an instanced mesh is marked once, in full
    if name == "DamagedHelmet.glb":
        assert len(cloud.points) == 8661 and len(cloud.faces()) == 15452    # 14,556 vertices, seams welded


def test_a_mesh_on_seven_nodes_gives_one_point_set_per_instance(shared_data):
    gltf = read_points(shared_data / "gltf" / "ShapeCollection.glb").native
    accessors = [s.accessor for s in gltf.slots]
    assert len(gltf.slots) == 7 and len(set(accessors)) == 6


KINDS = ["plain", "instanced", "embedded", "skinned", "morph", "interleaved", "shared-view", "quantized",
         "spelled", "spelled-glb"]


@pytest.mark.parametrize("kind", KINDS)
def test_generated_files_keep_every_other_byte(tmp_path, kind):
    source = make(tmp_path, kind)
    cloud, moved, back = round_trip(source, tmp_path / "out" / f"copy{source.suffix}", sigma=2e-3)
    step = 1.5 / 32767 if kind == "quantized" else 1e-6
    assert np.abs(back.points - moved).max() < 2 * step
    if kind == "spelled":                      # the data URI keeps its media type
        text = json.loads((tmp_path / "out" / "copy.gltf").read_text())
        media = "gltf-buffer" if kind == "spelled" else "octet-stream"
        assert text["buffers"][0]["uri"].startswith(f"data:application/{media};base64,")


def test_world_space_transforms_instances_and_bind_pose(tmp_path):
    local, _ = _grid()
    plain = read_points(make(tmp_path, "plain")).points
    assert np.allclose(np.sort(plain[:, 1]), np.sort(local[:, 1] + 2.0), atol=1e-6)    # translated
    assert len(read_points(make(tmp_path, "instanced")).points) == len(local)      # counted once
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


needs_tools = pytest.mark.usefixtures("node_tools")    # skips without them, fails under CI=true


def _problems(issues):
    return {(code, pointer) for code, severity, pointer in issues if severity <= 1}


@needs_tools
def test_the_validator_finds_nothing_new_in_written_files(shared_data, tmp_path):
    sources = [shared_data / "gltf" / n for n in REAL if n not in REFUSED]
    sources += [make(tmp_path, k) for k in KINDS]
    targets = [tmp_path / "out" / f"{source.stem}-copy{source.suffix}" for source in sources]
    for source, target in zip(sources, targets):
        round_trip(source, target)
    reports = gltf_tools.validate_all(sources + targets)        # one node process for all
    assert len(reports) == 2 * len(sources)
    for source, old, new in zip(sources, reports, reports[len(sources):]):
        assert _problems(new) <= _problems(old), source.name
    assert gltf_tools.validate(targets[0]) == reports[len(sources)]


@needs_tools
def test_tool_attacks_chain_in_an_evaluation(tmp_path):
    from pipeline.orchestrate.evaluate import parse_chain
    from pipeline.surface import apply_chain

    points, faces = _grid(20)
    chain = parse_chain("gltf-weld+gltf-simplify:0.5+gltf-draco:11")
    assert chain[1] == ("gltf-simplify", 0.5) and chain[2] == ("gltf-draco", 11.0)
    out = apply_chain(points.astype(np.float64), chain, 0, faces=faces.astype(np.int64))
    assert 0 < len(out) < len(points) and np.abs(out).max() < 1.5


# ---------------------------------------------------------------------------------------------------------------
# Hostile and awkward inputs: one line naming the file, before any work, in bounded memory.

def _hostile(count=50, uri=None, nodes=None):
    """A small .gltf document of bare points, its buffer a data URI (or ``uri``)."""
    pts = np.random.default_rng(0).normal(size=(count, 3)).astype("<f4")
    blob = pts.tobytes()
    return {"asset": {"version": "2.0"}, "scenes": [{"nodes": [0]}], "nodes": nodes or [{"mesh": 0}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "mode": 0}]}],
            "buffers": [{"byteLength": len(blob),
                         "uri": uri or "data:application/octet-stream;base64," + base64.b64encode(blob).decode()}],
            "bufferViews": [{"buffer": 0, "byteLength": len(blob)}],
            "accessors": [_vec3(0, count, pts)]}, blob


def _refused(path, match, *, distinct=False):
    with pytest.raises(InputError, match=match) as info:
        read_points(path, distinct=distinct)
    message = str(info.value)
    assert str(path) in message and "\n" not in message
    return message


@pytest.mark.parametrize("where, why", [("/dev/zero", "not a relative path"), ("../outside.bin", "leaves the file's folder"),
                                        ("link.bin", "leaves the file's folder"), ("fifo.bin", "not a regular file"),
                                        ("short.bin", "holds 100 bytes"), ("sub", "not a regular file"),
                                        ("http://example.com/a.bin", "not a relative path")])
def test_buffer_uris_stay_inside_the_folder_and_name_regular_files(tmp_path, where, why):
    import os

    folder = tmp_path / "asset"
    folder.mkdir()
    (tmp_path / "outside.bin").write_bytes(bytes(600))
    os.symlink(tmp_path / "outside.bin", folder / "link.bin")
    os.mkfifo(folder / "fifo.bin")                  # opened with blocking, this would hang the read
    (folder / "short.bin").write_bytes(bytes(100))
    (folder / "sub").mkdir()
    doc, _ = _hostile(uri=where)
    path = folder / "m.gltf"
    path.write_text(json.dumps(doc))
    _refused(path, why)


def test_an_external_buffer_is_read_up_to_its_length_for_a_suspect_and_refused_in_an_original(tmp_path):
    doc, blob = _hostile(uri="data%20file.bin")
    (tmp_path / "data file.bin").write_bytes(blob + b"trailing bytes the buffer does not declare")
    path = tmp_path / "m.gltf"
    path.write_text(json.dumps(doc))
    cloud = read_points(path)                       # a suspect may keep its buffers beside it
    assert len(cloud.points) == 50 and len(cloud.native.buffers[0]) == len(blob)
    message = _refused(path, "pack it as .glb or embed the buffers", distinct=True)
    assert "gltf-transform copy in.gltf out.glb" in message


def _edit(doc, how):
    if how == "mesh":
        doc["nodes"][0]["mesh"] = 5
    elif how == "negative mesh":
        doc["nodes"][0]["mesh"] = -1
    elif how == "position":
        doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = 9
    elif how == "view":
        doc["accessors"][0]["bufferView"] = 7
    elif how == "negative view":
        doc["accessors"][0]["bufferView"] = -1
    elif how == "buffer":
        doc["bufferViews"][0]["buffer"] = 3
    elif how == "child":
        doc["nodes"][0]["children"] = [4]
    elif how == "cycle":
        doc["nodes"] = [{"mesh": 0}, {"children": [2]}, {"children": [1]}]
    elif how == "own child":
        doc["nodes"][0]["children"] = [0]
    elif how == "shared child":
        doc["nodes"] = [{"children": [2]}, {"children": [2]}, {"mesh": 0}]
    elif how == "string index":
        doc["nodes"][0]["mesh"] = "0"
    elif how == "count":
        doc["accessors"][0]["count"] = -1
    elif how == "stride":
        doc["bufferViews"][0]["byteStride"] = -12
    elif how == "offset":
        doc["accessors"][0]["byteOffset"] = -12
    elif how == "matrix":
        doc["nodes"][0]["matrix"] = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0]
    elif how == "rotation":
        doc["nodes"][0]["rotation"] = [0, 0, 0]
    elif how == "indices":
        doc["meshes"][0]["primitives"][0].update(indices=0, mode=4)
    elif how == "vec2":
        doc["accessors"][0]["type"] = "VEC2"
    return doc


HOSTILE = {"mesh": "node 0: mesh is '5'", "negative mesh": "node 0: mesh is '-1'", "position": "POSITION is '9'",
           "view": "bufferView is '7'", "negative view": "bufferView is '-1'", "buffer": "buffer is '3'",
           "child": "child is '4'", "cycle": "node 1 is part of a cycle", "own child": "reached twice",
           "shared child": "node 2 is reached twice", "string index": "mesh is '0'", "count": "count is '-1'",
           "stride": "byteStride is '-12'", "offset": "byteOffset is '-12'", "matrix": "'matrix' must be 16 numbers",
           "rotation": "'rotation' must be 4 numbers", "indices": "indices must be SCALAR unsigned integers",
           "vec2": "must be VEC3"}


@pytest.mark.parametrize("how", sorted(HOSTILE))
def test_hostile_indices_and_types_are_one_line(tmp_path, how):
    doc, _ = _hostile()
    path = tmp_path / "m.gltf"
    path.write_text(json.dumps(_edit(doc, how)))
    _refused(path, HOSTILE[how])


def test_deeply_nested_json_is_one_line(tmp_path):
    path = tmp_path / "deep.gltf"
    path.write_text('{"asset":{"version":"2.0"},"extras":' + "[" * 200000 + "]" * 200000 + "}")
    _refused(path, "nested too deep")


def test_the_cli_names_a_hostile_file_in_one_line_with_status_2(tmp_path, capsys):
    from pipeline.cli import main

    doc, _ = _hostile()
    path = tmp_path / "m.gltf"
    path.write_text(json.dumps(_edit(doc, "view")))
    assert main(["attack", str(path), str(tmp_path / "out.gltf"), "--attack", "similarity"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(path) in err and "bufferView is '7'" in err


def test_sizes_beyond_what_the_file_holds_are_refused_before_allocating(tmp_path):
    doc, _ = _hostile()
    del doc["accessors"][0]["bufferView"]
    doc["accessors"][0]["count"] = 10**11               # zero-filled: 2.4 TB of float64
    (tmp_path / "zeros.gltf").write_text(json.dumps(doc))
    _refused(tmp_path / "zeros.gltf", "would expand the file beyond 64 values per stored byte")
    doc, _ = _hostile()                                 # a meshopt fallback buffer of 40 GB holds no bytes
    doc["buffers"].append({"byteLength": 4 * 10**10, "extensions": {"EXT_meshopt_compression": {"fallback": True}}})
    doc["bufferViews"].append({"buffer": 1, "byteLength": 4 * 10**10, "byteStride": 12,
                               "extensions": {"EXT_meshopt_compression": {"buffer": 0, "byteLength": 600,
                                                                          "byteStride": 12, "count": 10**9}}})
    doc["accessors"][0]["bufferView"] = 1
    doc["accessors"][0]["count"] = 10**9
    doc["extensionsUsed"] = ["EXT_meshopt_compression"]
    (tmp_path / "meshopt.gltf").write_text(json.dumps(doc))
    _refused(tmp_path / "meshopt.gltf", "would expand the file")
    doc["bufferViews"][1]["extensions"]["EXT_meshopt_compression"]["count"] = 50   # the view longer than its data
    doc["accessors"][0]["count"] = 50
    (tmp_path / "meshopt.gltf").write_text(json.dumps(doc))
    _refused(tmp_path / "meshopt.gltf", "decoded bytes are fewer")


def test_a_mesh_on_2000_nodes_is_counted_once(tmp_path):
    doc, _ = _hostile(count=300, nodes=[{"children": list(range(1, 2001))}]
                      + [{"mesh": 0, "translation": [i, 0, 0]} for i in range(2000)])
    path = tmp_path / "many.gltf"
    path.write_text(json.dumps(doc))
    cloud = read_points(path, distinct=True)
    assert len(cloud.points) == 300 and len(cloud.native.slots) == 2000


def test_an_instanced_mesh_is_marked_once_and_every_instance_moves_with_it(tmp_path):
    source = make(tmp_path, "instanced")
    cloud, moved, back = round_trip(source, tmp_path / "copy.glb")
    assert np.abs(back.points - moved).max() < 1e-5          # the whole mark, not the mean of two instances
    second = [s for s in back.native.slots if s.where is None][0]
    local = read_gltf((tmp_path / "copy.glb").read_bytes(), tmp_path / "copy.glb")
    from pipeline.io.gltf import _accessor
    world = _accessor(local, second.accessor) @ second.matrix[:3, :3].T + second.matrix[:3, 3]
    first = [s for s in back.native.slots if s.where is not None][0]
    inverse = np.linalg.inv(first.matrix)
    expected = (moved[first.where] @ inverse[:3, :3].T + inverse[:3, 3]) @ second.matrix[:3, :3].T + second.matrix[:3, 3]
    assert np.abs(world - expected).max() < 1e-5            # the second instance: the same marked data, moved


@pytest.mark.parametrize("transform", [{"translation": [1.0, 0.0, 0.0]},
                                       {"translation": [0.7, 0.1, -0.3], "rotation": [0.0, 0.3826834, 0.0, 0.9238795],
                                        "scale": [1.3, 1.3, 1.3]}])
def test_a_seam_between_two_transformed_nodes_stays_one_point_set(tmp_path, transform):
    """Two meshes on differently transformed nodes share a seam column: marked, it reads back point for point."""
    n = 24
    u, w = np.arange(0, 2 * n + 1) / n, np.arange(0, n + 1) / n
    X, Y = np.meshgrid(u, w, indexing="ij")
    world = np.stack([X, Y, np.round(0.2 * np.sin(3 * X) * np.cos(2 * Y) * 1024) / 1024], -1)
    a = world[:n + 1].reshape(-1, 3).astype("<f4")
    node_b = {"mesh": 1, **transform}
    from pipeline.io.gltf import _local
    matrix = _local(node_b)
    inverse = np.linalg.inv(matrix)
    b = (world[n:].reshape(-1, 3) @ inverse[:3, :3].T + inverse[:3, 3]).astype("<f4")
    blob = a.tobytes() + b.tobytes()
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0, 1]}], "nodes": [{"mesh": 0}, node_b],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "mode": 0}]},
                      {"primitives": [{"attributes": {"POSITION": 1}, "mode": 0}]}],
           "buffers": [{"byteLength": len(blob),
                        "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()}],
           "bufferViews": [{"buffer": 0, "byteLength": a.nbytes},
                           {"buffer": 0, "byteOffset": a.nbytes, "byteLength": b.nbytes}],
           "accessors": [_vec3(0, len(a), a), _vec3(1, len(b), b)]}
    source = tmp_path / "seam.gltf"
    source.write_text(json.dumps(doc))
    cloud = read_points(source, distinct=True)
    assert len(cloud.points) == len(a) + len(b) - (n + 1)            # the seam column is one set of points
    for seed in range(3):
        moved = cloud.points + np.random.default_rng(seed).normal(scale=1e-3, size=cloud.points.shape)
        write_points(cloud, moved, tmp_path / f"copy{seed}.gltf")
        back = read_points(tmp_path / f"copy{seed}.gltf")
        assert back.points.shape == cloud.points.shape
        assert np.abs(back.points - moved).max() < 1e-6              # the same points, in the same order


def test_attack_writes_a_gltf_copy_with_an_embedded_buffer(tmp_path):
    from pipeline.cli import main

    source = tmp_path / "m.glb"
    source.write_bytes(glb_from_mesh(*_grid()))
    assert main(["attack", str(source), str(tmp_path / "out.gltf"), "--attack", "noise:0.1%"]) == 0
    text = json.loads((tmp_path / "out.gltf").read_text())
    assert text["buffers"][0]["uri"].startswith("data:application/octet-stream;base64,")
    assert len(read_points(tmp_path / "out.gltf").points) == len(_grid()[0])


@pytest.mark.parametrize("spec, why", [("gltf-simplify:7", "in \\(0, 1\\]"), ("gltf-simplify:0", "in \\(0, 1\\]"),
                                       ("gltf-draco:40", "from 1 to 30"), ("gltf-draco:nan", "from 1 to 30"),
                                       ("gltf-draco:10.5", "from 1 to 30"), ("gltf-simplify:inf", "in \\(0, 1\\]"),
                                       ("gltf-weld:3", "takes no strength"), ("gltf-draco:x", "not a number")])
def test_tool_attack_strengths_are_checked_before_any_work(tmp_path, capsys, spec, why):
    from pipeline.cli import main
    from pipeline.surface import parse_attack

    with pytest.raises(ValueError, match=why):
        parse_attack(spec)
    source = tmp_path / "m.glb"
    source.write_bytes(glb_from_mesh(*_grid()))
    assert main(["attack", str(source), str(tmp_path / "out.glb"), "--attack", spec]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--attack" in err
    assert parse_attack("gltf-simplify:50%") == ("gltf-simplify", 0.5) and parse_attack("gltf-draco:30")[1] == 30


def test_a_tool_error_is_a_usage_error():
    from pipeline.cli import USAGE_ERRORS

    assert issubclass(gltf_tools.ToolError, USAGE_ERRORS)
