"""XYZ and PTS text point clouds, read strictly and written back token for token.

A file is kept as its lines.  Only the x, y and z tokens of point lines are
ever rewritten, and only where a coordinate changed, at full float64
precision (``repr``); every other column (PTS intensity and colour, any
extra XYZ column), every separator, comment and line ending stays as it was.

Rules (both formats):

* columns are separated by white space; x, y and z are the first three;
* blank lines and lines whose first non-blank character is ``#`` are kept
  verbatim and hold no point;
* every point line has as many columns as the first one (at least three),
  otherwise the line number is reported;
* PTS: the first line holding data is the point count; after that many point
  lines another count line may start a further block (Leica's multi-scan
  files).  A count that disagrees with the lines that follow is an error.

The helpers :func:`parse_coords` and :func:`rewrite_lines` are shared with
the PCD (ascii) and OBJ modules.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

__all__ = ["TextFormatError", "TextTable", "read_xyz", "read_pts", "write_text",
           "xyz_from_points", "pts_from_points", "parse_coords", "rewrite_lines",
           "format_coordinate", "split_lines", "excerpt", "describe_value", "describe_word", "check_text",
           "packed_kind", "MAX_LINE"]

_SEPARATORS = re.compile(rb"(\s+)")
MAX_LINE = 1 << 20          # bytes; a longer line is not a point line (a binary file, a one-line dump)
EXCERPT = 40                # characters of file content an error message may quote
_PLAIN = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789 .,:;+-_=/()[]{}#@%*~^!?")
_WORD = re.compile(r"[A-Za-z0-9_.:\-]+")
_NUMERIC = re.compile(r"[-+0-9.eE_ ]+|[-+]?(nan|inf|infinity)", re.IGNORECASE)
_PACKED = {b"\x1f\x8b": "gzip", b"PK\x03\x04": "zip", b"\x28\xb5\x2f\xfd": "zstd", b"\xfd7zXZ\x00": "xz",
           b"BZh": "bzip2", b"7z\xbc\xaf\x27\x1c": "7-zip"}
_IS_CONTROL = np.zeros(256, dtype=bool)
_IS_CONTROL[sorted(set(range(32)) - set(b"\t\n\r\f\v")) + [0x7F]] = True


class TextFormatError(ValueError):
    """A text point file that cannot be read (the message says why and where)."""


@dataclass
class TextTable:
    """The lines of a text point file and where its coordinates sit.

    Attributes
    ----------
    lines : list of bytes
        The file split at ``b"\\n"`` (line endings other than ``\\n`` stay in the lines).
    rows : (n,) int64
        Index into ``lines`` of each point's line, in point order.
    cols : tuple of 3 int
        Token index of x, y and z within a point line.
    points : (n, 3) float64
        Coordinates as stored.
    kinds : tuple of 3 str
        How each coordinate is written: ``"f8"`` (repr of a float64),
        ``"f4"`` (a float32, written as the float64 text of its exact value) or
        ``"i"`` (an integer).
    """

    lines: list
    rows: np.ndarray
    cols: tuple
    points: np.ndarray
    kinds: tuple = ("f8", "f8", "f8")


def excerpt(raw, limit=EXCERPT):
    """A short, escaped quotation of file content for an error message.

    At most ``limit`` characters of ``raw``, between single quotes; every
    character outside letters, digits, space and plain punctuation (quotes,
    ``|``, backticks, ``<``, ``>``, backslash, control characters, non-ASCII)
    is written as ``\\xNN``, so the quotation stays on one line and cannot
    form Markdown or shell syntax.

    Parameters
    ----------
    raw : bytes or str
    limit : int

    Returns
    -------
    str
    """
    text = bytes(raw).decode("latin-1") if isinstance(raw, (bytes, bytearray, memoryview)) else str(raw)
    shown = "".join(c if c in _PLAIN else (f"\\x{ord(c):02x}" if ord(c) < 256 else f"\\u{ord(c):04x}")
                    for c in text[:limit])
    return f"'{shown}{'...' if len(text) > limit else ''}'"


def describe_value(raw):
    """A value from a file's body for an error message: quoted only when it looks numeric.

    Numeric-looking text (digits, signs, points, exponents, ``nan``, ``inf``)
    is quoted through :func:`excerpt`; anything else is described by its
    length only, so a secret or private text read by mistake is never echoed.

    Parameters
    ----------
    raw : bytes or str

    Returns
    -------
    str
    """
    text = bytes(raw).decode("latin-1") if isinstance(raw, (bytes, bytearray, memoryview)) else str(raw)
    if text and len(text) <= EXCERPT and _NUMERIC.fullmatch(text):
        return excerpt(text)
    return f"a {len(text)}-character non-numeric value"


def describe_word(raw, limit=24):
    """A header keyword or name for an error message: quoted when it is a short plain word.

    Letters, digits and ``_ . : -``, at most ``limit`` characters, are quoted;
    anything else is described by its length only.

    Parameters
    ----------
    raw : bytes or str
    limit : int

    Returns
    -------
    str
    """
    text = bytes(raw).decode("latin-1") if isinstance(raw, (bytes, bytearray, memoryview)) else str(raw)
    if text and len(text) <= limit and _WORD.fullmatch(text):
        return f"'{text}'"
    return describe_value(text)


def packed_kind(head):
    """The archive or compression format whose signature starts ``head`` (bytes), else None."""
    return next((kind for magic, kind in _PACKED.items() if bytes(head[:len(magic)]) == magic), None)


def check_text(data):
    """Refuse bytes that are not line-oriented ASCII/UTF-8 text, before any parsing.

    Parameters
    ----------
    data : bytes
        The whole file, or its first block.

    Raises
    ------
    TextFormatError
        Compressed data, a byte-order mark, NUL or other control bytes
        (binary data, UTF-16), old-Mac CR-only line endings, or a line
        longer than :data:`MAX_LINE`.
    """
    kind = packed_kind(data)
    if kind:
        raise TextFormatError(f"{kind}-compressed data, not text; decompress the file first")
    if data[:2] in (b"\xff\xfe", b"\xfe\xff"):
        raise TextFormatError("UTF-16 text is not supported; save the file as ASCII or UTF-8")
    if data[:3] == b"\xef\xbb\xbf":
        raise TextFormatError("the file starts with a UTF-8 byte-order mark; save it without one")
    _scan(data)
    if data.count(b"\r") != data.count(b"\r\n"):
        raise TextFormatError("CR line endings (old Mac text) are not supported; convert them to LF or CRLF")


def _scan(data, block=1 << 24):
    """Refuse control bytes and lines longer than MAX_LINE, block by block (bounded memory)."""
    start, line_start = 0, 0
    while start < len(data):
        chunk = np.frombuffer(data, dtype=np.uint8, count=min(block, len(data) - start), offset=start)
        control = np.flatnonzero(_IS_CONTROL[chunk])
        if len(control):
            at = start + int(control[0])
            what = "a NUL byte" if data[at] == 0 else f"control byte 0x{data[at]:02x}"
            raise TextFormatError(f"{what} at offset {at}: binary data or UTF-16 text, not a text point file")
        ends = np.flatnonzero(chunk == 10) + start
        if len(ends):
            lengths = np.diff(np.concatenate([[line_start], ends + 1]))
            if lengths.max() > MAX_LINE:
                first = int(np.argmax(lengths > MAX_LINE))
                _too_long(data, line_start + int(lengths[:first].sum()))
            line_start = int(ends[-1]) + 1
        start += len(chunk)
        if start - line_start > MAX_LINE:
            _too_long(data, line_start)


def _too_long(data, at):
    line = data.count(b"\n", 0, at) + 1
    raise TextFormatError(f"line {line} is longer than {MAX_LINE} bytes: not a text point file")


def split_lines(data):
    """Split bytes at ``\\n``; joining with ``\\n`` gives the bytes back.

    Parameters
    ----------
    data : bytes

    Returns
    -------
    list of bytes
    """
    return data.split(b"\n")


def _is_skipped(line):
    stripped = line.strip()
    return not stripped or stripped.startswith(b"#")


def parse_coords(tokens, cols, lineno):
    """Three coordinates from a point line's tokens.

    Parameters
    ----------
    tokens : list of bytes
    cols : tuple of 3 int
        Token indices of x, y, z.
    lineno : int
        1-based line number, for the message.

    Returns
    -------
    tuple of 3 float
    """
    try:
        return tuple(float(tokens[c]) for c in cols)
    except ValueError:
        k, bad = next((k, t) for k, t in enumerate(tokens[c] for c in cols) if not _is_float(t))
        raise TextFormatError(f"line {lineno}: coordinate {'xyz'[k]} ({describe_value(bad)}) "
                              "is not a number") from None


def _is_float(token):
    try:
        float(token)
    except ValueError:
        return False
    return True


def read_xyz(data):
    """Parse an XYZ file: one point per line, x y z then any extra columns.

    Parameters
    ----------
    data : bytes

    Returns
    -------
    TextTable
    """
    check_text(data)
    lines = split_lines(data)
    rows, coords, width = [], [], None
    for i, line in enumerate(lines):
        if _is_skipped(line):
            continue
        tokens = line.split()
        width = _check_width(tokens, width, i + 1)
        rows.append(i)
        coords.append(parse_coords(tokens, (0, 1, 2), i + 1))
    return _table(lines, rows, coords)


def _check_width(tokens, width, lineno):
    if width is None:
        if len(tokens) < 3:
            raise TextFormatError(f"line {lineno}: {len(tokens)} columns, a point needs x y z")
        return len(tokens)
    if len(tokens) != width:
        raise TextFormatError(f"line {lineno}: {len(tokens)} columns, the first point line has {width}")
    return width


def _table(lines, rows, coords):
    points = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    return TextTable(lines, np.asarray(rows, dtype=np.int64), (0, 1, 2), points)


def read_pts(data):
    """Parse a PTS file: a count line, then that many ``x y z [i [r g b]]`` lines (repeatable).

    Parameters
    ----------
    data : bytes

    Returns
    -------
    TextTable
    """
    check_text(data)
    lines = split_lines(data)
    rows, coords, width = [], [], None
    left, count_line = None, 0
    for i, line in enumerate(lines):
        if _is_skipped(line):
            continue
        tokens = line.split()
        if not left:
            left, count_line = _count(tokens, i + 1), i + 1
            continue
        width = _check_width(tokens, width, i + 1)
        rows.append(i)
        coords.append(parse_coords(tokens, (0, 1, 2), i + 1))
        left -= 1
    if left is None:
        raise TextFormatError("no point count line (a PTS file starts with the number of points)")
    if left:
        raise TextFormatError(f"line {count_line} declares more points than follow ({left} missing)")
    return _table(lines, rows, coords)


def _count(tokens, lineno):
    if len(tokens) != 1 or not tokens[0].isdigit():
        raise TextFormatError(f"line {lineno}: expected a point count, found {describe_value(b' '.join(tokens))} "
                              "(more point lines than the count declares, or no count line)")
    return int(tokens[0])


def format_coordinate(value, kind):
    """Text for one coordinate.

    Parameters
    ----------
    value : float
    kind : {"f8", "f4", "i"}
        ``f4`` rounds to float32 and writes that value exactly, so readers
        that parse as float32 and as float64 both get it.

    Returns
    -------
    bytes
    """
    if kind == "f4":
        return repr(float(np.float32(value))).encode()
    if kind == "i":
        return str(int(np.rint(value))).encode()
    return repr(float(value)).encode()


def _replace_tokens(line, cols, texts):
    parts = _SEPARATORS.split(line)
    first = 2 if parts[0] == b"" else 0
    for c, text in zip(cols, texts):
        if text is not None:
            parts[first + 2 * c] = text
    return b"".join(parts)


def rewrite_lines(lines, rows, cols, kinds, old, new):
    """Lines with the coordinates that changed rewritten, every other token as it was.

    Parameters
    ----------
    lines : list of bytes
    rows : (n,) int
        Line index of each point.
    cols : tuple of 3 int
        Token index of x, y, z in a point line.
    kinds : tuple of 3 str
        See :func:`format_coordinate`.
    old, new : (n, 3) float64
        Coordinates as read and as to be written.

    Returns
    -------
    bytes
    """
    new = np.asarray(new, dtype=np.float64)
    if new.shape != old.shape:
        raise TextFormatError(f"{new.shape[0]} points given, the file holds {old.shape[0]}")
    out = list(lines)
    moved = new != old
    for k in np.flatnonzero(moved.any(axis=1)).tolist():
        texts = [format_coordinate(v, kind) if m else None
                 for v, kind, m in zip(new[k].tolist(), kinds, moved[k].tolist())]
        out[rows[k]] = _replace_tokens(lines[rows[k]], cols, texts)
    return b"\n".join(out)


def write_text(table, points):
    """Serialise an XYZ or PTS table with new coordinates.

    Parameters
    ----------
    table : TextTable
    points : (n, 3) float

    Returns
    -------
    bytes
    """
    return rewrite_lines(table.lines, table.rows, table.cols, table.kinds, table.points, points)


def _coordinate_lines(points):
    return "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in np.asarray(points, dtype=np.float64).tolist())


def xyz_from_points(points):
    """A new XYZ file of bare coordinates, full precision.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    bytes
    """
    return _coordinate_lines(points).encode()


def pts_from_points(points):
    """A new PTS file (count line, then ``x y z`` lines) of bare coordinates.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    bytes
    """
    return (f"{len(points)}\n" + _coordinate_lines(points)).encode()
