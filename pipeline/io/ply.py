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
        with np.errstate(invalid="ignore"):   # a signalling NaN stays a NaN; the caller refuses it
            return np.column_stack([self.vertices[a].astype(np.float64) for a in "xyz"])

    def faces(self):
        """(f, 3) int triangles, decoded from the element ``face`` (if any)."""
        return _decode_faces(self)


def read_ply(data):
    """Parse PLY bytes.

    The body must match the header exactly: a vertex count, element count or
    list length that disagrees with the data is an error, never a guess
    (fewer or more records than declared, bytes or lines left over).

    Parameters
    ----------
    data : bytes

    Returns
    -------
    PlyData
    """
    if not data.startswith(b"ply"):
        raise PlyError("not a PLY file (no 'ply' magic or no 'end_header')")
    body_start = _end_of_header(data)
    # latin-1 maps every byte to one character: the header is written back byte for byte
    header = [line.removesuffix("\r") for line in data[:body_start].decode("latin-1").split("\n")]
    header = header[:-1] if header and header[-1] == "" else header
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
        _check_ascii_tail(tail, count, elements[1:])
    else:
        dtype = np.dtype([(p, _FORMATS[fmt] + t) for p, _, t in props])
        need = dtype.itemsize * count
        if len(body) < need:
            raise PlyError(
                f"truncated: {count} vertices need {need} bytes, the file has {len(body)} after the header"
            )
        vertices = np.frombuffer(body, dtype=dtype, count=count).copy()
        tail = body[need:]
        _check_binary_tail(tail, count, dtype.itemsize, elements[1:], _FORMATS[fmt])
    return PlyData(vertices, header, fmt, tail, elements)


def _end_of_header(data):
    """Offset of the first body byte: just after the line that is exactly ``end_header``."""
    start = 0
    while True:
        at = data.find(b"end_header", start)
        if at < 0:
            raise PlyError("not a PLY file (no 'ply' magic or no 'end_header')")
        nl = data.find(b"\n", at)
        line_start = data.rfind(b"\n", 0, at) + 1
        line = data[line_start: len(data) if nl < 0 else nl]
        if line.strip() == b"end_header" and line_start > 0:
            return len(data) if nl < 0 else nl + 1
        start = at + 1

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
    head = ("\n".join(ply.header) + "\n").encode("latin-1")
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
            if len(words) != 3 or not (words[2].isascii() and words[2].isdigit()):
                raise PlyError(f"bad element line {line!r}")
            if any(words[1] == e[0] for e in elements):
                raise PlyError(f"element {words[1]!r} is declared twice")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PlyError(f"property before any element: {line!r}")
            prop = _parse_property(words, line)
            if any(prop[0] == q[0] for q in elements[-1][2]):
                raise PlyError(f"property {prop[0]!r} is declared twice in element {elements[-1][0]!r}")
            elements[-1][2].append(prop)
        else:
            raise PlyError(f"unexpected header line {line!r}")
    if fmt is None:
        raise PlyError("no 'format' line in the header")
    return fmt, elements


def _parse_property(words, line):
    if len(words) == 5 and words[1] == "list":
        if words[2] not in _TYPES or words[3] not in _TYPES:
            raise PlyError(f"unknown type in {line!r}")
        if _TYPES[words[2]][0] not in "iu":
            raise PlyError(f"the length of a list must have an integer type: {line!r}")
        return (words[4], "list", (_TYPES[words[2]], _TYPES[words[3]]))
    if len(words) != 3 or words[1] not in _TYPES:
        raise PlyError(f"bad property line {line!r}")
    return (words[2], "scalar", _TYPES[words[1]])


def _read_ascii_vertices(body, count, props):
    lines = body.split(b"\n")
    if len(lines) < count or (count and not lines[count - 1].strip()):
        raise PlyError(f"truncated: the header declares {count} vertices, fewer lines follow")
    dtype = np.dtype([(p, t) for p, _, t in props])
    rows = lines[:count]
    for i, row in enumerate(rows):
        if len(row.split()) != len(props):
            raise PlyError(f"vertex line {i + 1} has {len(row.split())} values, the header declares "
                           f"{len(props)} properties")
    try:
        table = np.loadtxt(rows, dtype=np.float64, ndmin=2, comments=None) if count else \
            np.zeros((0, len(props)))
    except ValueError as exc:
        raise PlyError(f"bad vertex line: {exc}") from None
    if table.shape != (count, len(props)):
        raise PlyError(f"vertex lines have {table.shape[1]} values, the header declares {len(props)}")
    vertices = np.empty(count, dtype=dtype)
    for i, (p, _, t) in enumerate(props):
        column = table[:, i]
        _check_ascii_range(p, column, np.dtype(t))
        vertices[p] = column
    tail = b"\n".join(lines[count:])
    return vertices, tail


def _check_ascii_range(name, column, dtype):
    """Values of an ASCII column must be representable in the declared type."""
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        bad = ~np.isfinite(column) | (column != np.round(column)) | (column < info.min) | (column > info.max)
        what = f"an integer in [{info.min}, {info.max}]"
    else:
        limit = np.finfo(dtype).max
        bad = np.isfinite(column) & (np.abs(column) > limit)
        what = f"within the range of {dtype.name}"
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise PlyError(f"vertex {i}: property {name!r} is {column[i]!r}, not {what}")


def _check_ascii_tail(tail, n_vertices, elements):
    """The lines after the vertices must hold exactly the declared records."""
    lines = [line for line in tail.split(b"\n") if line.strip()]
    declared = sum(count for _, count, _ in elements)
    if len(lines) != declared:
        if not elements:
            raise PlyError(f"the header declares {n_vertices} vertices, the body holds "
                           f"{n_vertices + len(lines)} lines of data")
        raise PlyError(f"after the {n_vertices} vertices the header declares {declared} records "
                       f"({', '.join(f'{c} {n}' for n, c, _ in elements)}), the body holds {len(lines)} lines")
    at = 0
    for name, count, props in elements:
        for k, line in enumerate(lines[at: at + count]):
            words = line.split()
            need = 0
            for _, kind, _ in props:
                if kind == "list":
                    try:
                        length = int(words[need])
                    except (IndexError, ValueError):
                        length = -1
                    if length < 0:
                        raise PlyError(f"{name} {k}: bad list length in {line[:80]!r}")
                    need += 1 + length
                else:
                    need += 1
            if need != len(words):
                raise PlyError(f"{name} {k}: {len(words)} values, the header declares {need}")
        at += count


def _check_binary_tail(tail, n_vertices, vertex_size, elements, endian):
    """The bytes after the vertices must hold exactly the declared records (no more, no less)."""
    at = 0
    for name, count, props in elements:
        at = _skip_binary_element(tail, at, name, count, props, endian)
    if at != len(tail):
        extra = len(tail) - at
        if not elements and extra % vertex_size == 0:
            raise PlyError(f"the header declares {n_vertices} vertices, the body holds "
                           f"{n_vertices + extra // vertex_size}")
        raise PlyError(f"{extra} bytes follow the records the header declares "
                       f"({n_vertices} vertices{''.join(f', {c} {n}' for n, c, _ in elements)})")


def _skip_binary_element(tail, at, name, count, props, endian):
    """Offset just after ``count`` records of an element starting at ``at``."""
    left = len(tail) - at
    fixed = sum(np.dtype(t).itemsize if kind == "scalar" else np.dtype(t[0]).itemsize
                for _, kind, t in props)
    if count and fixed == 0:
        raise PlyError(f"element {name!r} has no properties")
    if count * fixed > left:
        raise PlyError(f"truncated: {count} {name} records need at least {count * fixed} bytes, "
                       f"{left} remain")
    if not any(kind == "list" for _, kind, _ in props):
        return at + count * fixed
    if count == 0:
        return at
    # Fast path: every list as long as in the first record (triangle meshes).
    layout, first = [], at
    for _, kind, t in props:
        if kind == "scalar":
            layout.append(np.dtype(endian + t).itemsize)
            first += layout[-1]
        else:
            if first + np.dtype(t[0]).itemsize > len(tail):
                raise PlyError(f"truncated {name} block")
            length = int(np.frombuffer(tail, dtype=endian + t[0], count=1, offset=first)[0])
            if length < 0:
                raise PlyError(f"{name} 0: negative list length {length}")
            layout.append((np.dtype(endian + t[0]), length * np.dtype(t[1]).itemsize))
            first += np.dtype(t[0]).itemsize + layout[-1][1]
    size = first - at
    if size * count <= left:
        fields, offset = [], 0
        for k, item in enumerate(layout):
            if isinstance(item, tuple):
                fields.append((f"n{k}", item[0], offset))
                offset += item[0].itemsize + item[1]
            else:
                offset += item
        block = np.frombuffer(tail, dtype=np.uint8, count=size * count, offset=at).reshape(count, size)
        same = True
        for (field, dt, off), item in zip(fields, [i for i in layout if isinstance(i, tuple)]):
            lengths = block[:, off: off + dt.itemsize].copy().view(dt).ravel()
            same &= bool((lengths.astype(np.int64) * 1 == lengths[0]).all())
        if same:
            return at + size * count
    # General path: one record at a time (bounded: each record takes at least one byte).
    for k in range(count):
        for _, kind, t in props:
            if kind == "scalar":
                at += np.dtype(t).itemsize
                continue
            dt = np.dtype(endian + t[0])
            if at + dt.itemsize > len(tail):
                raise PlyError(f"truncated: {name} {k} of {count} is cut off")
            length = int(np.frombuffer(tail, dtype=dt, count=1, offset=at)[0])
            if length < 0:
                raise PlyError(f"{name} {k}: negative list length {length}")
            at += dt.itemsize + length * np.dtype(t[1]).itemsize
        if at > len(tail):
            raise PlyError(f"truncated: {name} {k} of {count} is cut off")
    return at


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
