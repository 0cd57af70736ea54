"""glTF 2.0 (``.gltf``) and GLB (``.glb``): world-space vertex positions, written back in place.

The point set is every mesh primitive's POSITION data in world space: node
transforms applied, a mesh on several nodes counted once per node, and
vertices at the same world position (the copies a UV seam or a shared
accessor makes) counted once, so a seam never cracks open.  Skinned meshes
give their bind pose (the node transform is ignored, as the spec says);
morph-target deltas are not applied and are written back unchanged.

Writing changes only the bytes of the POSITION accessors and their ``min``
and ``max``: each point's new world position goes back through the inverse
node transform, a mesh instanced on several nodes takes the mean of its
instances' positions, and the values are stored in the accessor's own
component type (float32, or KHR_mesh_quantization's integers, normalized or
not).  The JSON text is patched in place: only the numbers of those
accessors' ``min`` and ``max`` arrays (and the base64 of a changed buffer's
URI) are spliced in, every other byte of the text is kept, and every other
byte of every buffer.  A GLB keeps its chunks; only the JSON chunk's length
and space padding and the header's total length follow the text.  A ``.gltf``
output (or a GLB's buffer with a URI) holds the changed buffers as base64 data
URIs; its other URIs (textures, untouched buffers) are kept as they are,
relative to the copy's folder.

Suspects compressed with KHR_draco_mesh_compression (DracoPy) or
EXT_meshopt_compression (meshoptimizer) are read; such originals, and
sparse POSITION accessors, are refused because they cannot be written back
byte for byte.
"""

from __future__ import annotations

import base64
import json
import os
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import unquote

import numpy as np

__all__ = ["GltfData", "GltfError", "read_gltf", "write_gltf", "check_head", "glb_from_points", "glb_from_mesh",
           "REFUSED"]

_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = b"glTF", 0x4E4F534A, 0x004E4942
_DTYPES = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_NORMALIZE = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}
DRACO, MESHOPT = "KHR_draco_mesh_compression", "EXT_meshopt_compression"
# what an original may not use, and why: a one-line refusal before any work
REFUSED = {
    DRACO: "Draco re-encoding rewrites every compressed attribute (normals, UVs, indices), not only the "
           "positions; decompress it to plain accessors first",
    MESHOPT: "meshopt re-encoding rewrites every compressed buffer view, not only the positions; "
             "decompress it to plain accessors first",
}


class GltfError(ValueError):
    """A glTF or GLB file that cannot be read or written back (the message says why)."""


@dataclass
class _Slot:
    """One POSITION accessor seen through one node: its world transform and its points."""

    accessor: int
    matrix: np.ndarray          # (4, 4) float64, local to world
    where: np.ndarray = None    # (count,) int64 index of each vertex in the point set


@dataclass
class GltfData:
    """A parsed glTF file: its JSON, its buffers and where each point came from.

    Attributes
    ----------
    doc : dict
        The JSON as parsed (key order kept).
    buffers : list of bytes
        Each buffer's bytes (the GLB BIN chunk for a buffer without ``uri``).
    container : str
        ``"glb"`` or ``"gltf"``.
    base : pathlib.Path
        Folder that relative URIs resolve against.
    points : (n, 3) float64
        Distinct world-space positions.
    triangles : (f, 3) int64
        Triangles over ``points`` (every triangle, strip and fan primitive).
    slots : list of _Slot
    refusal : str or None
        Why the file cannot be written back (a compression extension, a sparse position accessor).
    text : bytes
        The JSON text as stored (a GLB's JSON chunk, padding included).
    source : bytes
        The whole file as read.
    bin_at : int or None
        Where the GLB's BIN chunk data starts in ``source``.
    """

    doc: dict
    buffers: list
    container: str
    base: Path
    points: np.ndarray = None
    triangles: np.ndarray = None
    slots: list = field(default_factory=list)
    refusal: str = None
    views: dict = field(default_factory=dict)     # meshopt-decoded buffer views
    text: bytes = b""
    source: bytes = b""
    bin_at: int = None

    def faces(self):
        """(f, 3) int64 triangles over the points, empty when the file has none."""
        return self.triangles


def check_head(fmt, head, size):
    """A GLB's header against the file's length; a ``.gltf`` must start as JSON text."""
    if fmt == "glb":
        if len(head) < 12 or head[:4] != _GLB_MAGIC:
            raise GltfError("not a GLB file (no 'glTF' magic)")
        version, length = struct.unpack_from("<II", head, 4)
        if version != 2:
            raise GltfError(f"GLB version {version} is not supported (2 expected)")
        if length != size:
            raise GltfError(f"the GLB header declares {length} bytes, the file holds {size}")
        if size < 20:
            raise GltfError("truncated: the GLB holds no JSON chunk")
    elif not head.lstrip()[:1] == b"{":
        raise GltfError("not a glTF file (its JSON does not start with '{')")


def read_gltf(data, path, *, original=False):
    """Parse a ``.glb`` or ``.gltf`` file into its point set.

    Parameters
    ----------
    data : bytes or binary file
    path : str or Path
        The file's path: its suffix picks the container, its folder resolves URIs.
    original : bool
        Refuse, before any work, a file that cannot be written back (:data:`REFUSED`).

    Returns
    -------
    GltfData
    """
    if not isinstance(data, (bytes, bytearray)):
        data.seek(0)
        data = data.read()
    raw = data
    path = Path(path)
    container = "glb" if path.suffix.lower() == ".glb" else "gltf"
    text, blob, bin_at = _split_glb(raw) if container == "glb" else (raw, None, None)
    doc = _parse_json(text)
    gltf = GltfData(doc, [], container, path.parent, text=bytes(text), source=bytes(raw), bin_at=bin_at)
    gltf.buffers = [_buffer(gltf, i, b, blob) for i, b in enumerate(doc.get("buffers", []))]
    gltf.refusal = _refusal(doc)
    if original and gltf.refusal:
        raise GltfError(gltf.refusal)
    _collect(gltf)
    return gltf


def _split_glb(raw):
    """(JSON bytes, BIN chunk bytes or None, where the BIN data starts or None) of a GLB."""
    if len(raw) < 20 or raw[:4] != _GLB_MAGIC:
        raise GltfError("not a GLB file (no 'glTF' magic)")
    chunks, at = [], 12
    while at + 8 <= len(raw):
        length, kind = struct.unpack_from("<II", raw, at)
        if at + 8 + length > len(raw):
            raise GltfError(f"truncated: a GLB chunk at byte {at} declares {length} bytes")
        chunks.append((kind, raw[at + 8:at + 8 + length], at + 8))
        at += 8 + length + (-length % 4)
    if not chunks or chunks[0][0] != _JSON_CHUNK:
        raise GltfError("the GLB's first chunk is not JSON")
    if len(chunks) > 1 and chunks[1][0] == _BIN_CHUNK:
        return chunks[0][1], chunks[1][1], chunks[1][2]
    return chunks[0][1], None, None


def _parse_json(text):
    """The JSON as a dict, checked against the glTF schema by pygltflib."""
    import pygltflib

    try:
        doc = json.loads(bytes(text).decode("utf-8"))
        with warnings.catch_warnings():         # its dataclass decoder warns on optional fields left out
            warnings.simplefilter("ignore")
            pygltflib.GLTF2.from_dict(doc)
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise GltfError(f"invalid glTF JSON: {' '.join(str(exc).split())[:160]}") from None
    if not isinstance(doc, dict) or not str(doc.get("asset", {}).get("version", "")).startswith("2"):
        raise GltfError("not a glTF 2.0 file (asset.version must be 2.x)")
    return doc


def _buffer(gltf, index, spec, blob):
    """Bytes of buffer ``index``: the GLB BIN chunk, a data URI or a file beside the glTF."""
    uri, length = spec.get("uri"), int(spec.get("byteLength", 0))
    if uri is None and spec.get("extensions", {}).get(MESHOPT, {}).get("fallback"):
        return bytes(length)            # meshopt's placeholder: every view on it is compressed
    if uri is None:
        if blob is None:
            raise GltfError(f"buffer {index} has no uri and the file no BIN chunk")
        data = blob
    elif uri.startswith("data:"):
        try:
            data = base64.b64decode(uri.split(",", 1)[1], validate=True)
        except (ValueError, IndexError):
            raise GltfError(f"buffer {index}: its data URI is not base64") from None
    else:
        target = gltf.base / unquote(uri)
        try:
            data = target.read_bytes()
        except OSError as exc:
            raise GltfError(f"buffer {index}: cannot read {uri!r}: {os.strerror(exc.errno or 0).lower()}") from None
    if len(data) < length:
        raise GltfError(f"buffer {index} declares {length} bytes, holds {len(data)}")
    return bytes(data)


def _refusal(doc):
    """Why the file cannot be written back byte for byte, or None."""
    for name in (DRACO, MESHOPT, "KHR_meshopt_compression"):
        if name in doc.get("extensionsUsed", []):
            return f"{name}: {REFUSED.get(name, REFUSED[MESHOPT])}"
    for mesh in doc.get("meshes", []):
        for prim in mesh.get("primitives", []):
            acc = doc["accessors"][prim["attributes"]["POSITION"]] if "POSITION" in prim.get("attributes", {}) \
                else {}
            if "sparse" in acc or (acc and "bufferView" not in acc):
                return "a sparse POSITION accessor cannot be written back in place; make it dense first"
    return None


def _collect(gltf):
    """Slots, distinct world points and triangles of every primitive reached from a root node."""
    doc = gltf.doc
    slots, triangles, seen = {}, [], set()
    for node, matrix in _walk(doc):
        mesh = doc.get("meshes", [])[doc["nodes"][node]["mesh"]]
        for prim in mesh.get("primitives", []):
            acc = prim.get("attributes", {}).get("POSITION")
            if acc is None:
                continue
            slot = slots.setdefault((acc, node), _Slot(acc, matrix))
            if (id(prim), node) not in seen:
                seen.add((id(prim), node))
                triangles.append((slot, _triangles(gltf, prim, doc["accessors"][acc]["count"])))
    if not slots:
        raise GltfError("no mesh primitive with POSITION data is reached from a node")
    gltf.slots = list(slots.values())
    worlds = [_world(gltf, s) for s in gltf.slots]
    points, inverse = _first_occurrences(np.concatenate(worlds))
    bounds = np.cumsum([0] + [len(w) for w in worlds])
    for s, a, b in zip(gltf.slots, bounds[:-1], bounds[1:]):
        s.where = np.asarray(inverse).reshape(-1)[a:b]
    tri = [s.where[t] for s, t in triangles if len(t)]
    tri = np.concatenate(tri) if tri else np.zeros((0, 3), dtype=np.int64)
    keep = (tri[:, 0] != tri[:, 1]) & (tri[:, 1] != tri[:, 2]) & (tri[:, 0] != tri[:, 2])
    gltf.points, gltf.triangles = points, tri[keep].astype(np.int64)


def _first_occurrences(worlds):
    """(distinct points (n, 3) in the order they first occur, (m,) index of each vertex among them).

    The order follows the file's structure, not the coordinates: a marked
    copy reads back in its original's order.
    """
    _, first, inverse = np.unique(worlds, axis=0, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int64)
    order = np.argsort(first)
    rank[order] = np.arange(len(first))
    return worlds[first[order]], rank[np.asarray(inverse).reshape(-1)]


def _walk(doc):
    """(node index, (4, 4) world matrix) of each node holding a mesh, from every root."""
    nodes = doc.get("nodes", [])
    children = {c for n in nodes for c in n.get("children", [])}
    stack = [(i, np.eye(4)) for i in range(len(nodes)) if i not in children]
    visited = set()
    while stack:
        index, parent = stack.pop()
        if index in visited:
            raise GltfError(f"node {index} is reached twice (a cycle or a shared child)")
        visited.add(index)
        node = nodes[index]
        world = parent @ _local(node)
        if "mesh" in node:
            yield index, np.eye(4) if "skin" in node else world     # skins: the bind pose
        stack.extend((c, world) for c in node.get("children", []))


def _local(node):
    """A node's (4, 4) local matrix: ``matrix`` (column-major) or T @ R @ S."""
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T
    x, y, z, w = node.get("rotation", (0.0, 0.0, 0.0, 1.0))
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    out = np.eye(4)
    out[:3, :3] = rotation * np.asarray(node.get("scale", (1.0, 1.0, 1.0)), dtype=np.float64)
    out[:3, 3] = node.get("translation", (0.0, 0.0, 0.0))
    return out


def _world(gltf, slot):
    """(count, 3) float64 world positions of a slot."""
    local = _accessor(gltf, slot.accessor)
    return local @ slot.matrix[:3, :3].T + slot.matrix[:3, 3]


def _accessor(gltf, index, *, draco=None):
    """(count, width) float64 values of an accessor (normalized integers scaled to [-1, 1] or [0, 1])."""
    acc = gltf.doc["accessors"][index]
    width, kind = _WIDTH.get(acc.get("type"), 0), acc.get("componentType")
    if kind not in _DTYPES or not width:
        raise GltfError(f"accessor {index}: component type {kind} / type {acc.get('type')} not supported")
    count = int(acc["count"])
    decoded = _draco_values(gltf, index)
    if decoded is not None:
        values = decoded
    elif "bufferView" in acc:
        values = _strided(gltf, acc, index, width).astype(np.float64)
    else:
        values = np.zeros((count, width))
    if "sparse" in acc:
        values = _sparse(gltf, acc, values)
    if acc.get("normalized") and kind in _NORMALIZE:
        values = np.maximum(values / _NORMALIZE[kind], -1.0)
    return values


def _strided(gltf, acc, index, width):
    """(count, width) stored values of an accessor, read through its buffer view's stride."""
    dtype = np.dtype(_DTYPES[acc["componentType"]])
    view, data = _view(gltf, acc["bufferView"])
    stride = view.get("byteStride") or dtype.itemsize * width
    start, count = int(acc.get("byteOffset", 0)), int(acc["count"])
    need = start + (count - 1) * stride + dtype.itemsize * width if count else 0
    if need > len(data):
        raise GltfError(f"accessor {index} reaches byte {need} of a {len(data)}-byte buffer view")
    return np.ndarray((count, width), dtype=dtype, buffer=data, offset=start, strides=(stride, dtype.itemsize))


def _view(gltf, index):
    """(view JSON, its bytes): meshopt-decoded when compressed."""
    view = gltf.doc["bufferViews"][index]
    if index in gltf.views:
        return view, gltf.views[index]
    ext = view.get("extensions", {}).get(MESHOPT) or view.get("extensions", {}).get("KHR_meshopt_compression")
    if ext:
        gltf.views[index] = _meshopt(gltf, ext, int(view["byteLength"]))
        return view, gltf.views[index]
    buffer = gltf.buffers[view["buffer"]]
    start, length = int(view.get("byteOffset", 0)), int(view["byteLength"])
    if start + length > len(buffer):
        raise GltfError(f"buffer view {index} reaches byte {start + length} of a {len(buffer)}-byte buffer")
    return view, memoryview(buffer)[start:start + length]


def _meshopt(gltf, ext, length):
    """A meshopt-compressed buffer view's bytes, decoded (vertex, index and sequence modes, filters)."""
    import meshoptimizer as mo

    source = gltf.buffers[ext["buffer"]]
    start = int(ext.get("byteOffset", 0))
    data = bytes(source[start:start + int(ext["byteLength"])])
    count, stride, mode = int(ext["count"]), int(ext["byteStride"]), ext.get("mode", "ATTRIBUTES")
    try:
        if mode == "ATTRIBUTES":
            out = mo.decode_vertex_buffer(count, stride, data)   # float32 words: its uint8 dtype overruns
            flt = {"OCTAHEDRAL": mo.decode_filter_oct, "QUATERNION": mo.decode_filter_quat,
                   "EXPONENTIAL": mo.decode_filter_exp}.get(ext.get("filter", "NONE"))
            if flt is not None:
                out = flt(np.asarray(out), count, stride)
        elif mode == "TRIANGLES":       # decoded as 32-bit (its 16-bit output packs two per word)
            out = mo.decode_index_buffer(count, 4, data)
        else:
            out = mo.decode_index_sequence(count, 4, data)
    except (ValueError, RuntimeError) as exc:
        raise GltfError(f"cannot decode meshopt data: {exc}") from None
    out = np.ascontiguousarray(out)
    if mode != "ATTRIBUTES":
        out = out.astype({2: "<u2", 4: "<u4"}[stride])
    return out.tobytes()[:length].ljust(length, b"\0")


def _sparse(gltf, acc, values):
    sparse = acc["sparse"]
    idx_spec, val_spec = sparse["indices"], sparse["values"]
    n = int(sparse["count"])
    idx = _strided(gltf, {"componentType": idx_spec["componentType"], "bufferView": idx_spec["bufferView"],
                          "byteOffset": idx_spec.get("byteOffset", 0), "count": n}, -1, 1)[:, 0]
    width = values.shape[1]
    new = _strided(gltf, {"componentType": acc["componentType"], "bufferView": val_spec["bufferView"],
                          "byteOffset": val_spec.get("byteOffset", 0), "count": n}, -1, width)
    if len(idx) and idx.max() >= len(values):
        raise GltfError("a sparse accessor's index lies beyond its count")
    values = values.copy()
    values[idx.astype(np.int64)] = new
    return values


def _draco_values(gltf, index):
    """Stored values of a Draco-compressed accessor (decoded once per primitive), or None."""
    cache = gltf.views.setdefault("draco", {})
    if not cache and DRACO in gltf.doc.get("extensionsUsed", []):
        _decode_draco(gltf, cache)
    return cache.get(index)


def _decode_draco(gltf, cache):
    import DracoPy

    for mesh in gltf.doc.get("meshes", []):
        for prim in mesh.get("primitives", []):
            ext = prim.get("extensions", {}).get(DRACO)
            if not ext:
                continue
            _, data = _view(gltf, ext["bufferView"])
            try:
                decoded = DracoPy.decode(bytes(data))
            except Exception as exc:    # DracoPy raises its own error types
                raise GltfError(f"cannot decode Draco data: {exc}") from None
            if "POSITION" in prim["attributes"]:
                cache[prim["attributes"]["POSITION"]] = np.asarray(decoded.points, dtype=np.float64)
            if "indices" in prim:
                cache[prim["indices"]] = np.asarray(decoded.faces, dtype=np.float64).reshape(-1, 1)


def _triangles(gltf, prim, count):
    """(t, 3) int64 vertex indices of a primitive's triangles (strips and fans unrolled)."""
    mode = prim.get("mode", 4)
    if mode not in (4, 5, 6):
        return np.zeros((0, 3), dtype=np.int64)
    if "indices" in prim:
        ids = _accessor(gltf, prim["indices"])[:, 0].astype(np.int64)
        if len(ids) and (ids.min() < 0 or ids.max() >= count):
            raise GltfError(f"primitive indices reach vertex {int(ids.max())} of {count}")
    else:
        ids = np.arange(count, dtype=np.int64)
    if mode == 4:
        return ids[:len(ids) // 3 * 3].reshape(-1, 3)
    k = np.arange(max(len(ids) - 2, 0))
    if mode == 5:
        return np.column_stack([ids[k], ids[k + 1 + k % 2], ids[k + 2 - k % 2]])
    return np.column_stack([np.full(len(k), ids[0] if len(ids) else 0), ids[k + 1], ids[k + 2]])


def write_gltf(gltf, points):
    """The file's bytes with the POSITION accessors holding ``points``; every other byte as it was.

    Parameters
    ----------
    gltf : GltfData
    points : (n, 3) float
        New world positions, in the order of ``gltf.points``.

    Returns
    -------
    bytes
    """
    if gltf.refusal:
        raise GltfError(gltf.refusal)
    points = np.asarray(points, dtype=np.float64)
    if points.shape != gltf.points.shape:
        raise GltfError(f"{len(points)} points given for a file of {len(gltf.points)}")
    buffers = [bytearray(b) for b in gltf.buffers]
    bounds, changed = {}, set()
    for acc, local in _locals(gltf, points).items():
        buffer, bounds[acc] = _store(gltf.doc, buffers, acc, local)
        changed.add(buffer)
    text = gltf.text.decode("utf-8")
    edits = _bound_edits(text, bounds) + _uri_edits(gltf, text, buffers, changed)
    text = _splice(text, edits).encode("utf-8")
    if gltf.container == "gltf":
        return text
    return _glb_patched(gltf, text, buffers, changed)


def _locals(gltf, points):
    """{accessor: (count, 3) local positions}: world points through each inverse node transform, instances averaged."""
    sums, counts = {}, {}
    for s in gltf.slots:
        inverse = np.linalg.inv(s.matrix)
        local = points[s.where] @ inverse[:3, :3].T + inverse[:3, 3]
        sums[s.accessor] = sums.get(s.accessor, 0.0) + local
        counts[s.accessor] = counts.get(s.accessor, 0) + 1
    return {a: sums[a] / counts[a] for a in sums}


def _store(doc, buffers, index, local):
    """Write local positions into accessor ``index``'s bytes at its own type.

    Returns
    -------
    (buffer index, {"min": [3 JSON numbers], "max": [...]}) : the bounds as JSON text
    """
    acc = doc["accessors"][index]
    kind = acc["componentType"]
    dtype = np.dtype(_DTYPES[kind])
    stored = local
    if kind != 5126:
        info = np.iinfo(dtype)
        scale = _NORMALIZE[kind] if acc.get("normalized") else 1.0
        stored = np.clip(np.rint(local * scale), info.min, info.max)
    stored = stored.astype(dtype)
    view = doc["bufferViews"][acc["bufferView"]]
    stride = view.get("byteStride") or dtype.itemsize * 3
    start = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
    target = np.ndarray((len(stored), 3), dtype=dtype, buffer=buffers[view["buffer"]], offset=start,
                        strides=(stride, dtype.itemsize))
    target[...] = stored
    as_json = (lambda v: json.dumps(float(v))) if kind == 5126 else (lambda v: str(int(v)))
    return view["buffer"], {"min": [as_json(v) for v in stored.min(axis=0)],
                            "max": [as_json(v) for v in stored.max(axis=0)]}


# Byte spans in the JSON text.  The text was parsed whole before, so it is valid JSON: the scanner
# only steps over whitespace and punctuation and lets the decoder measure each value.
_DECODER = json.JSONDecoder()


def _skip(text, at):
    while text[at] in " \t\n\r":
        at += 1
    return at


def _members(text, at):
    """{key: (start, end)} of the value of each member of the JSON object at ``text[at]`` ('{').

    A key given twice keeps its last value, as the parser does.
    """
    out, at = {}, _skip(text, at + 1)
    while text[at] != "}":
        key, at = _DECODER.raw_decode(text, at)
        start = _skip(text, _skip(text, at) + 1)        # past the ':'
        _, end = _DECODER.raw_decode(text, start)
        out[key] = (start, end)
        at = _skip(text, end)
        if text[at] == ",":
            at = _skip(text, at + 1)
    return out


def _items(text, at):
    """[(start, end)] of each element of the JSON array at ``text[at]`` ('[')."""
    out, at = [], _skip(text, at + 1)
    while text[at] != "]":
        _, end = _DECODER.raw_decode(text, at)
        out.append((at, end))
        at = _skip(text, end)
        if text[at] == ",":
            at = _skip(text, at + 1)
    return out


def _element(text, key, index):
    """{key: (start, end)} of the members of object ``index`` of the top-level array ``key``."""
    top = _members(text, _skip(text, 0))
    return _members(text, _items(text, top[key][0])[index][0])


def _bound_edits(text, bounds):
    """(start, end, new text) of each number of the changed accessors' ``min`` and ``max``.

    Each number is replaced where it stands, the spacing between them kept; an
    array that does not hold three numbers is written again whole.
    """
    if not bounds:
        return []
    top = _members(text, _skip(text, 0))
    accessors = _items(text, top["accessors"][0])
    edits = []
    for acc, values in bounds.items():
        spans = _members(text, accessors[acc][0])
        for key in ("min", "max"):
            if key not in spans:
                continue
            start, end = spans[key]
            numbers = _items(text, start) if text[start] == "[" else []
            if len(numbers) == len(values[key]):
                edits += [(a, b, v) for (a, b), v in zip(numbers, values[key])]
            else:
                edits.append((start, end, "[" + ",".join(values[key]) + "]"))
    return edits


def _uri_edits(gltf, text, buffers, changed):
    """(start, end, new text) of the URI of each changed buffer that has one: its bytes as base64.

    A data URI keeps its own media type and its decoded length; a file
    beside the original becomes a data URI of its declared length.
    """
    edits = []
    for i in sorted(changed):
        spec = gltf.doc["buffers"][i]
        if "uri" not in spec:
            continue                                    # the GLB's BIN chunk
        start, end = _element(text, "buffers", i)["uri"]
        raw = text[start:end]
        if spec["uri"].startswith("data:"):
            data, prefix = bytes(buffers[i]), spec["uri"].split(",", 1)[0] + ","
        else:
            data, prefix = bytes(buffers[i][:int(spec["byteLength"])]), "data:application/octet-stream;base64,"
        comma = raw.find(",")
        if spec["uri"].startswith("data:") and comma > 0 and json.loads(raw[:comma + 1] + '"') == prefix:
            new = raw[:comma + 1] + base64.b64encode(data).decode("ascii") + '"'   # the prefix as spelled
        else:
            new = json.dumps(prefix + base64.b64encode(data).decode("ascii"))
        edits.append((start, end, new))
    return edits


def _splice(text, edits):
    """``text`` with each (start, end, new) span replaced; the spans do not overlap."""
    parts, at = [], 0
    for start, end, new in sorted(edits):
        parts += [text[at:start], new]
        at = end
    return "".join(parts + [text[at:]])


def _glb_patched(gltf, text, buffers, changed):
    """The original GLB with its JSON chunk replaced by ``text`` and its BIN chunk data by buffer 0.

    The JSON chunk keeps its trailing spaces while they keep it 4-byte
    aligned, else it is padded again with the fewest spaces; every chunk
    after it (headers, data, padding) is kept byte for byte but the BIN
    data's POSITION bytes.
    """
    if len(text) % 4:
        text = text.rstrip(b" ")
        text += b" " * (-len(text) % 4)
    source = gltf.source
    length = struct.unpack_from("<I", source, 12)[0]
    rest = bytearray(source[20 + length + (-length % 4):])
    if gltf.bin_at is not None:
        for i in changed:
            if "uri" not in gltf.doc["buffers"][i]:
                at = gltf.bin_at - (20 + length + (-length % 4))
                rest[at:at + len(buffers[i])] = buffers[i]
    body = struct.pack("<II", len(text), _JSON_CHUNK) + text + bytes(rest)
    return source[:8] + struct.pack("<I", 12 + len(body)) + body


def _glb(doc, buffers):
    """A new GLB's bytes: the JSON chunk (space padded), the BIN chunk (zero padded)."""
    text = json.dumps(doc, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), _JSON_CHUNK) + text
    if buffers and "uri" not in doc["buffers"][0]:
        blob = bytes(buffers[0])
        blob += b"\0" * (-len(blob) % 4)
        body += struct.pack("<II", len(blob), _BIN_CHUNK) + blob
    return _GLB_MAGIC + struct.pack("<II", 2, 12 + len(body)) + body


def glb_from_mesh(points, faces=None):
    """A new GLB holding one mesh: float32 positions (and uint32 triangles), one node, no transform.

    Parameters
    ----------
    points : (n, 3) float
    faces : (f, 3) int, optional
        Without faces the primitive is a point set (mode 0).

    Returns
    -------
    bytes
    """
    points = np.asarray(points, dtype="<f4")
    blob = points.tobytes()
    doc = {"asset": {"version": "2.0", "generator": "pointmark"}, "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0}], "buffers": [{"byteLength": 0}],
           "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": len(blob), "target": 34962}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": len(points), "type": "VEC3",
                          "min": points.min(axis=0).tolist(), "max": points.max(axis=0).tolist()}]}
    prim = {"attributes": {"POSITION": 0}, "mode": 0}
    if faces is not None and len(faces):
        index = np.asarray(faces, dtype="<u4").reshape(-1)
        doc["bufferViews"].append({"buffer": 0, "byteOffset": len(blob), "byteLength": index.nbytes,
                                   "target": 34963})
        doc["accessors"].append({"bufferView": 1, "componentType": 5125, "count": len(index), "type": "SCALAR"})
        blob += index.tobytes()
        prim = {"attributes": {"POSITION": 0}, "indices": 1, "mode": 4}
    doc["meshes"] = [{"primitives": [prim]}]
    doc["buffers"][0]["byteLength"] = len(blob)
    return _glb(doc, [bytearray(blob)])


def glb_from_points(points):
    """A new GLB of bare points (mode 0), float32."""
    return glb_from_mesh(points)
