"""glTF 2.0 (``.gltf``) and GLB (``.glb``): world-space vertex positions, written back in place.

The point set is every mesh primitive's POSITION data in world space: node
transforms applied, an accessor reached by several nodes (an instanced mesh)
counted once in its first node's frame, and vertices at the same world
position (the copies a UV seam or a shared accessor makes; across frames,
within their float32 rounding) counted once, so a seam never cracks open.  Skinned meshes
give their bind pose (the node transform is ignored, as the spec says);
morph-target deltas are not applied and are written back unchanged.

Writing changes only the bytes of the POSITION accessors and their ``min``
and ``max``: each point's new world position goes back through the inverse
node transform of its accessor's first node (the other instances move with
it), and the values are stored in the accessor's own
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
byte for byte; so are originals whose buffers lie in other files (their
digest would not cover them).  Every index, count and size is checked
before it is used (docs/formats.md, "Hostile files").
"""

from __future__ import annotations

import base64
import json
import os
import re
import stat
import struct
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import unquote

import numpy as np

__all__ = ["GltfData", "GltfError", "read_gltf", "write_gltf", "check_head", "glb_from_points", "glb_from_mesh",
           "gltf_from_points", "REFUSED"]

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
    where: np.ndarray = None    # (count,) int64 index of each vertex in the point set; None: a later instance


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
    budget: int = 0                               # values the file may still expand to

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
        Refuse, before any work, a file that cannot be written back (:data:`REFUSED`) or whose
        buffers lie in other files (its identity is the digest of its own bytes).

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
    specs = _array(doc, "buffers")
    if original:
        for i, spec in enumerate(specs):
            uri = spec.get("uri")
            if isinstance(uri, str) and not uri.startswith("data:"):
                raise GltfError(f"buffer {i} lies in another file ({uri[:60]!r}), which the original's digest "
                                f"would not cover; pack it as .glb or embed the buffers "
                                f"(gltf-transform copy in.gltf out.glb)")
    gltf.buffers = [_buffer(gltf, i, b, blob) for i, b in enumerate(specs)]
    gltf.budget = _EXPANSION * max(len(raw) + sum(len(b) for b in gltf.buffers), 1)
    gltf.refusal = _refusal(doc)
    if original and gltf.refusal:
        raise GltfError(gltf.refusal)
    _collect(gltf, original=original)
    return gltf


# Values a file may expand to (zero-filled accessors, decoded meshopt and Draco data, indices of
# primitives that share an accessor), per byte of the file and its buffers: beyond is refused.
_EXPANSION = 64


def _spend(gltf, n, what):
    """Count ``n`` values against the file's budget; refuse a file that would expand beyond it."""
    gltf.budget -= int(n)
    if gltf.budget < 0:
        raise GltfError(f"{what} would expand the file beyond {_EXPANSION} values per stored byte "
                        f"(a corrupt count or a hostile file)")


def _array(doc, key):
    """The top-level array ``key`` of the JSON (empty when absent), each element an object."""
    value = doc.get(key, [])
    if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
        raise GltfError(f"'{key}' must be an array of objects")
    return value


def _index(doc, key, value, what):
    """``value`` checked as an index into the top-level array ``key``: an int in range."""
    items = _array(doc, key)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < len(items):
        raise GltfError(f"{what} is {str(value)[:20]!r}, not an index of the {len(items)} {key}")
    return value


def _whole(spec, key, what, default=None, low=0):
    """A non-negative integer member of a JSON object (``default`` when absent)."""
    value = spec.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise GltfError(f"{what} {key} is {str(value)[:20]!r}, not an integer >= {low}")
    return value


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
    except RecursionError:
        raise GltfError("invalid glTF JSON: nested too deep") from None
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise GltfError(f"invalid glTF JSON: {' '.join(str(exc).split())[:160]}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("asset"), dict) \
            or not str(doc["asset"].get("version", "")).startswith("2"):
        raise GltfError("not a glTF 2.0 file (asset.version must be 2.x)")
    return doc


def _buffer(gltf, index, spec, blob):
    """Bytes of buffer ``index``: the GLB BIN chunk, a data URI or a file beside the glTF."""
    uri, length = spec.get("uri"), _whole(spec, "byteLength", f"buffer {index}:", low=1)
    ext = spec.get("extensions", {})
    if uri is None and isinstance(ext, dict) and isinstance(ext.get(MESHOPT), dict) and ext[MESHOPT].get("fallback"):
        return b""                      # meshopt's placeholder: every view on it is compressed
    if uri is None:
        if blob is None:
            raise GltfError(f"buffer {index} has no uri and the file no BIN chunk")
        data = blob
    elif not isinstance(uri, str):
        raise GltfError(f"buffer {index}: its uri is not a string")
    elif uri.startswith("data:"):
        try:
            data = base64.b64decode(uri.split(",", 1)[1], validate=True)
        except (ValueError, IndexError):
            raise GltfError(f"buffer {index}: its data URI is not base64") from None
    else:
        data = _external(gltf, index, uri, length)
    if len(data) < length:
        raise GltfError(f"buffer {index} declares {length} bytes, holds {len(data)}")
    return bytes(data)


def _external(gltf, index, uri, length):
    """The first ``length`` bytes of the regular file a relative URI names inside the glTF's own folder.

    An absolute path, a scheme, a ``..`` or a link that leaves the folder,
    and anything but a regular file (a FIFO, a device) are refused; the file
    is opened without blocking and checked on its descriptor.
    """
    name = unquote(uri)
    where = f"buffer {index}: {uri[:60]!r}"
    if "\0" in name or os.path.isabs(name) or re.match(r"^[A-Za-z][A-Za-z0-9+.-]*:", name):
        raise GltfError(f"{where} is not a relative path inside the file's folder")
    folder = os.path.realpath(gltf.base)
    target = os.path.realpath(os.path.join(folder, name))
    if os.path.commonpath([folder, target]) != folder or target == folder:
        raise GltfError(f"{where} leaves the file's folder (through '..' or a link)")
    try:
        if not stat.S_ISREG(os.stat(target).st_mode):
            raise GltfError(f"{where} is not a regular file (a folder, FIFO or device)")
        fd = os.open(target, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise GltfError(f"{where} is not a regular file (a folder, FIFO or device)")
            os.set_blocking(fd, True)
            data = f.read(length)
    except OSError as exc:
        raise GltfError(f"{where}: cannot read: {os.strerror(exc.errno or 0).lower()}") from None
    if len(data) < length:
        raise GltfError(f"{where} holds {len(data)} bytes, the buffer declares {length}")
    return data


def _refusal(doc):
    """Why the file cannot be written back byte for byte, or None."""
    used = doc.get("extensionsUsed", [])
    for name in (DRACO, MESHOPT, "KHR_meshopt_compression"):
        if isinstance(used, list) and name in used:
            return f"{name}: {REFUSED.get(name, REFUSED[MESHOPT])}"
    for m, mesh in enumerate(_array(doc, "meshes")):
        for prim in _primitives(mesh, m):
            if "POSITION" in prim["attributes"]:
                acc = _array(doc, "accessors")[_index(doc, "accessors", prim["attributes"]["POSITION"],
                                                      f"mesh {m}: POSITION")]
                if "sparse" in acc or "bufferView" not in acc:
                    return "a sparse POSITION accessor cannot be written back in place; make it dense first"
    return None


def _primitives(mesh, m):
    """A mesh's primitives, each an object with an ``attributes`` object."""
    prims = mesh.get("primitives", [])
    if not isinstance(prims, list) or not all(isinstance(p, dict) and isinstance(p.get("attributes", {}), dict)
                                              for p in prims):
        raise GltfError(f"mesh {m}: 'primitives' must be an array of objects with attributes")
    for prim in prims:
        prim.setdefault("attributes", {})
    return prims


def _collect(gltf, *, original=False):
    """Slots, distinct world points and triangles of every primitive reached from a root node.

    Each POSITION accessor is counted once, in the world frame of the first
    node that reaches it (its primary slot); later instances are the same
    data moved and add no point.
    """
    doc = gltf.doc
    slots, triangles, primary = {}, [], {}
    accessors, meshes = _array(doc, "accessors"), _array(doc, "meshes")
    for node, matrix in _walk(doc):
        m = _index(doc, "meshes", doc["nodes"][node]["mesh"], f"node {node}: mesh")
        for prim in _primitives(meshes[m], m):
            acc = prim["attributes"].get("POSITION")
            if acc is None:
                continue
            acc = _index(doc, "accessors", acc, f"mesh {m}: POSITION")
            if accessors[acc].get("type") != "VEC3":
                raise GltfError(f"accessor {acc}: a POSITION accessor must be VEC3, not {accessors[acc].get('type')!r}")
            slot = slots.setdefault((acc, node), _Slot(acc, matrix))
            if primary.setdefault(acc, slot) is not slot:
                continue                                # a later instance: the same data moved
            count = _whole(accessors[acc], "count", f"accessor {acc}:")
            triangles.append((slot, _triangles(gltf, prim, count)))
    if not slots:
        raise GltfError("no mesh primitive with POSITION data is reached from a node")
    gltf.slots = list(slots.values())
    firsts = list(primary.values())
    for s in firsts:
        if original and not np.linalg.cond(s.matrix[:3, :3]) < 1e12:
            raise GltfError(f"accessor {s.accessor}: its node's transform is singular (a zero scale), "
                            f"so marked positions cannot be written back")
    locals_ = [_accessor(gltf, s.accessor) for s in firsts]
    with np.errstate(all="ignore"):            # an overflow is refused as non-finite points
        worlds = [v @ s.matrix[:3, :3].T + s.matrix[:3, 3] for s, v in zip(firsts, locals_)]
    points, inverse = _merged(gltf, firsts, locals_, worlds)
    bounds = np.cumsum([0] + [len(w) for w in worlds])
    for s, a, b in zip(firsts, bounds[:-1], bounds[1:]):
        s.where = inverse[a:b]
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


def _rounding(gltf, slot, local, world):
    """(count,) bound on how far storing a vertex in its accessor's type moves its world position."""
    acc = gltf.doc["accessors"][slot.accessor]
    linear = np.linalg.norm(slot.matrix[:3, :3])          # Frobenius: bounds the operator norm
    if acc.get("componentType") == 5126:
        step = np.linalg.norm(local, axis=1) * 2.0**-24 + 2.0**-140
    else:
        scale = _NORMALIZE.get(acc.get("componentType"), 1.0) if acc.get("normalized") else 1.0
        step = np.full(len(local), 0.5 * np.sqrt(3) / scale)
    arithmetic = (np.linalg.norm(world, axis=1) + np.linalg.norm(slot.matrix[:3, 3])) * 2.0**-48
    return linear * step + arithmetic


def _merged(gltf, slots, locals_, worlds):
    """Distinct world points of the slots' vertices and each vertex's index among them.

    Vertices at the same world position are one point; across frames (slots
    whose transforms differ), vertices whose positions agree within what
    storing them in their own frames can move them (float32 rounding, a
    quantized accessor's step; twice that bound) are one point too: the
    writer gives them one marked position, which each frame rounds its own
    way, and the copy merges them again.
    """
    every = np.concatenate(worlds)
    points, inverse = _first_occurrences(every)
    frames = {}
    frame = np.concatenate([np.full(len(w), frames.setdefault(s.matrix.tobytes(), len(frames)))
                            for s, w in zip(slots, worlds)])
    if len(frames) < 2:
        return points, inverse
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    slack = np.concatenate([_rounding(gltf, s, v, w) for s, v, w in zip(slots, locals_, worlds)])
    tau = np.zeros(len(points))
    np.maximum.at(tau, inverse, slack)
    first = np.full(len(points), len(every))
    np.minimum.at(first, inverse, np.arange(len(every)))
    home = frame[first]
    pairs = cKDTree(points).query_pairs(r=4 * float(tau.max()), output_type="ndarray")
    if len(pairs):
        a, b = pairs[:, 0], pairs[:, 1]
        close = np.linalg.norm(points[a] - points[b], axis=1) <= 2 * (tau[a] + tau[b])
        pairs = pairs[close & (home[a] != home[b])]
    if not len(pairs):
        return points, inverse
    n = len(points)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    _, lead, group = np.unique(labels, return_index=True, return_inverse=True)
    rank = np.empty(len(lead), dtype=np.int64)
    order = np.argsort(lead)
    rank[order] = np.arange(len(lead))
    return points[lead[order]], rank[np.asarray(group).reshape(-1)][inverse]


def _walk(doc):
    """(node index, (4, 4) world matrix) of each node holding a mesh, from every root.

    Every index is checked; a node that is the child of two parents, or
    that only a cycle of children reaches, is refused.
    """
    nodes = _array(doc, "nodes")
    parent_of = {}
    for i, node in enumerate(nodes):
        children = node.get("children", [])
        if not isinstance(children, list):
            raise GltfError(f"node {i}: 'children' must be an array")
        for c in children:
            _index(doc, "nodes", c, f"node {i}: child")
            if c in parent_of or c == i:
                raise GltfError(f"node {c} is reached twice (a cycle or a shared child)")
            parent_of[c] = i
    stack = [(i, np.eye(4)) for i in reversed(range(len(nodes))) if i not in parent_of][::-1]
    visited = set()
    out = []
    while stack:
        index, parent = stack.pop()
        visited.add(index)
        node = nodes[index]
        world = parent @ _local(node, index)
        if not np.isfinite(world).all():
            raise GltfError(f"node {index}: its world transform is not finite")
        if "mesh" in node:
            out.append((index, np.eye(4) if "skin" in node else world))     # skins: the bind pose
        stack.extend((c, world) for c in node.get("children", []))
    if len(visited) < len(nodes):
        lost = min(set(range(len(nodes))) - visited)
        raise GltfError(f"node {lost} is part of a cycle of children (no root reaches it)")
    return out


def _numbers(node, key, n, default, index):
    value = node.get(key, default)
    if not isinstance(value, (list, tuple)) or len(value) != n or \
            not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise GltfError(f"node {index}: '{key}' must be {n} numbers")
    value = np.asarray(value, dtype=np.float64)
    if not np.isfinite(value).all():
        raise GltfError(f"node {index}: '{key}' holds a non-finite number")
    return value


def _local(node, index=0):
    """A node's (4, 4) local matrix: ``matrix`` (column-major) or T @ R @ S."""
    if "matrix" in node:
        return _numbers(node, "matrix", 16, None, index).reshape(4, 4).T
    x, y, z, w = _numbers(node, "rotation", 4, (0.0, 0.0, 0.0, 1.0), index)
    rotation = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    out = np.eye(4)
    with np.errstate(all="ignore"):
        out[:3, :3] = rotation * _numbers(node, "scale", 3, (1.0, 1.0, 1.0), index)
    out[:3, 3] = _numbers(node, "translation", 3, (0.0, 0.0, 0.0), index)
    return out


def _accessor(gltf, index, *, draco=None):
    """(count, width) float64 values of an accessor (normalized integers scaled to [-1, 1] or [0, 1])."""
    acc = _array(gltf.doc, "accessors")[index]
    width, kind = _WIDTH.get(acc.get("type"), 0), acc.get("componentType")
    if kind not in _DTYPES or not width:
        raise GltfError(f"accessor {index}: component type {kind} / type {acc.get('type')} not supported")
    count = _whole(acc, "count", f"accessor {index}:")
    _spend(gltf, count * width, f"accessor {index} ({count} x {width} values)")
    decoded = _draco_values(gltf, index)
    if decoded is not None:
        if decoded.shape[0] != count:
            raise GltfError(f"accessor {index} declares {count} elements, its Draco data decodes to {len(decoded)}")
        values = decoded
    elif "bufferView" in acc:
        values = _strided(gltf, acc, index, width).astype(np.float64)
    else:
        values = np.zeros((count, width))
    if "sparse" in acc:
        values = _sparse(gltf, acc, values, index)
    if acc.get("normalized") and kind in _NORMALIZE:
        values = np.maximum(values / _NORMALIZE[kind], -1.0)
    return values


def _strided(gltf, acc, index, width):
    """(count, width) stored values of an accessor, read through its buffer view's stride."""
    dtype = np.dtype(_DTYPES[acc["componentType"]])
    what = f"accessor {index}:"
    view, data = _view(gltf, _index(gltf.doc, "bufferViews", acc["bufferView"], f"accessor {index}: bufferView"))
    stride = _whole(view, "byteStride", what, 0) or dtype.itemsize * width
    if stride < dtype.itemsize * width or stride > 252 and "byteStride" in view:
        raise GltfError(f"accessor {index}: a byte stride of {stride} does not hold {width} x {dtype.itemsize} bytes")
    start, count = _whole(acc, "byteOffset", what, 0), _whole(acc, "count", what)
    need = start + (count - 1) * stride + dtype.itemsize * width if count else 0
    if need > len(data):
        raise GltfError(f"accessor {index} reaches byte {need} of a {len(data)}-byte buffer view")
    return np.ndarray((count, width), dtype=dtype, buffer=data, offset=start, strides=(stride, dtype.itemsize))


def _view(gltf, index):
    """(view JSON, its bytes): meshopt-decoded when compressed."""
    view = _array(gltf.doc, "bufferViews")[index]
    if index in gltf.views:
        return view, gltf.views[index]
    exts = view.get("extensions", {}) if isinstance(view.get("extensions", {}), dict) else {}
    ext = exts.get(MESHOPT) or exts.get("KHR_meshopt_compression")
    length = _whole(view, "byteLength", f"buffer view {index}:", low=1)
    if isinstance(ext, dict):
        gltf.views[index] = _meshopt(gltf, ext, length, index)
        return view, gltf.views[index]
    buffer = gltf.buffers[_index(gltf.doc, "buffers", view.get("buffer"), f"buffer view {index}: buffer")]
    start = _whole(view, "byteOffset", f"buffer view {index}:", 0)
    if start + length > len(buffer):
        raise GltfError(f"buffer view {index} reaches byte {start + length} of a {len(buffer)}-byte buffer")
    return view, memoryview(buffer)[start:start + length]


def _meshopt(gltf, ext, length, index):
    """A meshopt-compressed buffer view's bytes, decoded (vertex, index and sequence modes, filters)."""
    import meshoptimizer as mo

    what = f"buffer view {index}: meshopt"
    source = gltf.buffers[_index(gltf.doc, "buffers", ext.get("buffer"), f"{what} buffer")]
    start = _whole(ext, "byteOffset", what, 0)
    data = bytes(source[start:start + _whole(ext, "byteLength", what)])
    count, stride, mode = _whole(ext, "count", what), _whole(ext, "byteStride", what, low=1), ext.get("mode", "ATTRIBUTES")
    if mode not in ("ATTRIBUTES", "TRIANGLES", "INDICES") or mode != "ATTRIBUTES" and stride not in (2, 4) \
            or mode == "ATTRIBUTES" and (stride % 4 or stride > 256):
        raise GltfError(f"{what} mode {str(mode)[:20]!r} with a stride of {stride} is not valid")
    if length > count * stride:
        raise GltfError(f"{what}: the view declares {length} bytes, its {count} x {stride} decoded bytes are fewer")
    _spend(gltf, count * max(stride, 4) // 4, f"{what} ({count} x {stride} bytes)")
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
    except (ValueError, RuntimeError, TypeError) as exc:
        raise GltfError(f"cannot decode meshopt data: {exc}") from None
    out = np.ascontiguousarray(out)
    if mode != "ATTRIBUTES":
        out = out.astype({2: "<u2", 4: "<u4"}[stride])
    return out.tobytes()[:length].ljust(length, b"\0")


def _sparse(gltf, acc, values, index):
    sparse = acc["sparse"]
    what = f"accessor {index}: sparse"
    if not isinstance(sparse, dict) or not isinstance(sparse.get("indices"), dict) \
            or not isinstance(sparse.get("values"), dict):
        raise GltfError(f"{what} must hold indices and values objects")
    idx_spec, val_spec = sparse["indices"], sparse["values"]
    n = _whole(sparse, "count", what, low=1)
    if n > len(values) or idx_spec.get("componentType") not in (5121, 5123, 5125):
        raise GltfError(f"{what}: {n} indices of type {idx_spec.get('componentType')} for {len(values)} elements")
    idx = _strided(gltf, {"componentType": idx_spec["componentType"], "bufferView": idx_spec.get("bufferView"),
                          "byteOffset": idx_spec.get("byteOffset", 0), "count": n}, index, 1)[:, 0]
    width = values.shape[1]
    new = _strided(gltf, {"componentType": acc["componentType"], "bufferView": val_spec.get("bufferView"),
                          "byteOffset": val_spec.get("byteOffset", 0), "count": n}, index, width)
    if len(idx) and idx.max() >= len(values):
        raise GltfError("a sparse accessor's index lies beyond its count")
    values = values.copy()
    values[idx.astype(np.int64)] = new
    return values


def _draco_values(gltf, index):
    """Stored values of a Draco-compressed accessor (decoded once per primitive), or None."""
    cache = gltf.views.setdefault("draco", {})
    used = gltf.doc.get("extensionsUsed", [])
    if not cache and isinstance(used, list) and DRACO in used:
        cache["decoded"] = True
        _decode_draco(gltf, cache)
    return cache.get(index)


def _decode_draco(gltf, cache):
    import DracoPy

    for m, mesh in enumerate(_array(gltf.doc, "meshes")):
        for prim in _primitives(mesh, m):
            ext = prim.get("extensions", {}).get(DRACO) if isinstance(prim.get("extensions", {}), dict) else None
            if not isinstance(ext, dict):
                continue
            _, data = _view(gltf, _index(gltf.doc, "bufferViews", ext.get("bufferView"), f"mesh {m}: Draco bufferView"))
            try:
                decoded = DracoPy.decode(bytes(data))
            except Exception as exc:    # DracoPy raises its own error types
                raise GltfError(f"cannot decode Draco data: {exc}") from None
            points = np.asarray(decoded.points, dtype=np.float64).reshape(-1, 3)
            faces = np.asarray(getattr(decoded, "faces", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 1)
            _spend(gltf, points.size + faces.size, f"mesh {m}'s Draco data")
            if "POSITION" in prim["attributes"]:
                cache[prim["attributes"]["POSITION"]] = points
            if "indices" in prim:
                cache[prim["indices"]] = faces


def _triangles(gltf, prim, count):
    """(t, 3) int64 vertex indices of a primitive's triangles (strips and fans unrolled)."""
    mode = prim.get("mode", 4)
    if mode not in (4, 5, 6):
        return np.zeros((0, 3), dtype=np.int64)
    if "indices" in prim:
        index = _index(gltf.doc, "accessors", prim["indices"], "a primitive's indices")
        acc = gltf.doc["accessors"][index]
        if acc.get("type") != "SCALAR" or acc.get("componentType") not in (5121, 5123, 5125):
            raise GltfError(f"accessor {index}: indices must be SCALAR unsigned integers")
        ids = _accessor(gltf, index)[:, 0].astype(np.int64)
        if len(ids) and (ids.min() < 0 or ids.max() >= count):
            raise GltfError(f"primitive indices reach vertex {int(ids.max())} of {count}")
    else:
        ids = np.arange(count, dtype=np.int64)
    _spend(gltf, 3 * len(ids), "a primitive's triangles")
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
    """{accessor: (count, 3) local positions}: world points through its primary slot's inverse transform.

    An accessor reached by several nodes (an instanced mesh) is counted once,
    in its first node's frame; the other instances move with it.
    """
    out = {}
    for s in gltf.slots:
        if s.where is None:
            continue
        inverse = np.linalg.inv(s.matrix)
        out[s.accessor] = points[s.where] @ inverse[:3, :3].T + inverse[:3, 3]
    return out


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


def _mesh_doc(points, faces=None):
    """(doc, blob) of a new glTF holding one mesh: float32 positions (and uint32 triangles), one node."""
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
    return doc, blob


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
    doc, blob = _mesh_doc(points, faces)
    return _glb(doc, [bytearray(blob)])


def glb_from_points(points):
    """A new GLB of bare points (mode 0), float32."""
    return glb_from_mesh(points)


def gltf_from_points(points, faces=None):
    """A new ``.gltf`` (JSON text) of bare points (mode 0, or triangles), float32, its buffer a base64 data URI."""
    doc, blob = _mesh_doc(points, faces)
    doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(blob).decode("ascii")
    return json.dumps(doc, separators=(",", ":")).encode("utf-8")
