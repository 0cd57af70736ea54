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
import struct
from dataclasses import dataclass, field

import numpy as np

from .text import (CHUNK, file_head, TextFormatError, Window, describe_value, describe_word, gather, non_finite, read_blocks,
                   whole_text)

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
    (fewer or more records than declared, bytes or lines left over).  An
    ASCII body is checked block by block, a binary one window by window
    (finite coordinates included), before anything is kept, so a refused
    one costs bounded memory; a binary body that passed is then read once.

    Parameters
    ----------
    data : bytes or binary file

    Returns
    -------
    PlyData
    """
    head, size = file_head(data, MAX_HEADER + 16)
    body_start, header, fmt, elements = _header(head, size)
    count, props = elements[0][1], elements[0][2]
    if fmt == "ascii":
        values = _read_ascii_body(data, body_start, count, props, elements[1:], header)
        body = memoryview(whole_text(data))[body_start:]
        vertices = np.empty(count, dtype=np.dtype([(p, t) for p, _, t in props]))
        for i, (p, _, _) in enumerate(props):
            vertices[p] = values[:, i]
        tail = bytes(body[_line_end(body, count):])
    else:
        dtype = np.dtype([(p, _FORMATS[fmt] + t) for p, _, t in props])
        _check_binary_body(data, body_start, size - body_start, count, dtype, elements[1:], _FORMATS[fmt])
        vertices, tail = _binary_body(data, body_start, size - body_start, count, dtype)
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


def _read_ascii_body(data, body_start, count, props, elements, header):
    """(count, p) float64 vertex values of an ASCII body; every line checked block by block first.

    The lines after the vertices must hold exactly the declared records; list
    lengths and vertex indices are checked.
    """
    try:
        (values,) = read_blocks(data, _ascii_block, lambda totals: _AsciiBody(count, props, elements),
                                start=body_start, line=len(header) + 1)
    except TextFormatError as exc:
        raise PlyError(f"the ascii body: {exc}") from None
    return values


class _AsciiBody:
    """An ASCII body's layout, and how far a pass over it has come."""

    def __init__(self, count, props, elements):
        self.count, self.props, self.elements = count, props, elements
        self.element, self.done, self.extra = 0, 0, 0      # element in checking, its records checked, lines beyond

    def finish(self, totals):
        if totals[0] < self.count:
            raise PlyError(f"truncated: the header declares {self.count} vertices, {totals[0]} lines follow")
        declared = sum(c for _, c, _ in self.elements)
        held = sum(c for _, c, _ in self.elements[:self.element]) + self.done + self.extra
        if held == declared and not self.extra:
            return False
        if not self.elements:
            raise PlyError(f"the header declares {self.count} vertices, the body holds {self.count + held} "
                           f"lines of data")
        if len(self.elements) == 1:
            name, n, _ = self.elements[0]
            raise PlyError(f"after the {self.count} vertices the header declares {n} {name} records, "
                           f"the body holds {held} lines")
        listing = ", ".join(f"{c} {n}" for n, c, _ in self.elements)
        raise PlyError(f"after the {self.count} vertices the header declares {declared} records ({listing}), "
                       f"the body holds {held if held else 'none'}{' lines' if held else ''}")


def _ascii_block(tokens, body):
    """((k, p) float64 values of the block's vertex lines,); the records after them checked."""
    n_lines = len(tokens.count)
    k = int(min(max(body.count - tokens.row, 0), n_lines))
    values = _vertex_values(tokens, k, body)
    lines = k + np.flatnonzero(tokens.count[k:])
    at = 0
    while at < len(lines):
        if body.element == len(body.elements):
            body.extra += len(lines) - at
            break
        name, count, props = body.elements[body.element]
        take = min(count - body.done, len(lines) - at)
        _check_records(tokens, lines[at:at + take], name, props, body.done, body.count)
        body.done, at = body.done + take, at + take
        if body.done == count:
            body.element, body.done = body.element + 1, 0
    return (values,)


def _vertex_values(tokens, k, body):
    """(k, p) float64: the block's first ``k`` lines, each one vertex of ``p`` values in range."""
    p = len(body.props)
    wrong = np.flatnonzero(tokens.count[:k] != p)
    pending = None
    if len(wrong):
        j = int(wrong[0])
        what = "is blank" if not tokens.count[j] else f"has {tokens.count[j]} values"
        pending = PlyError(f"line {tokens.line + j} (vertex {tokens.row + j}) {what}, the header declares "
                           f"{p} properties")
        k = j
    words = tokens.words[:k * p]
    try:
        values = np.fromiter(map(float, words), dtype=np.float64, count=k * p).reshape(k, p)
    except ValueError:
        i = next(i for i, w in enumerate(words) if not _is_number(w))
        raise PlyError(f"line {tokens.line + i // p} (vertex {tokens.row + i // p}): value {i % p + 1} "
                       f"({describe_value(words[i])}) is not a number") from None
    if pending is not None:
        raise pending
    for i, (name, _, t) in enumerate(body.props):
        _check_ascii_range(name, values[:, i], np.dtype(t), tokens.row)
    return values


def _is_number(word):
    try:
        float(word)
    except ValueError:
        return False
    return True


def _check_records(tokens, lines, name, props, k0, n_vertices):
    """Records ``k0``, ``k0 + 1``, ... of an element, one per line: list lengths, value counts, vertex indices.

    Vectorised over the lines; the first bad record (and within it the first
    bad property) is named.
    """
    first = tokens.first[lines]
    end = first + tokens.count[lines]
    cursor, found = first.copy(), []                  # found: (record, property order, message)
    signs = any(c in tokens.data for c in (b"+", b"-", b"_"))
    for order, (prop, kind, _) in enumerate(props):
        if kind != "list":
            cursor = cursor + 1
            continue
        inside = cursor < end
        lengths = _lengths(gather(tokens.words, np.minimum(cursor, end - 1)), signs)
        bad = ~inside | (lengths < 0)
        if bad.any():
            r = int(np.argmax(bad))
            found.append((r, order, f"{name} {k0 + r}: bad list length (value {int(cursor[r] - first[r]) + 1})"))
        lengths = np.where(bad, 0, lengths)
        if _is_index(name, prop):
            found += _index_errors(tokens, cursor + 1, np.minimum(cursor + 1 + lengths, end), name, k0,
                                   n_vertices, order)
        cursor = cursor + 1 + lengths
    wrong = np.flatnonzero(cursor != end)
    if len(wrong):
        r = int(wrong[0])
        found.append((r, len(props), f"{name} {k0 + r}: {int(end[r] - first[r])} values, the header declares "
                                     f"{int(cursor[r] - first[r])}"))
    if found:
        r, _, message = min(found)
        raise PlyError(f"line {tokens.line + int(lines[r])}, {message}")


_LONGEST = 1 << 40          # a list length beyond any line (the count check then refuses it)


def _lengths(words, signs=True):
    """(r,) int64 list lengths; -1 where a word is not a plain decimal number.

    Without ``+``, ``-`` or ``_`` in the block (``signs`` false), ``int``
    accepts exactly the plain decimal numbers, so it decides in C.
    """
    if not signs:
        try:
            return np.minimum(np.fromiter(map(int, words), dtype=np.int64, count=len(words)), _LONGEST)
        except (ValueError, OverflowError):
            pass
    return np.fromiter((min(int(w), _LONGEST) if w.isdigit() else -1 for w in words), dtype=np.int64,
                       count=len(words))


def _index_errors(tokens, start, stop, name, k0, n_vertices, order):
    """[(record, order, message)] for the first record whose words ``start:stop`` hold a bad vertex index."""
    n = np.maximum(stop - start, 0)
    idx = np.arange(int(n.sum())) + np.repeat(start - (np.cumsum(n) - n), n)
    words = gather(tokens.words, idx)
    values, ok = _integers(words)
    bad = ~ok | (values < 0) | (values >= n_vertices)
    if not bad.any():
        return []
    at = int(np.argmax(bad))
    r = int(np.repeat(np.arange(len(n)), n)[at])
    if not ok[at]:
        return [(r, order, f"{name} {k0 + r}: a vertex index is not an integer")]
    return [(r, order, f"{name} {k0 + r}: vertex index {int(words[at])} is outside the {n_vertices} vertices")]


def _integers(words):
    """((r,) int64 values, (r,) bool: whether each word is an integer Python reads)."""
    try:
        return np.fromiter(map(int, words), dtype=np.int64, count=len(words)), np.ones(len(words), dtype=bool)
    except (ValueError, OverflowError):
        pass
    values = np.fromiter(map(_integer, words), dtype=np.int64, count=len(words))
    return values, values != _NOT_INTEGER


_NOT_INTEGER = np.iinfo(np.int64).min


def _integer(word):
    try:
        return max(min(int(word), 1 << 62), -(1 << 62))      # out of range either way
    except ValueError:
        return _NOT_INTEGER


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


def _check_ascii_range(name, column, dtype, first=0):
    """Values of an ASCII column (vertices ``first``, ``first + 1``, ...) must fit the declared type."""
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
        raise PlyError(f"vertex {first + i}: property {name!r} is {column[i]!r}, not {what}")


def _data_lines(data):
    """The non-blank lines of ``data``, one at a time (no list of the whole body)."""
    start = 0
    while start < len(data):
        nl = data.find(b"\n", start)
        end = len(data) if nl < 0 else nl
        if data[start:end].strip():
            yield data[start:end]
        start = end + 1


def _is_index(element, prop):
    """Whether a list property holds vertex indices (checked against the vertex count)."""
    return element == "face" or prop in _INDEX_NAMES


def _check_index_range(idx, name, first, n_vertices):
    """Refuse indices outside [0, n_vertices); ``idx`` (r, l) holds records ``first``, ``first + 1``, ..."""
    bad = (idx < 0) | (idx >= n_vertices)
    if bad.any():
        at = np.argwhere(bad)[0]
        raise PlyError(f"{name} {first + int(at[0])}: vertex index {int(idx[tuple(at)])} is outside the "
                       f"{n_vertices} vertices")


def _check_binary_body(source, start, left, count, vertex, elements, endian):
    """Check a binary body window by window, before anything is kept; the vertices' dtype is ``vertex``.

    Every value check runs here (finite coordinates, list lengths, vertex
    indices, truncation, bytes left over), on one reused buffer of
    :data:`~pipeline.io.text.CHUNK` bytes, so a refused body of any size
    costs bounded memory.  ``left`` is the body's length in bytes.
    """
    w = Window(source, start, min(CHUNK, left))      # a small body: a small buffer
    bad, first = _check_vertices(w, count, vertex)
    for name, n, props in elements:
        _check_element(w, name, n, props, endian, count, left)
    extra = left - w.consumed
    if extra:
        if not elements and extra % vertex.itemsize == 0:
            raise PlyError(f"the header declares {count} vertices, the body holds "
                           f"{count + extra // vertex.itemsize}")
        raise PlyError(f"{extra} bytes follow the records the header declares "
                       f"({count} vertices{''.join(f', {c} {n}' for n, c, _ in elements)})")
    if bad:
        raise PlyError(f"{bad} points have NaN or infinite coordinates (first at index {first})")


def _check_vertices(w, count, dtype):
    """(count, first index) of the vertices with a coordinate that is not finite; the window moves past them."""
    size, done, bad, first = dtype.itemsize, 0, 0, -1
    while done < count:
        if not w.need(size):
            raise PlyError(f"truncated: the header declares {count} vertices, {done} follow")
        k = min(count - done, (w.hi - w.lo) // size)
        n, at = non_finite(np.frombuffer(w.buf, dtype=dtype, count=k, offset=w.lo))
        first = done + at if n and first < 0 else first
        bad, done, w.lo = bad + n, done + k, w.lo + k * size
    return bad, first


def _skip(w, n):
    """Consume ``n`` bytes; False when the body ends first."""
    while n:
        if w.lo == w.hi and not w.fill():
            return False
        take = min(n, w.hi - w.lo)
        w.lo, n = w.lo + take, n - take
    return True


def _check_element(w, name, count, props, endian, n_vertices, left):
    """Move the window past ``count`` records of an element; list lengths and vertex indices checked."""
    fixed = sum(np.dtype(t).itemsize if kind == "scalar" else np.dtype(t[0]).itemsize for _, kind, t in props)
    if count and fixed == 0:
        raise PlyError(f"element {describe_word(name)} has no properties")
    remain = left - w.consumed
    if count * fixed > remain:
        raise PlyError(f"truncated: {count} {name} records need at least {count * fixed} bytes, {remain} remain")
    if not any(kind == "list" for _, kind, _ in props):
        _skip(w, count * fixed)
        return
    plan = [(np.dtype(t).itemsize, None, 0, None) if kind == "scalar" else
            (np.dtype(t[0]).itemsize, struct.Struct(endian + _STRUCT[t[0]]), np.dtype(t[1]).itemsize,
             np.dtype(endian + t[1]) if _is_index(name, prop) else None) for prop, kind, t in props]
    layout = _first_layout(w, plan, endian, props)
    k = _check_same_records(w, name, count, layout, n_vertices) if layout else 0
    if k < count:
        _walk_records(w, name, k, count, plan, n_vertices)


_STRUCT = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I"}
_SPAN_ITEMS = 1 << 19        # vertex indices gathered before they are checked at once
_LONG_SPAN = 1 << 12         # a list at least this long is checked on its own, without a gather


def _first_layout(w, plan, endian, props):
    """The record at the window's start, with every list as long as in it: (size, lengths, indices).

    ``lengths``: [(offset, dtype, length)]; ``indices``: [(offset, bytes, dtype)].
    None when that record does not fit in half a window or cannot be read (the walk then names why).
    """
    at, lengths, indices, limit = 0, [], [], CHUNK // 2
    for (width, length_of, item, index), (_, _, t) in zip(plan, props):
        if length_of is None:
            at += width
            continue
        if at + width > limit or not w.need(at + width):
            return None
        length = length_of.unpack_from(w.buf, w.lo + at)[0]
        if length < 0:
            return None
        lengths.append((at, np.dtype(endian + t[0]), length))
        if index is not None:
            indices.append((at + width, length * item, index))
        at += width + length * item
    return (at, lengths, indices) if at <= limit else None


def _check_same_records(w, name, count, layout, n_vertices):
    """Check records while their lists are as long as the first one's, a window of records at once.

    Returns the number of records passed: ``count``, or the first record
    that differs (or is cut off), where the walk takes over.
    """
    size, lengths, indices = layout
    k = 0
    while k < count and w.need(size):
        m = min(count - k, (w.hi - w.lo) // size)
        block = np.frombuffer(w.buf, dtype=np.uint8, count=m * size, offset=w.lo).reshape(m, size)
        same = np.ones(m, dtype=bool)
        for off, dt, length in lengths:
            same &= block[:, off: off + dt.itemsize].copy().view(dt).ravel() == length
        r = m if same.all() else int(np.argmin(same))
        for off, nbytes, dt in indices:
            if nbytes:
                _check_index_range(block[:r, off: off + nbytes].copy().view(dt), name, k, n_vertices)
        w.lo, k = w.lo + r * size, k + r
        if r < m:
            break
    return k


def _walk_records(w, name, k0, count, plan, n_vertices):
    """Move the window past records ``k0`` to ``count`` of lists of several lengths, one record at a time.

    List lengths come from ``struct`` (no array per record); a list may
    run across windows.  Vertex indices are checked in batches, each before
    the window moves and before a later error is raised, so the first bad
    record is the one named.
    """
    buf, spans, items = w.buf, [], 0
    lo, hi = w.lo, w.hi

    def refill(n, k):
        nonlocal lo, hi, spans, items
        w.lo = lo
        _check_spans(buf, spans, name, n_vertices)
        spans, items = [], 0
        if not w.need(n):
            raise PlyError(f"truncated: {name} {k} of {count} is cut off")
        lo, hi = w.lo, w.hi

    for k in range(k0, count):
        for width, length_of, item, index in plan:
            if hi - lo < width:
                refill(width, k)
            if length_of is None:
                lo += width
                continue
            length = length_of.unpack_from(buf, lo)[0]
            lo += width
            if length < 0:
                w.lo = lo
                _check_spans(buf, spans, name, n_vertices)
                raise PlyError(f"{name} {k}: negative list length {length}")
            nbytes = length * item
            while nbytes:
                take = min(nbytes, (hi - lo) // item * item)
                if not take:
                    refill(item, k)
                    continue
                if index is not None:
                    spans.append((k, lo, take // item, index))
                    items += take // item
                lo, nbytes = lo + take, nbytes - take
        if items > _SPAN_ITEMS:
            _check_spans(buf, spans, name, n_vertices)
            spans, items = [], 0
    w.lo = lo
    _check_spans(buf, spans, name, n_vertices)


def _check_spans(buf, spans, name, n_vertices):
    """Check the vertex indices of list spans ``[(record, offset, length, dtype)]`` in ``buf``.

    The first bad record is named.
    """
    found, short = [], {}
    for k, offset, length, dt in spans:
        if length >= _LONG_SPAN:
            idx = np.frombuffer(buf, dtype=dt, count=length, offset=offset)
            bad = (idx < 0) | (idx >= n_vertices)
            if bad.any():
                found.append((k, int(idx[int(np.argmax(bad))])))
        else:
            short.setdefault(dt, []).append((k, offset, length))
    for dt, group in short.items():
        record, offset, length = (np.asarray(c, dtype=np.int64) for c in zip(*group))
        n = length * dt.itemsize
        byte = np.arange(int(n.sum())) + np.repeat(offset - (np.cumsum(n) - n), n)
        idx = np.frombuffer(buf, dtype=np.uint8)[byte].view(dt).astype(np.int64)
        bad = (idx < 0) | (idx >= n_vertices)
        if bad.any():
            at = int(np.argmax(bad))
            found.append((int(np.repeat(record, length)[at]), int(idx[at])))
    if found:
        k, value = min(found)
        raise PlyError(f"{name} {k}: vertex index {value} is outside the {n_vertices} vertices")


def _binary_body(source, start, left, count, dtype):
    """(vertices, tail bytes) of a binary body that :func:`_check_binary_body` passed: the bytes, read once."""
    need = count * dtype.itemsize
    if not hasattr(source, "readinto"):
        return np.frombuffer(source, dtype=dtype, count=count, offset=start).copy(), bytes(source[start + need:])
    vertices = np.empty(count, dtype=dtype)
    source.seek(start)
    view, got = memoryview(vertices.view(np.uint8)), 0
    while got < need:
        n = source.readinto(view[got:])
        if not n:
            break
        got += n
    tail = source.read(left - need)          # one allocation of the known length (``read()`` joins parts)
    if got != need or len(tail) != left - need or source.read(1):
        raise PlyError("the file changed while it was read")
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
