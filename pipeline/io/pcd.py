"""PCD (Point Cloud Library) reading and writing that keeps every field and byte.

The header (comments, VERSION, FIELDS, SIZE, TYPE, COUNT, WIDTH, HEIGHT,
VIEWPOINT, POINTS, DATA) is kept verbatim.  ``ascii`` bodies are kept as
text and only the x, y, z tokens of moved points are rewritten (full
precision of the field's type); ``binary`` and ``binary_compressed`` bodies
become a packed little-endian record array whose x, y, z are replaced and
which is written back in the input's own encoding.  Fields keep their
TYPE, SIZE and COUNT; double x, y, z stay double.

``binary_compressed`` uses LZF: decompression is complete; the compressor
here encodes literals and repeats at short distances (the byte runs of
constant or periodic field columns).  Its output is valid LZF that PCL and
open3d read, though it may be larger than PCL's own.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

import numpy as np


from .text import (CHUNK, MAX_LINE, file_head, TextFormatError, Window, coordinates, describe_value, describe_word,
                   non_finite, read_blocks, rewrite_lines, split_lines, whole_text)

__all__ = ["PcdData", "PcdError", "read_pcd", "write_pcd", "pcd_from_points",
           "lzf_compress", "lzf_decompress", "check_head", "MAX_HEADER"]

MAX_HEADER = 1 << 20      # bytes; the DATA line must end within them
_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
_POSITIVE = re.compile(r"[1-9][0-9]{0,17}")     # a count: decimal digits, no sign, no leading zero

_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4",
          ("I", 8): "<i8", ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8"}
_ENCODINGS = ("ascii", "binary", "binary_compressed")
_REPEAT_DISTANCES = (1, 2, 3, 4, 6, 8, 12, 16)
_MIN_REPEAT = 8  # shorter repeats save too little to pay for the Python loop over them


class PcdError(ValueError):
    """A PCD file that cannot be read (the message says why)."""


@dataclass
class PcdData:
    """A PCD file: verbatim header plus its records or its text body.

    Attributes
    ----------
    header : bytes
        Everything up to and including the ``DATA`` line.
    fields : list of (name, type, size, count)
    encoding : str
        ``ascii``, ``binary`` or ``binary_compressed``.
    records : (n,) structured array or None
        Binary encodings; field names made unique (``_`` padding fields renamed).
    lines, rows, cols, kinds :
        ASCII encoding: see :class:`pipeline.io.text.TextTable`.
    points : (n, 3) float64
    """

    header: bytes
    fields: list
    encoding: str
    points: np.ndarray
    records: np.ndarray = None
    lines: list = None
    rows: np.ndarray = None
    cols: tuple = None
    kinds: tuple = None


def read_pcd(data):
    """Parse PCD bytes.

    Parameters
    ----------
    data : bytes or binary file
        An ascii body is checked line by line, block by block, before it is kept.

    Returns
    -------
    PcdData
    """
    head, size = file_head(data, MAX_HEADER + 8)
    header, fields, n, encoding = _layout(head, size)
    if encoding == "ascii":
        return _read_ascii(data, header, fields, n)
    dtype = _dtype(fields)
    if encoding == "binary":
        records = _binary_body(data, len(header), n, dtype)
    else:
        body = memoryview(whole_text(data))[len(header):]
        records = _from_columns(_compressed_body(body, n, dtype), n, dtype)
    points = np.column_stack([records[a].astype(np.float64) for a in "xyz"])
    return PcdData(header, fields, encoding, points, records=records)


def check_head(head, size):
    """Check a PCD's header and declared sizes from its first bytes, before the body is read.

    Parameters
    ----------
    head : bytes
        The file's first bytes (at least :data:`MAX_HEADER` plus 8 of them, or the whole file).
    size : int
        The file's length in bytes.

    Raises
    ------
    PcdError
        No header, a bad one, or a body length that disagrees with it.
    """
    _layout(head, size)


def _layout(data, size):
    """(header bytes, fields, point count, encoding), the body length checked against ``size``."""
    header, keys = _split_header(data)
    fields = _fields(keys)
    n = _point_count(keys)
    encoding = keys["DATA"][0]
    if encoding not in _ENCODINGS:
        raise PcdError(f"unknown DATA encoding {describe_word(encoding)} (use one of {', '.join(_ENCODINGS)})")
    _check_body_size(encoding, fields, n, data[len(header):len(header) + 8], size - len(header))
    return header, fields, n, encoding


# a binary_compressed body is decoded whole (LZF, in Python): above this many unpacked bytes it is
# refused before any read, so a refused file of any size costs bounded memory (about 4x this)
MAX_COMPRESSED_BODY = 64 * 2**20


def _check_body_size(encoding, fields, n, prefix, held):
    """The body's length (``held`` bytes, starting with ``prefix``) against what the header declares."""
    itemsize = _dtype(fields).itemsize
    if encoding == "binary" and held != n * itemsize:
        raise PcdError(f"POINTS {n} x {itemsize} bytes = {n * itemsize} bytes of data, the body has {held}")
    if encoding == "ascii" and held < n * sum(c for *_rest, c in fields):     # a byte per value at least
        raise PcdError(f"truncated: POINTS {n} ascii records need at least "
                       f"{n * sum(c for *_rest, c in fields)} bytes, the body has {held}")
    if encoding == "binary_compressed":
        if held < 8 or len(prefix) < 8:
            raise PcdError("binary_compressed body shorter than its 8-byte size prefix")
        packed, unpacked = struct.unpack("<II", bytes(prefix))
        if held - 8 != packed:
            raise PcdError(f"the compressed block declares {packed} bytes, the body holds {held - 8}")
        if unpacked != n * itemsize:
            raise PcdError(f"the compressed block unpacks to {unpacked} bytes, "
                           f"POINTS {n} x {itemsize} bytes = {n * itemsize}")
        if unpacked > MAX_COMPRESSED_BODY:
            raise PcdError(f"binary_compressed bodies are read up to {MAX_COMPRESSED_BODY >> 20} MiB unpacked, "
                           f"this one unpacks to {unpacked >> 20} MiB: re-save it as binary (e.g. pcl_convert_pcd_"
                           f"ascii_binary in.pcd out.pcd 1)")


def _split_header(data):
    """(header bytes up to and including the DATA line, {key: words}); bounded to MAX_HEADER bytes."""
    keys, pos, lineno = {}, 0, 0
    while pos < min(len(data), MAX_HEADER):
        nl = data.find(b"\n", pos, pos + MAX_LINE)
        end = min(len(data), pos + MAX_LINE) if nl < 0 else nl + 1
        raw = bytes(data[pos:end])
        line = raw.decode("ascii", errors="replace").strip()
        pos, lineno = end, lineno + 1
        if not line or line.startswith("#"):
            continue
        words = line.split()
        if words[0] not in _KEYS and not keys:
            raise PcdError("not a PCD file (its first header line holds no PCD keyword such as VERSION or FIELDS)")
        if words[0] not in _KEYS:
            raise PcdError(f"header line {lineno}: unknown key {describe_word(words[0])} "
                           f"(PCD keys: {' '.join(_KEYS)})")
        if words[0] in keys:
            raise PcdError(f"header line {lineno}: {words[0]} appears twice")
        keys[words[0]] = words[1:]
        if words[0] == "DATA":
            if len(words) != 2:
                raise PcdError(f"header line {lineno}: bad DATA line (DATA ENCODING expected)")
            return bytes(data[:pos]), keys
    raise PcdError(f"not a PCD file (no DATA line within the first {MAX_HEADER} bytes)")


def _fields(keys):
    for key in ("FIELDS", "SIZE", "TYPE"):
        if key not in keys:
            raise PcdError(f"the header has no {key} line")
    names = keys["FIELDS"]
    counts = keys.get("COUNT", ["1"] * len(names))
    if not len(names) == len(keys["SIZE"]) == len(keys["TYPE"]) == len(counts):
        raise PcdError(f"FIELDS, SIZE, TYPE and COUNT disagree in length "
                       f"({len(names)}, {len(keys['SIZE'])}, {len(keys['TYPE'])}, {len(counts)})")
    fields = []
    for name, size, kind, count in zip(names, keys["SIZE"], keys["TYPE"], counts):
        if not (_POSITIVE.fullmatch(size) and _POSITIVE.fullmatch(count)) or (kind, int(size)) not in _TYPES:
            raise PcdError(f"field {describe_word(name)}: unsupported TYPE {describe_word(kind)} "
                           f"SIZE {describe_value(size)} COUNT {describe_value(count)} "
                           f"(SIZE 1, 2, 4 or 8, COUNT a positive integer)")
        fields.append((name, kind, int(size), int(count)))
    for axis in "xyz":
        found = [f for f in fields if f[0] == axis]
        if len(found) != 1 or found[0][3] != 1:
            raise PcdError(f"the header needs exactly one field {axis!r} with COUNT 1 "
                           f"(FIELDS has {len(names)} names)")
    return fields


def _point_count(keys):
    values = {}
    for key in ("WIDTH", "HEIGHT", "POINTS"):
        words = keys.get(key, ["1"] if key == "HEIGHT" else None if key == "WIDTH" else [])
        if words is None:
            raise PcdError("the header has no WIDTH line")
        if key == "POINTS" and not words:
            continue
        if len(words) != 1 or not _POSITIVE.fullmatch(words[0]):
            raise PcdError(f"{key} {describe_value(' '.join(words))} is not a positive integer")
        values[key] = int(words[0])
    width, height = values["WIDTH"], values["HEIGHT"]
    points = values.get("POINTS", width * height)
    if width * height != points:
        raise PcdError(f"WIDTH x HEIGHT = {width} x {height} disagrees with POINTS {points}")
    return points


def _unique_names(fields):
    seen, names = set(), []
    for i, (name, *_rest) in enumerate(fields):
        unique = name if name and name not in seen else f"_field{i}"
        seen.add(unique)
        names.append(unique)
    return names


def _dtype(fields):
    return np.dtype([(u, _TYPES[(k, s)], (c,)) if c > 1 else (u, _TYPES[(k, s)])
                     for u, (_, k, s, c) in zip(_unique_names(fields), fields)])


def _binary_body(source, start, n, dtype):
    """(n,) records of a binary body, its length checked by :func:`_check_body_size`.

    The coordinates are checked window by window first, so a refused body
    costs bounded memory; one that passed is read once, into the array.
    """
    window, done, bad, first = Window(source, start, min(CHUNK, n * dtype.itemsize)), 0, 0, -1
    while done < n and window.need(dtype.itemsize):
        k = min(n - done, (window.hi - window.lo) // dtype.itemsize)
        count, at = non_finite(np.frombuffer(window.buf, dtype=dtype, count=k, offset=window.lo))
        first = done + at if count and first < 0 else first
        bad, done, window.lo = bad + count, done + k, window.lo + k * dtype.itemsize
    if done != n:
        raise PcdError(f"truncated: POINTS {n}, the body holds {done} records")
    if bad:
        raise PcdError(f"{bad} points have NaN or infinite coordinates (first at index {first})")
    if not hasattr(source, "readinto"):
        return np.frombuffer(source, dtype=dtype, count=n, offset=start).copy()
    records = np.empty(n, dtype=dtype)
    source.seek(start)
    view, got = memoryview(records.view(np.uint8)), 0
    while got < len(view) and (step := source.readinto(view[got:])):
        got += step
    if got != len(view) or source.read(1):
        raise PcdError("the file changed while it was read")
    return records


def _compressed_body(body, n, dtype):
    """The decompressed column block; sizes were checked by :func:`_check_body_size`."""
    return lzf_decompress(bytes(body[8:]), n * dtype.itemsize)


def _from_columns(raw, n, dtype):
    records = np.zeros(n, dtype=dtype)
    pos = 0
    for name in dtype.names:
        sub = dtype[name]
        size = n * sub.itemsize
        records[name] = np.frombuffer(raw[pos:pos + size], dtype=sub.base).reshape(records[name].shape)
        pos += size
    return records


def _to_columns(records):
    return b"".join(np.ascontiguousarray(records[name]).tobytes() for name in records.dtype.names)


def _read_ascii(data, header, fields, n):
    """An ascii body: every line checked block by block, then kept for faithful writing."""
    layout = _AsciiBody(fields, n)
    try:
        rows, points = read_blocks(data, _ascii_block, lambda totals: _AsciiBody(fields, n),
                                   start=len(header), line=header.count(b"\n") + 1)
    except TextFormatError as exc:          # not text (the lines' own errors are PcdErrors)
        raise PcdError(f"the ascii body: {exc}") from None
    lines = split_lines(whole_text(data, len(header)))
    return PcdData(header, fields, "ascii", points, lines=lines, rows=rows, cols=layout.cols, kinds=layout.kinds)


class _AsciiBody:
    """The layout an ascii body's lines must follow, and the data lines counted so far."""

    def __init__(self, fields, n):
        self.n, self.seen = n, 0
        self.width = sum(c for *_rest, c in fields)
        offsets = np.cumsum([0] + [c for *_rest, c in fields])
        names = [f[0] for f in fields]
        self.cols = tuple(int(offsets[names.index(a)]) for a in "xyz")
        self.kinds = tuple(_kind(_TYPES[(fields[names.index(a)][1], fields[names.index(a)][2])]) for a in "xyz")

    def finish(self, totals):
        if totals[0] != self.n:
            raise PcdError(f"POINTS {self.n} disagrees with the {totals[0]} data lines")
        return False


def _ascii_block(tokens, body):
    """(rows (k,), points (k, 3)) of a block of ascii data lines; float32 fields rounded as stored."""
    lines = np.flatnonzero(tokens.count > 0)
    wrong = np.flatnonzero(tokens.count[lines] != body.width)
    try:
        points = coordinates(tokens, lines[:wrong[0]] if len(wrong) else lines, body.cols)
    except TextFormatError as exc:
        raise PcdError(str(exc)) from None
    if len(wrong):
        at = int(lines[wrong[0]])
        raise PcdError(f"line {tokens.line + at}: {tokens.count[at]} values, the fields need {body.width}")
    for i, a in enumerate("xyz"):
        if body.kinds[i] == "f4":
            if len(points) and np.abs(points[:, i]).max() > np.finfo(np.float32).max:
                raise PcdError(f"field {a} is declared float32 but holds {np.abs(points[:, i]).max():.3g}, "
                               f"beyond float32's range")
            points[:, i] = points[:, i].astype(np.float32)
    return tokens.row + lines.astype(np.int64), points


def _kind(dtype):
    dtype = np.dtype(dtype)
    if dtype.kind == "f":
        return "f4" if dtype.itemsize == 4 else "f8"
    return "i"


def write_pcd(pcd, points):
    """Serialise a PCD with new coordinates, everything else unchanged.

    Parameters
    ----------
    pcd : PcdData
    points : (n, 3) float

    Returns
    -------
    bytes
    """
    points = np.asarray(points, dtype=np.float64)
    if points.shape != pcd.points.shape:
        raise PcdError(f"{len(points)} points given, the file holds {len(pcd.points)}")
    if pcd.encoding == "ascii":
        return pcd.header + rewrite_lines(pcd.lines, pcd.rows, pcd.cols, pcd.kinds, pcd.points, points)
    records = pcd.records.copy()
    for i, a in enumerate("xyz"):
        records[a] = _cast(points[:, i], records.dtype[a])
    if pcd.encoding == "binary":
        return pcd.header + records.tobytes()
    raw = _to_columns(records)
    packed = lzf_compress(raw)
    return pcd.header + struct.pack("<II", len(packed), len(raw)) + packed


def _cast(values, dtype):
    if dtype.kind == "f":
        return values.astype(dtype)
    info = np.iinfo(dtype)
    rounded = np.rint(values)
    if rounded.min() < info.min or rounded.max() > info.max:
        raise PcdError(f"coordinates do not fit the field type {dtype}")
    return rounded.astype(dtype)


def pcd_from_points(points):
    """A new binary PCD of bare float64 coordinates.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    bytes
    """
    points = np.asarray(points, dtype="<f8")
    n = len(points)
    head = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\n"
            f"TYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
            f"POINTS {n}\nDATA binary\n")
    return head.encode("ascii") + np.ascontiguousarray(points).tobytes()


def lzf_decompress(data, size):
    """Decode an LZF block.

    Parameters
    ----------
    data : bytes
    size : int
        Expected decoded length: a hard limit, decoding stops the moment the
        output would grow past it.

    Returns
    -------
    bytes
    """
    out = bytearray()
    i, n = 0, len(data)
    try:
        while i < n:
            ctrl = data[i]
            i += 1
            if ctrl < 32:
                if i + ctrl + 1 > n:
                    raise PcdError("corrupt LZF data (literal run past the end)")
                _check_room(out, ctrl + 1, size)
                out += data[i:i + ctrl + 1]
                i += ctrl + 1
                continue
            length = ctrl >> 5
            if length == 7:
                length += data[i]
                i += 1
            ref = len(out) - ((ctrl & 0x1F) << 8) - data[i] - 1
            i += 1
            _check_room(out, length + 2, size)
            _copy_back(out, ref, length + 2)
    except IndexError:
        raise PcdError("corrupt LZF data (back reference past the end)") from None
    if len(out) != size:
        raise PcdError(f"LZF data decodes to {len(out)} bytes, the header says {size}")
    return bytes(out)


def _check_room(out, length, size):
    if len(out) + length > size:
        raise PcdError(f"LZF data decodes to more than the {size} bytes the header declares")


def _copy_back(out, ref, length):
    if ref < 0:
        raise PcdError("corrupt LZF data (back reference before the start)")
    if ref + length <= len(out):
        out += out[ref:ref + length]
        return
    pattern = out[ref:]
    out += (pattern * (length // len(pattern) + 1))[:length]


def lzf_compress(data):
    """Encode bytes as LZF: literals plus repeats at short distances.

    Parameters
    ----------
    data : bytes

    Returns
    -------
    bytes
    """
    out = bytearray()
    pos = 0
    for start, length, dist in _repeats(np.frombuffer(data, dtype=np.uint8)):
        if start < pos:
            start, length = pos, length - (pos - start)
        if length < 3:
            continue
        _literals(out, data[pos:start])
        while length >= 3:
            chunk = min(length, 264)
            _back_reference(out, chunk, dist)
            start, length = start + chunk, length - chunk
        pos = start
    _literals(out, data[pos:])
    return bytes(out)


def _repeats(buf):
    """(start, length, distance) runs where buf[i] == buf[i - distance], by start."""
    found = []
    for dist in _REPEAT_DISTANCES:
        if len(buf) <= dist:
            break
        same = np.concatenate([[False], buf[dist:] == buf[:-dist], [False]])
        edges = np.flatnonzero(same[1:] != same[:-1])
        starts, ends = edges[0::2] + dist, edges[1::2] + dist
        keep = ends - starts >= _MIN_REPEAT
        found += zip(starts[keep].tolist(), (ends - starts)[keep].tolist(), [dist] * int(keep.sum()))
    found.sort(key=lambda r: (r[0], -r[1]))
    return found


def _literals(out, chunk):
    full = len(chunk) // 32
    if full:
        block = np.empty((full, 33), dtype=np.uint8)
        block[:, 0] = 31
        block[:, 1:] = np.frombuffer(chunk, dtype=np.uint8, count=full * 32).reshape(full, 32)
        out += block.tobytes()
    rest = chunk[full * 32:]
    if rest:
        out.append(len(rest) - 1)
        out += rest


def _back_reference(out, length, dist):
    off, code = dist - 1, length - 2
    if code < 7:
        out += bytes(((code << 5) | (off >> 8), off & 0xFF))
    else:
        out += bytes(((7 << 5) | (off >> 8), code - 7, off & 0xFF))
