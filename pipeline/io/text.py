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

Every line is checked in a first pass over blocks of whole lines
(:func:`read_blocks`), which keeps nothing but counts for a large file, so a
refused file costs bounded memory whatever its size; a valid one is then
parsed by the same block function into arrays of the counted size.  The
block helpers (:func:`text_blocks`, :func:`tokenise`, :func:`read_blocks`,
:func:`coordinates`) and :func:`rewrite_lines` are shared with the PCD
(ascii) and OBJ modules.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import re
from dataclasses import dataclass
from operator import itemgetter

import numpy as np

__all__ = ["TextFormatError", "TextTable", "read_xyz", "read_pts", "write_text",
           "xyz_from_points", "pts_from_points", "parse_coords", "rewrite_lines",
           "format_coordinate", "split_lines", "excerpt", "describe_value", "describe_word", "check_text",
           "packed_kind", "MAX_LINE", "Tokens", "tokenise", "text_blocks", "read_blocks", "whole_text",
           "coordinates", "gather", "line_words", "BLOCK", "Window", "CHUNK", "non_finite"]

_SEPARATORS = re.compile(rb"(\s+)")
MAX_LINE = 1 << 20          # bytes; a longer line is not a point line (a binary file, a one-line dump)
EXCERPT = 40                # characters of file content an error message may quote
_PLAIN = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789 .,:;+-_=/()[]{}#@%*~^!?")
_WORD = re.compile(r"[A-Za-z0-9_.:\-]+")
_NUMERIC = re.compile(r"[-+0-9.eE_ ]+|[-+]?(nan|inf|infinity)", re.IGNORECASE)
_PACKED = {b"\x1f\x8b": "gzip", b"PK\x03\x04": "zip", b"\x28\xb5\x2f\xfd": "zstd", b"\xfd7zXZ\x00": "xz",
           b"BZh": "bzip2", b"7z\xbc\xaf\x27\x1c": "7-zip"}
BLOCK = 1 << 20             # bytes of whole lines tokenised at a time (their tokens cost tens of MB at most)
KEEP = 1 << 25              # bytes of parsed arrays the checking pass keeps; beyond, the file is parsed again
_IS_SPACE = np.zeros(256, dtype=bool)
_IS_SPACE[list(b" \t\n\r\x0b\x0c")] = True         # what bytes.split() splits at
_IS_CONTROL = np.zeros(256, dtype=bool)
_IS_CONTROL[sorted(set(range(32)) - set(b"\t\n\r\f\v")) + [0x7F]] = True


class TextFormatError(ValueError):
    """A text point file that cannot be read (the message says why and where).

    ``line`` is the 1-based line it names, when it names one.
    """

    def __init__(self, message, line=None):
        super().__init__(message)
        self.line = line


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
    text = _as_text(raw)
    shown = "".join(c if c in _PLAIN else (f"\\x{ord(c):02x}" if ord(c) < 256 else f"\\u{ord(c):04x}")
                    for c in text[:limit])
    return f"'{shown}{'...' if len(text) > limit else ''}'"


def _as_text(raw):
    """Bytes (each byte one character) or any value, as text."""
    return bytes(raw).decode("latin-1") if isinstance(raw, (bytes, bytearray, memoryview)) else str(raw)


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
    text = _as_text(raw)
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
    text = _as_text(raw)
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
    _check_start(data)
    _check_lines(data)


def _check_start(data):
    kind = packed_kind(data)
    if kind:
        raise TextFormatError(f"{kind}-compressed data, not text; decompress the file first")
    if data[:2] in (b"\xff\xfe", b"\xfe\xff"):
        raise TextFormatError("UTF-16 text is not supported; save the file as ASCII or UTF-8")
    if data[:3] == b"\xef\xbb\xbf":
        raise TextFormatError("the file starts with a UTF-8 byte-order mark; save it without one")


def _check_lines(data, offset=0, line=1):
    """Control bytes, long lines and CR-only endings in ``data``, which starts at byte ``offset``, line ``line``."""
    _scan(data, offset=offset, line=line)
    if data.count(b"\r") != data.count(b"\r\n"):
        raise TextFormatError("CR line endings (old Mac text) are not supported; convert them to LF or CRLF")


def _scan(data, block=1 << 24, offset=0, line=1):
    """Refuse control bytes and lines longer than MAX_LINE, block by block (bounded memory)."""
    start, line_start = 0, 0
    while start < len(data):
        chunk = np.frombuffer(data, dtype=np.uint8, count=min(block, len(data) - start), offset=start)
        control = np.flatnonzero(_IS_CONTROL[chunk])
        if len(control):
            at = start + int(control[0])
            what = "a NUL byte" if data[at] == 0 else f"control byte 0x{data[at]:02x}"
            raise TextFormatError(f"{what} at offset {offset + at}: binary data or UTF-16 text, "
                                  "not a text point file")
        ends = np.flatnonzero(chunk == 10) + start
        if len(ends):
            lengths = np.diff(np.concatenate([[line_start], ends + 1]))
            if lengths.max() > MAX_LINE:
                first = int(np.argmax(lengths > MAX_LINE))
                _too_long(line + data.count(b"\n", 0, line_start + int(lengths[:first].sum())))
            line_start = int(ends[-1]) + 1
        start += len(chunk)
        if start - line_start > MAX_LINE:
            _too_long(line + data.count(b"\n", 0, line_start))


def _too_long(line):
    raise TextFormatError(f"line {line} is longer than {MAX_LINE} bytes: not a text point file", line)


def _reader(source, start):
    """``read(n)`` over bytes or a binary file, from byte ``start``."""
    if hasattr(source, "read"):
        source.seek(start)
        return source.read
    view, at = memoryview(source), start

    def read(n):
        nonlocal at
        chunk = bytes(view[at:at + n])
        at += len(chunk)
        return chunk
    return read


def whole_text(source, start=0):
    """The bytes of ``source`` (bytes or a binary file) from byte ``start`` on."""
    return _reader(source, start)(-1) if hasattr(source, "read") else bytes(memoryview(source)[start:])


CHUNK = 1 << 25             # bytes of a binary body held at a time by a checking pass


class Window:
    """A binary body one window at a time, through one reused buffer (never a copy of the whole body).

    ``buf[lo:hi]`` holds the body's bytes not yet consumed that have been
    read; a reader consumes by advancing ``lo`` and calls :meth:`fill` for
    more.  Files are read with ``readinto`` (no ``mmap``: mapped pages
    count as resident memory).

    Parameters
    ----------
    source : bytes or binary file
    start : int
        Byte offset of the body in ``source``.
    size : int
        Bytes of the buffer; a record a reader needs whole must be shorter.
    """

    def __init__(self, source, start, size=CHUNK):
        if hasattr(source, "readinto"):
            source.seek(start)
            self._readinto = source.readinto
        else:
            self._readinto = _view_reader(memoryview(source)[start:])
        self.buf = bytearray(size)
        self.lo = self.hi = 0
        self.read = 0               # body bytes read so far (consumed: ``read - (hi - lo)``)

    @property
    def consumed(self):
        return self.read - (self.hi - self.lo)

    def fill(self):
        """Move the unconsumed bytes to the front and read more; False when the body has no more."""
        keep = self.hi - self.lo
        if self.lo:
            self.buf[:keep] = self.buf[self.lo:self.hi]
        self.lo, self.hi, got = 0, keep, 0
        view = memoryview(self.buf)
        while self.hi < len(self.buf):
            n = self._readinto(view[self.hi:])
            if not n:
                break
            self.hi, got = self.hi + n, got + n
        view.release()
        self.read += got
        return got > 0

    def need(self, n):
        """Whether ``n`` unconsumed bytes are (or could be made) available."""
        while self.hi - self.lo < n:
            if not self.fill():
                return False
        return True


def _view_reader(view):
    """``readinto(buffer)`` over a memoryview, as a file's."""
    at = 0

    def readinto(out):
        nonlocal at
        n = min(len(out), len(view) - at)
        out[:n] = view[at:at + n]
        at += n
        return n
    return readinto


def file_head(data, n):
    """(the first ``n`` bytes of an open binary file, or all of ``data`` given as bytes; its whole length)."""
    if not hasattr(data, "read"):
        return data, len(data)
    data.seek(0)
    return data.read(n), os.fstat(data.fileno()).st_size


def non_finite(records, names=("x", "y", "z")):
    """(count, first index) of the records whose fields ``names`` are not all finite; first is -1 when none.

    Parameters
    ----------
    records : (k,) structured array
    """
    with np.errstate(invalid="ignore"):       # a signalling NaN is counted like any NaN
        ok = np.ones(len(records), dtype=bool)
        for name in names:
            if records.dtype[name].kind == "f":
                ok &= np.isfinite(records[name])
    bad = np.flatnonzero(~ok)
    return len(bad), int(bad[0]) if len(bad) else -1


def text_blocks(source, start=0, line=1, size=BLOCK):
    """Whole lines of a text body, about ``size`` bytes at a time, each block checked as text.

    Parameters
    ----------
    source : bytes or binary file
    start : int
        Byte offset of the body in ``source``.
    line : int
        1-based line number of the body's first line in the file.

    Yields
    ------
    block : bytes
        Whole lines (the last block's last line may lack its ``\\n``).
    line : int
        1-based file line number of the block's first line.
    row : int
        0-based index of that line within the body.

    Raises
    ------
    TextFormatError
        As :func:`check_text`, naming the file's offset or line.
    """
    read, carry, offset, row = _reader(source, start), b"", start, 0
    while True:
        chunk = read(size)
        if not chunk:
            break
        data = carry + chunk if carry else chunk
        cut = data.rfind(b"\n") + 1
        if not cut and len(data) > MAX_LINE:
            _too_long(line)
        block, carry = data[:cut], data[cut:]
        if block:
            yield _checked(block, offset, line, row)
            n = block.count(b"\n")
            offset, line, row = offset + len(block), line + n, row + n
    if carry:
        yield _checked(carry, offset, line, row)


def _checked(block, offset, line, row):
    if row == 0:
        _check_start(block)
    _check_lines(block, offset, line)
    return block, line, row


@dataclass
class Tokens:
    """The white-space separated tokens of a block of whole lines.

    Attributes
    ----------
    words : list of bytes
        Every token of the block, in order, (t,).
    count : (m,) int64
        Tokens on each line.
    first : (m,) int64
        Index into ``words`` of each line's first token.
    head : (m,) uint8
        First byte of each line's first token (0 on an empty line).
    size : (m,) int64
        Length of each line's first token (0 on an empty line).
    line : int
        1-based file line number of the block's first line.
    row : int
        0-based index of the block's first line within the body.
    data : bytes
        The block itself.
    """

    words: list
    count: np.ndarray
    first: np.ndarray
    head: np.ndarray
    size: np.ndarray
    line: int = 1
    row: int = 0
    data: bytes = b""


def tokenise(block, line=1, row=0):
    """Split a block of whole lines into tokens, with their per-line counts (vectorised).

    Parameters
    ----------
    block : bytes
    line, row : int
        See :class:`Tokens`.

    Returns
    -------
    Tokens
    """
    a = np.frombuffer(block, dtype=np.uint8)
    space = _IS_SPACE[a]
    begin, end = ~space, ~space
    begin[1:] &= space[:-1]
    end[:-1] &= space[1:]
    starts, ends = np.flatnonzero(begin), np.flatnonzero(end) + 1
    newlines = np.flatnonzero(a == 10)
    n_lines = len(newlines) + int(len(a) > 0 and a[-1] != 10)
    count = np.bincount(np.searchsorted(newlines, starts), minlength=n_lines).astype(np.int64)
    first = np.cumsum(count) - count
    head, size = np.zeros(n_lines, dtype=np.uint8), np.zeros(n_lines, dtype=np.int64)
    has = np.flatnonzero(count)
    head[has], size[has] = a[starts[first[has]]], (ends - starts)[first[has]]
    return Tokens(block.split(), count, first, head, size, line, row, block)


def gather(words, idx):
    """``[words[i] for i in idx]``, the loop in C.

    Parameters
    ----------
    words : list
    idx : (k,) int

    Returns
    -------
    sequence of k items
    """
    idx = idx.tolist()
    return itemgetter(*idx)(words) if len(idx) > 1 else [words[i] for i in idx]


def coordinates(tokens, lines, cols):
    """Three coordinates from each of some lines of a block, parsed as Python floats.

    Parameters
    ----------
    tokens : Tokens
    lines : (k,) int
        Line indices within the block, increasing.
    cols : tuple of 3 int
        Token indices of x, y, z within a line.

    Returns
    -------
    (k, 3) float64

    Raises
    ------
    TextFormatError
        Naming the first line (and coordinate) that is not a number.
    """
    n = len(lines)
    if n and n == len(tokens.count) and len(tokens.words) == n * int(tokens.count[0]) and \
            (tokens.count == tokens.count[0]).all():          # every line a point line, all as wide: slices
        width = int(tokens.count[0])
        words = tokens.words if width == 3 and tuple(cols) == (0, 1, 2) else \
            [w for column in zip(*(tokens.words[c::width] for c in cols)) for w in column]
    else:
        words = gather(tokens.words, (tokens.first[lines][:, None] + np.asarray(cols, dtype=np.int64)).ravel())
    try:
        return np.fromiter(map(float, words), dtype=np.float64, count=3 * n).reshape(-1, 3)
    except ValueError:
        k = next(k for k, w in enumerate(words) if not _is_float(w))
        lineno = tokens.line + int(lines[k // 3])
        raise TextFormatError(f"line {lineno}: coordinate {'xyz'[k % 3]} ({describe_value(words[k])}) "
                              "is not a number", lineno) from None


def line_words(tokens, j):
    """The tokens of line ``j`` of a block (list of bytes)."""
    a = int(tokens.first[j])
    return tokens.words[a:a + int(tokens.count[j])]


def _parts(source, parse, state, start, line):
    """``parse(tokens, state)`` of every block of ``source``; one part of empty arrays for an empty body."""
    empty = True
    for block, first, row in text_blocks(source, start, line):
        empty = False
        yield parse(tokenise(block, first, row), state)
    if empty:
        yield parse(tokenise(b"", line, 0), state)


# set by :func:`refusing_repeats`: the checking pass counts distinct coordinates as it goes
_REPEATS = contextvars.ContextVar("pointmark_repeats", default=None)


class _Distinct:
    """Distinct (x, y, z) rows seen so far, exactly, while they are fewer than ``limit``."""

    def __init__(self, max_share, limit=1 << 16):
        self.max_share, self.limit, self.n, self.rows = max_share, limit, 0, np.empty((0, 3))

    def add(self, points):
        self.n += len(points)
        if self.rows is not None:
            rows = np.unique(np.concatenate([self.rows, points]), axis=0)   # as check_distinct counts
            self.rows = rows if len(rows) < self.limit else None                  # too many to count

    def check(self):
        """Raise when more than ``max_share`` of the points surely repeat another (counted exactly)."""
        if self.rows is None or self.n < 2:
            return
        repeats = self.n - len(self.rows)
        if len(self.rows) == 1:
            raise TextFormatError(f"all points are identical ({repeats} of {self.n} points repeat another "
                                  f"point's coordinates; the bounding box has zero size)")
        if repeats > self.max_share * self.n:
            raise TextFormatError(f"{repeats} of {self.n} points repeat another point's coordinates (at most "
                                  f"{self.max_share:.0%} may); remove duplicate points before watermarking")


@contextlib.contextmanager
def refusing_repeats(max_share):
    """Inside the block, text readers refuse, at the end of their checking pass and before any
    full parse, a body in which more than ``max_share`` of the points repeat (when few enough
    distinct points make that exact): a file of identical points costs blocks, not its size."""
    token = _REPEATS.set(max_share)
    try:
        yield
    finally:
        _REPEATS.reset(token)


def read_blocks(source, parse, new_state, *, start=0, line=1):
    """Check every line of a text body block by block, then return its parsed arrays.

    The first pass keeps what ``parse`` returns only while it is under
    :data:`KEEP` bytes, so a file refused near its end has cost one block's
    memory; a larger valid file is parsed again, by the same function, into
    arrays of the counted size.

    Parameters
    ----------
    source : bytes or binary file
    parse : callable
        ``parse(tokens, state)`` -> tuple of arrays for one block (each
        ``(k, ...)``); raises :class:`TextFormatError` for a bad line.
    new_state : callable
        ``new_state(totals)`` -> a fresh state (``totals``: None in the
        first pass, else the array lengths it counted).  ``state.finish(totals)``
        raises for what only the end can tell, or returns True when a check
        needs the totals (a pass with them then names the line).
    start, line : int
        The body's byte offset and first line number.

    Returns
    -------
    list of arrays
    """
    state = new_state(None)
    totals, kept, held = None, [], 0
    share = _REPEATS.get()
    distinct = _Distinct(share) if share is not None else None
    for part in _parts(source, parse, state, start, line):
        if distinct is not None:      # the coordinates: the part's (k, 3) float array
            for p in part:
                if p.dtype.kind == "f" and p.ndim == 2 and p.shape[1] == 3:
                    distinct.add(p)
                    break
        totals = [len(p) for p in part] if totals is None else [t + len(p) for t, p in zip(totals, part)]
        held += sum(p.nbytes for p in part)
        if held > KEEP:
            kept = None
        elif kept is not None:
            kept.append(part)
    if state.finish(totals):
        for _ in _parts(source, parse, new_state(totals), start, line):
            pass
        raise TextFormatError("the file changed while it was read")
    if distinct is not None:
        distinct.check()
    if kept is not None:
        return [np.concatenate(arrays) for arrays in zip(*kept)]
    return _filled(_parts(source, parse, new_state(totals), start, line), totals)


def _filled(parts, totals):
    """The parts' arrays copied into arrays of the counted lengths."""
    out, at = None, [0] * len(totals)
    for part in parts:
        out = out or [np.empty((n,) + p.shape[1:], dtype=p.dtype) for n, p in zip(totals, part)]
        for k, p in enumerate(part):
            if at[k] + len(p) > totals[k]:
                raise TextFormatError("the file changed while it was read")
            out[k][at[k]:at[k] + len(p)] = p
            at[k] += len(p)
    if at != totals:
        raise TextFormatError("the file changed while it was read")
    return out


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
    data : bytes or binary file

    Returns
    -------
    TextTable
    """
    rows, points = read_blocks(data, _xyz_block, _Points)
    return TextTable(split_lines(whole_text(data)), rows, (0, 1, 2), points)


class _Points:
    """What a pass over an XYZ or PTS file carries from block to block."""

    def __init__(self, totals=None):
        self.width = None                       # columns of the first point line
        self.left, self.count_line = None, 0    # PTS: points still due after the count line

    def finish(self, totals):
        return False


class _PtsPoints(_Points):
    def finish(self, totals):
        if self.left is None:
            raise TextFormatError("no point count line (a PTS file starts with the number of points)")
        if self.left:
            raise TextFormatError(f"line {self.count_line} declares more points than follow "
                                  f"({self.left} missing)", self.count_line)
        return False


def _data_lines(tokens):
    """(k,) indices of a block's lines that hold data: not blank, not a ``#`` comment."""
    return np.flatnonzero((tokens.count > 0) & (tokens.head != ord("#")))


def _xyz_block(tokens, state):
    return _point_lines(tokens, _data_lines(tokens), state)


def _point_lines(tokens, lines, state, pending=None):
    """(rows (k,) int64, points (k, 3)) of a block's point lines; every line as wide as the first.

    ``pending`` is an error found at a later line of the block: it is raised
    once the lines before it are checked, so the first bad line is the one named.
    """
    if state.width is None and len(lines):
        n = int(tokens.count[lines[0]])
        if n < 3:
            raise TextFormatError(f"line {tokens.line + lines[0]}: {n} columns, a point needs x y z",
                                  tokens.line + int(lines[0]))
        state.width = n
    wrong = np.flatnonzero(tokens.count[lines] != state.width)
    if len(wrong):
        at = int(lines[wrong[0]])
        lineno = tokens.line + at
        if pending is None or lineno < pending.line:
            pending = TextFormatError(f"line {lineno}: {tokens.count[at]} columns, the first point line has "
                                      f"{state.width}", lineno)
    if pending is not None:
        lines = lines[lines < pending.line - tokens.line]
    points = coordinates(tokens, lines, (0, 1, 2))
    if pending is not None:
        raise pending
    return tokens.row + lines.astype(np.int64), points


def read_pts(data):
    """Parse a PTS file: a count line, then that many ``x y z [i [r g b]]`` lines (repeatable).

    Parameters
    ----------
    data : bytes or binary file

    Returns
    -------
    TextTable
    """
    rows, points = read_blocks(data, _pts_block, _PtsPoints)
    return TextTable(split_lines(whole_text(data)), rows, (0, 1, 2), points)


def _pts_block(tokens, state):
    """Count lines and the point lines each announces, across block ends."""
    lines, runs, p, pending = _data_lines(tokens), [], 0, None
    words, first, single = tokens.words, tokens.first[lines].tolist(), (tokens.count[lines] == 1).tolist()
    while p < len(lines):
        if not state.left:
            word = words[first[p]]
            if not (single[p] and word.isdigit()):
                j = int(lines[p])
                pending = TextFormatError("", tokens.line + j)
                try:
                    _count(line_words(tokens, j), tokens.line + j)
                except TextFormatError as exc:
                    pending = exc
                break
            state.left, state.count_line, p = int(word), tokens.line + int(lines[p]), p + 1
            continue
        take = min(state.left, len(lines) - p)
        runs.append((p, take))
        state.left, p = state.left - take, p + take
    start, n = (np.asarray(c, dtype=np.int64) for c in zip(*runs)) if runs else (np.zeros(0, np.int64),) * 2
    taken = lines[np.arange(int(n.sum())) + np.repeat(start - (np.cumsum(n) - n), n)]
    return _point_lines(tokens, taken, state, pending)


def _count(tokens, lineno):
    if len(tokens) != 1 or not tokens[0].isdigit():
        raise TextFormatError(f"line {lineno}: expected a point count, found {describe_value(b' '.join(tokens))} "
                              "(more point lines than the count declares, or no count line)", lineno)
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
