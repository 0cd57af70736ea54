"""PLY reading and writing that keeps every vertex property, its type and the point order.

ASCII and binary (little and big endian) files; float32 or float64
coordinates; any extra vertex properties (colour, intensity, normals) are
carried through untouched.  Elements after the vertices (faces) are kept as
raw bytes and written back verbatim; triangle faces can also be decoded for
mesh attacks.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass, field

import numpy as np

from .text import describe_word

__all__ = ["PlyData", "read_ply", "write_ply", "PlyError", "check_head", "MAX_HEADER"]

MAX_HEADER = 1 << 20      # bytes; the header must end within them
_INDEX_NAMES = ("vertex_indices", "vertex_index")
_NAME = re.compile(r"[A-Za-z0-9_.:\-]{1,64}")     # element and property names (they appear in messages)

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
    body_start, header, fmt, elements = _header(data, len(data))
    count, props = elements[0][1], elements[0][2]
    body = memoryview(data)[body_start:]
    if fmt == "ascii":
        vertices, tail = _read_ascii_vertices(body, count, props)
        _check_ascii_tail(tail, count, elements[1:])
    else:
        dtype = np.dtype([(p, _FORMATS[fmt] + t) for p, _, t in props])
        need = dtype.itemsize * count
        vertices = np.frombuffer(body, dtype=dtype, count=count).copy()
        tail = bytes(body[need:])
        _check_binary_tail(tail, count, dtype.itemsize, elements[1:], _FORMATS[fmt])
    return PlyData(vertices, header, fmt, tail, elements)


def check_head(head, size):
    """Check a PLY's magic, header and declared sizes from its first bytes, before the body is read.

    Parameters
    ----------
    head : bytes
        The file's first bytes (at least :data:`MAX_HEADER` of them, or the whole file).
    size : int
        The file's length in bytes.

    Raises
    ------
    PlyError
        No ``ply`` magic, no ``end_header`` within :data:`MAX_HEADER` bytes, a
        bad header, or declared records that need more bytes than the file has.
    """
    _header(head, size)


def _header(data, size):
    """(body offset, header lines, format, elements), checked against a file of ``size`` bytes."""
    if not (data.startswith(b"ply\n") or data.startswith(b"ply\r\n")):
        raise PlyError("not a PLY file (it does not start with the line 'ply')")
    body_start = _end_of_header(data)
    # latin-1 maps every byte to one character: the header is written back byte for byte
    header = [line.removesuffix("\r") for line in bytes(data[:body_start]).decode("latin-1").split("\n")]
    header = header[:-1] if header and header[-1] == "" else header
    fmt, elements = _parse_header(header)
    if not elements or elements[0][0] != "vertex":
        raise PlyError("the first element must be 'vertex'")
    props = elements[0][2]
    if any(kind == "list" for _, kind, _ in props):
        raise PlyError("list properties on vertices are not supported")
    names = [p for p, _, _ in props]
    if not {"x", "y", "z"} <= set(names):
        raise PlyError(f"the vertex element lacks x, y or z (it has {len(names)} other properties)")
    _check_declared_size(fmt, elements, size - body_start)
    return body_start, header, fmt, elements


def _check_declared_size(fmt, elements, left):
    """Refuse declared counts whose smallest encoding needs more than the ``left`` body bytes.

    Binary: every scalar and list length at its size (exact for the vertices);
    ASCII: at least one digit and one separator per value.
    """
    need = 0
    for name, count, props in elements:
        if fmt == "ascii":
            per = 2 * len(props)
        else:
            per = sum(np.dtype(t if kind == "scalar" else t[0]).itemsize for _, kind, t in props)
        need += count * per
        if need > left:
            what = f"{count} {name} records" if name != "vertex" else f"{count} vertices"
            raise PlyError(f"truncated: the header declares {what}, which need at least {need} bytes "
                           f"({fmt}); the file holds {max(left, 0)} after the header")


def _end_of_header(data):
    """Offset of the first body byte: just after the line that is exactly ``end_header``."""
    start = 0
    data = bytes(data[:MAX_HEADER + 16])
    while True:
        at = data.find(b"end_header", start)
        if at < 0 or at > MAX_HEADER:
            raise PlyError(f"not a PLY file (no 'end_header' line within the first {MAX_HEADER} bytes)")
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
    """(format, [(name, count, properties)]); messages name the header line, never quote it."""
    fmt = None
    elements = []
    for n, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info", "end_header"):
            continue
        where = f"header line {n}"
        if words[0] == "format":
            if len(words) < 2 or words[1] not in _FORMATS:
                raise PlyError(f"{where}: unknown PLY format (ascii, binary_little_endian or binary_big_endian)")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not (words[2].isascii() and words[2].isdigit()):
                raise PlyError(f"{where}: bad element line (element NAME COUNT expected)")
            _check_name(words[1], where)
            if any(words[1] == e[0] for e in elements):
                raise PlyError(f"{where}: element {describe_word(words[1])} is declared twice")
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if not elements:
                raise PlyError(f"{where}: a property before any element")
            prop = _parse_property(words, where)
            _check_name(prop[0], where)
            if any(prop[0] == q[0] for q in elements[-1][2]):
                raise PlyError(f"{where}: property {describe_word(prop[0])} is declared twice in element "
                               f"{describe_word(elements[-1][0])}")
            elements[-1][2].append(prop)
        else:
            raise PlyError(f"{where}: not a PLY header line (format, element, property, comment or end_header)")
    if fmt is None:
        raise PlyError("no 'format' line in the header")
    return fmt, elements


def _check_name(name, where):
    if not _NAME.fullmatch(name):
        raise PlyError(f"{where}: an element or property name must be a plain word (letters, digits, _ . : -)")


def _parse_property(words, where):
    if len(words) == 5 and words[1] == "list":
        if words[2] not in _TYPES or words[3] not in _TYPES:
            raise PlyError(f"{where}: unknown type in a list property")
        if _TYPES[words[2]][0] not in "iu":
            raise PlyError(f"{where}: the length of a list must have an integer type")
        return (words[4], "list", (_TYPES[words[2]], _TYPES[words[3]]))
    if len(words) != 3 or words[1] not in _TYPES:
        raise PlyError(f"{where}: bad property line (property TYPE NAME, or property list TYPE TYPE NAME)")
    return (words[2], "scalar", _TYPES[words[1]])


def _read_ascii_vertices(body, count, props):
    """Vertex records from the first ``count`` lines of an ASCII body, parsed in C (no per-token lists).

    Returns
    -------
    vertices : (count,) structured array
    tail : bytes
        The body after the vertex lines.
    """
    end = _line_end(body, count)
    if end is None:
        raise PlyError(f"truncated: the header declares {count} vertices, fewer lines follow")
    dtype = np.dtype([(p, t) for p, _, t in props])
    table = _ascii_table(body[:end], np.float64, "vertex") if count else np.zeros((0, len(props)))
    if table.shape[0] != count:
        raise PlyError(f"the {count} vertex lines include {count - table.shape[0]} blank lines")
    if table.shape[1] != len(props):
        raise PlyError(f"vertex line 1 has {table.shape[1]} values, the header declares {len(props)} properties")
    vertices = np.empty(count, dtype=dtype)
    for i, (p, _, t) in enumerate(props):
        column = table[:, i]
        _check_ascii_range(p, column, np.dtype(t))
        vertices[p] = column
    return vertices, bytes(body[end:])


def _line_end(body, count, block=1 << 24):
    """Offset just after the ``count``-th line of ``body`` (its last line may lack a newline), or None."""
    if count == 0:
        return 0
    seen, start = 0, 0
    while start < len(body):
        chunk = np.frombuffer(body, dtype=np.uint8, count=min(block, len(body) - start), offset=start)
        ends = np.flatnonzero(chunk == 10)
        if seen + len(ends) >= count:
            return start + int(ends[count - seen - 1]) + 1
        seen, start = seen + len(ends), start + len(chunk)
    if seen == count - 1 and len(body) and body[-1] != 10:
        return len(body)
    return None


_COLUMNS = re.compile(r"columns changed from (\d+) to (\d+) at row (\d+)")
_CONVERT = re.compile(r"at row (\d+), column (\d+)")


def _ascii_table(block, dtype, what):
    """(rows, values) table of whitespace-separated numbers; blank lines skipped.

    Raises
    ------
    PlyError
        Naming the line (1-based within ``block``) and never quoting its text.
    """
    try:
        return np.loadtxt(io.BytesIO(bytes(block)), dtype=dtype, ndmin=2, comments=None)
    except ValueError as exc:
        text = str(exc)
        m = _COLUMNS.search(text)
        if m:
            raise PlyError(f"{what} line {m.group(3)} has {m.group(2)} values, the first has {m.group(1)}") from None
        m = _CONVERT.search(text)
        if m:
            kind = "an integer" if np.dtype(dtype).kind == "i" else "a number"
            raise PlyError(f"{what} line {int(m.group(1)) + 1}: value {m.group(2)} is not {kind}") from None
        raise PlyError(f"bad {what} lines") from None


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
    """The lines after the vertices must hold exactly the declared records; face indices name vertices."""
    declared = sum(count for _, count, _ in elements)
    if not tail.strip():
        if declared:
            raise PlyError(f"after the {n_vertices} vertices the header declares {declared} records "
                           f"({_listing(elements)}), the body holds none")
        return
    if len(elements) == 1 and _fixed_list_table(tail, n_vertices, elements[0]):
        return
    lines = _data_lines(tail)
    for name, count, props in elements:
        for k in range(count):
            line = next(lines, None)
            if line is None:
                raise PlyError(f"after the {n_vertices} vertices the header declares {declared} records "
                               f"({_listing(elements)}), the body holds fewer lines")
            _check_ascii_record(line.split(), name, k, props, n_vertices)
    extra = sum(1 for _ in lines)
    if extra:
        if not elements:
            raise PlyError(f"the header declares {n_vertices} vertices, the body holds "
                           f"{n_vertices + extra} lines of data")
        raise PlyError(f"after the {n_vertices} vertices the header declares {declared} records "
                       f"({_listing(elements)}), the body holds {declared + extra} lines")


def _listing(elements):
    return ", ".join(f"{c} {n}" for n, c, _ in elements)


def _data_lines(data):
    """The non-blank lines of ``data``, one at a time (no list of the whole body)."""
    start = 0
    while start < len(data):
        nl = data.find(b"\n", start)
        end = len(data) if nl < 0 else nl
        if data[start:end].strip():
            yield data[start:end]
        start = end + 1


def _check_ascii_record(words, name, k, props, n_vertices):
    need = 0
    for prop, kind, _ in props:
        if kind != "list":
            need += 1
            continue
        length = int(words[need]) if need < len(words) and words[need].isdigit() else -1
        if length < 0:
            raise PlyError(f"{name} {k}: bad list length (value {need + 1})")
        if _is_index(name, prop):
            _check_indices(words[need + 1: need + 1 + length], name, k, n_vertices)
        need += 1 + length
    if need != len(words):
        raise PlyError(f"{name} {k}: {len(words)} values, the header declares {need}")


def _is_index(element, prop):
    """Whether a list property holds vertex indices (checked against the vertex count)."""
    return element == "face" or prop in _INDEX_NAMES


def _check_indices(words, name, k, n_vertices):
    try:
        idx = np.asarray([int(w) for w in words], dtype=np.int64)
    except (ValueError, OverflowError):
        raise PlyError(f"{name} {k}: a vertex index is not an integer") from None
    _check_index_range(idx, name, k, n_vertices)


def _check_index_range(idx, name, k, n_vertices):
    """Refuse indices outside [0, n_vertices); ``k`` is the record (or None to find it in ``idx`` rows)."""
    bad = (idx < 0) | (idx >= n_vertices)
    if bad.any():
        at = np.argwhere(bad)[0]
        record = k if k is not None else int(at[0])
        value = int(idx[tuple(at)])
        raise PlyError(f"{name} {record}: vertex index {value} is outside the {n_vertices} vertices")


def _fixed_list_table(tail, n_vertices, element):
    """Fast path for one element of equal-length index lists (triangle meshes); False if it does not apply."""
    name, count, props = element
    if len(props) != 1 or props[0][1] != "list" or np.dtype(props[0][2][1]).kind not in "iu":
        return False
    try:
        table = _ascii_table(tail, np.int64, name)
    except PlyError as exc:
        if "values, the first has" in str(exc):
            return False       # lists of several lengths: the line-by-line path
        raise
    if table.shape[1] < 1 or (table[:, 0] != table.shape[1] - 1).any():
        return False
    if table.shape[0] != count:
        raise PlyError(f"after the {n_vertices} vertices the header declares {count} {name} records, "
                       f"the body holds {table.shape[0]} lines")
    if _is_index(name, props[0][0]):
        _check_index_range(table[:, 1:], name, None, n_vertices)
    return True


def _check_binary_tail(tail, n_vertices, vertex_size, elements, endian):
    """The bytes after the vertices must hold exactly the declared records (no more, no less)."""
    at = 0
    for name, count, props in elements:
        at = _skip_binary_element(tail, at, name, count, props, endian, n_vertices)
    if at != len(tail):
        extra = len(tail) - at
        if not elements and extra % vertex_size == 0:
            raise PlyError(f"the header declares {n_vertices} vertices, the body holds "
                           f"{n_vertices + extra // vertex_size}")
        raise PlyError(f"{extra} bytes follow the records the header declares "
                       f"({n_vertices} vertices{''.join(f', {c} {n}' for n, c, _ in elements)})")


def _skip_binary_element(tail, at, name, count, props, endian, n_vertices):
    """Offset just after ``count`` records of an element starting at ``at``; vertex indices checked."""
    left = len(tail) - at
    fixed = sum(np.dtype(t).itemsize if kind == "scalar" else np.dtype(t[0]).itemsize
                for _, kind, t in props)
    if count and fixed == 0:
        raise PlyError(f"element {describe_word(name)} has no properties")
    if count * fixed > left:
        raise PlyError(f"truncated: {count} {name} records need at least {count * fixed} bytes, "
                       f"{left} remain")
    if not any(kind == "list" for _, kind, _ in props):
        return at + count * fixed
    if count == 0:
        return at
    # Fast path: every list as long as in the first record (triangle meshes).
    layout, first = [], at
    for prop, kind, t in props:
        if kind == "scalar":
            layout.append(np.dtype(endian + t).itemsize)
            first += layout[-1]
        else:
            if first + np.dtype(t[0]).itemsize > len(tail):
                raise PlyError(f"truncated {name} block")
            length = int(np.frombuffer(tail, dtype=endian + t[0], count=1, offset=first)[0])
            if length < 0:
                raise PlyError(f"{name} 0: negative list length {length}")
            layout.append((np.dtype(endian + t[0]), length * np.dtype(t[1]).itemsize,
                           np.dtype(endian + t[1]) if _is_index(name, prop) else None))
            first += np.dtype(t[0]).itemsize + layout[-1][1]
    size = first - at
    if size * count <= left:
        fields, indices, offset = [], [], 0
        for k, item in enumerate(layout):
            if isinstance(item, tuple):
                fields.append((f"n{k}", item[0], offset))
                if item[2] is not None:
                    indices.append((offset + item[0].itemsize, item[1], item[2]))
                offset += item[0].itemsize + item[1]
            else:
                offset += item
        block = np.frombuffer(tail, dtype=np.uint8, count=size * count, offset=at).reshape(count, size)
        same = True
        for (field, dt, off), item in zip(fields, [i for i in layout if isinstance(i, tuple)]):
            lengths = block[:, off: off + dt.itemsize].copy().view(dt).ravel()
            same &= bool((lengths.astype(np.int64) * 1 == lengths[0]).all())
        if same:
            for off, nbytes, dt in indices:
                idx = block[:, off: off + nbytes].copy().view(dt)
                _check_index_range(idx, name, None, n_vertices)
            return at + size * count
    # General path: one record at a time (bounded: each record takes at least one byte).
    for k in range(count):
        for prop, kind, t in props:
            if kind == "scalar":
                at += np.dtype(t).itemsize
                continue
            dt = np.dtype(endian + t[0])
            if at + dt.itemsize > len(tail):
                raise PlyError(f"truncated: {name} {k} of {count} is cut off")
            length = int(np.frombuffer(tail, dtype=dt, count=1, offset=at)[0])
            if length < 0:
                raise PlyError(f"{name} {k}: negative list length {length}")
            at += dt.itemsize
            if _is_index(name, prop) and at + length * np.dtype(t[1]).itemsize <= len(tail):
                idx = np.frombuffer(tail, dtype=endian + t[1], count=length, offset=at)
                _check_index_range(idx, name, k, n_vertices)
            at += length * np.dtype(t[1]).itemsize
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


def _ascii_triangles(tail, count):
    """(f, 3) int64 triangles among the first ``count`` face lines (other polygons skipped)."""
    if not count:
        return np.zeros((0, 3), dtype=np.int64)
    try:
        table = np.loadtxt(io.BytesIO(tail), dtype=np.int64, ndmin=2, comments=None, max_rows=count)
        rows = table[table[:, 0] == 3, 1:4] if table.shape[1] == 4 else np.zeros((0, 3), dtype=np.int64)
    except ValueError:                      # polygons of several sizes
        lines = (line.split() for _, line in zip(range(count), _data_lines(tail)))
        rows = [[int(w) for w in words[1:4]] for words in lines if words and words[0] == b"3"]
    return np.asarray(rows, dtype=np.int64).reshape(-1, 3)


def _decode_faces(ply):
    if len(ply.elements) < 2 or ply.elements[1][0] != "face":
        return np.zeros((0, 3), dtype=np.int64)
    _, count, props = ply.elements[1]
    if len(props) != 1 or props[0][1] != "list":
        raise PlyError("only face elements with a single list property are supported")
    count_t, item_t = props[0][2]
    if ply.fmt == "ascii":
        return _ascii_triangles(ply.tail, count)
    e = _FORMATS[ply.fmt]
    dtype = np.dtype([("n", e + count_t), ("v", e + item_t, (3,))])
    if len(ply.tail) < dtype.itemsize * count:
        raise PlyError("truncated face block")
    faces = np.frombuffer(ply.tail[: dtype.itemsize * count], dtype=dtype)
    if not (faces["n"] == 3).all():
        raise PlyError("only triangle faces are supported")
    return faces["v"].astype(np.int64)
