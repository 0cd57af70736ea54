"""PLY reading and writing that keeps every vertex property, its type and the point order.

ASCII and binary (little and big endian) files; float32 or float64
coordinates; any extra vertex properties (colour, intensity, normals) are
carried through untouched.  Elements after the vertices (faces) are kept as
raw bytes and written back verbatim; triangle faces can also be decoded for
mesh attacks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["PlyData", "read_ply", "write_ply", "PlyError"]

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


class PlyError(ValueError):
    """A PLY file that cannot be read (the message says why)."""


@dataclass
class PlyData:
    """A PLY file: vertex records plus what follows them.

    Attributes
    ----------
    vertices : (n,) structured array with at least x, y, z
    header : list of str
        Header lines, ``ply`` to ``end_header``.
    fmt : str
        ``ascii``, ``binary_little_endian`` or ``binary_big_endian``.
    tail : bytes
        Everything after the vertex block (faces, other elements), verbatim.
    elements : list of (name, count, properties)
    """

    vertices: np.ndarray
    header: list
    fmt: str
    tail: bytes = b""
    elements: list = field(default_factory=list)

    @property
    def points(self):
        """(n, 3) float64 coordinates."""
        return np.column_stack([self.vertices[a].astype(np.float64) for a in "xyz"])

    def faces(self):
        """(f, 3) int triangles, decoded from the element ``face`` (if any)."""
        return _decode_faces(self)


def read_ply(data):
    """Parse PLY bytes.

    Parameters
    ----------
    data : bytes

    Returns
    -------
    PlyData
    """
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise PlyError("not a PLY file (no 'ply' magic or no 'end_header')")
    nl = data.find(b"\n", end)
    body_start = len(data) if nl < 0 else nl + 1
    header = data[:body_start].decode("ascii", errors="replace").splitlines()
    fmt, elements = _parse_header(header)
    if not elements or elements[0][0] != "vertex":
        raise PlyError("the first element must be 'vertex'")
    name, count, props = elements[0]
    if any(kind == "list" for _, kind, _ in props):
        raise PlyError("list properties on vertices are not supported")
    names = [p for p, _, _ in props]
    if not {"x", "y", "z"} <= set(names):
        raise PlyError(f"vertex element lacks x, y or z (has {names})")
    body = data[body_start:]
    if fmt == "ascii":
        vertices, tail = _read_ascii_vertices(body, count, props)
    else:
        dtype = np.dtype([(p, _FORMATS[fmt] + t) for p, _, t in props])
        need = dtype.itemsize * count
        if len(body) < need:
            raise PlyError(
                f"truncated: {count} vertices need {need} bytes, the file has {len(body)} after the header"
            )
        vertices = np.frombuffer(body[:need], dtype=dtype).copy()
        tail = body[need:]
    return PlyData(vertices, header, fmt, tail, elements)


def write_ply(ply, points):
    """Serialise a PLY with new coordinates, everything else unchanged.

    Parameters
    ----------
    ply : PlyData
    points : (n, 3) float

    Returns
    -------
    bytes
    """
    vertices = ply.vertices.copy()
    for i, a in enumerate("xyz"):
        vertices[a] = points[:, i].astype(vertices.dtype[a])
    head = ("\n".join(ply.header) + "\n").encode("ascii")
    if ply.fmt == "ascii":
        body = _write_ascii_vertices(vertices)
    else:
        body = vertices.tobytes()
    return head + body + ply.tail


def _parse_header(lines):
    fmt = None
    elements = []
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info", "end_header"):
            continue
        if words[0] == "format":
            if len(words) < 2 or words[1] not in _FORMATS:
                raise PlyError(f"unknown PLY format line {line!r}")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PlyError(f"bad element line {line!r}")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PlyError(f"property before any element: {line!r}")
            elements[-1][2].append(_parse_property(words, line))
        else:
            raise PlyError(f"unexpected header line {line!r}")
    if fmt is None:
        raise PlyError("no 'format' line in the header")
    return fmt, elements


def _parse_property(words, line):
    if len(words) == 5 and words[1] == "list":
        if words[2] not in _TYPES or words[3] not in _TYPES:
            raise PlyError(f"unknown type in {line!r}")
        return (words[4], "list", (_TYPES[words[2]], _TYPES[words[3]]))
    if len(words) != 3 or words[1] not in _TYPES:
        raise PlyError(f"bad property line {line!r}")
    return (words[2], "scalar", _TYPES[words[1]])


def _read_ascii_vertices(body, count, props):
    lines = body.split(b"\n")
    if len(lines) < count or (count and not lines[count - 1].strip()):
        raise PlyError(f"truncated: the header declares {count} vertices, fewer lines follow")
    dtype = np.dtype([(p, t) for p, _, t in props])
    try:
        table = np.loadtxt(lines[:count], dtype=np.float64, ndmin=2)
    except ValueError as exc:
        raise PlyError(f"bad vertex line: {exc}") from None
    if table.shape != (count, len(props)):
        raise PlyError(f"vertex lines have {table.shape[1]} values, the header declares {len(props)}")
    vertices = np.empty(count, dtype=dtype)
    for i, (p, _, _) in enumerate(props):
        vertices[p] = table[:, i]
    tail = b"\n".join(lines[count:])
    return vertices, tail


def _write_ascii_vertices(vertices):
    cols = []
    for name in vertices.dtype.names:
        col = vertices[name]
        if col.dtype.kind == "f":
            cols.append(np.char.mod("%.17g" if col.dtype.itemsize == 8 else "%.9g", col))
        else:
            cols.append(col.astype(str))
    rows = [" ".join(r) for r in zip(*cols)]
    return ("\n".join(rows) + "\n").encode("ascii") if rows else b""


def _decode_faces(ply):
    if len(ply.elements) < 2 or ply.elements[1][0] != "face":
        return np.zeros((0, 3), dtype=np.int64)
    _, count, props = ply.elements[1]
    if len(props) != 1 or props[0][1] != "list":
        raise PlyError("only face elements with a single list property are supported")
    count_t, item_t = props[0][2]
    if ply.fmt == "ascii":
        rows = [list(map(int, r.split())) for r in ply.tail.strip().split(b"\n")[:count]]
        tri = [r[1:4] for r in rows if r and r[0] == 3]
        return np.asarray(tri, dtype=np.int64).reshape(-1, 3)
    e = _FORMATS[ply.fmt]
    dtype = np.dtype([("n", e + count_t), ("v", e + item_t, (3,))])
    if len(ply.tail) < dtype.itemsize * count:
        raise PlyError("truncated face block")
    faces = np.frombuffer(ply.tail[: dtype.itemsize * count], dtype=dtype)
    if not (faces["n"] == 3).all():
        raise PlyError("only triangle faces are supported")
    return faces["v"].astype(np.int64)
