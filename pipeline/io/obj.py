"""Wavefront OBJ: the vertices are the points, the rest of the file is kept byte for byte.

``v x y z``, ``v x y z w``, ``v x y z r g b`` (vertex colours) and
``v x y z w r g b`` lines give the points, in file order.  Writing rewrites
only the x, y, z tokens of vertices that moved (``repr`` of the float64);
``w`` and colour tokens, normals (``vn``), texture coordinates (``vt``),
faces, groups, materials, comments and line endings are untouched.

Faces (``f``) are decoded for :meth:`ObjData.faces`: indices may be
``v``, ``v/vt``, ``v//vn`` or ``v/vt/vn``, positive (1-based) or negative
(relative to the vertices defined so far); polygons are fan-triangulated.
Line continuations (a trailing backslash) are not supported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .text import (TextFormatError, coordinates, describe_value, gather, read_blocks, rewrite_lines, split_lines,
                   whole_text)

__all__ = ["ObjData", "ObjError", "read_obj", "write_obj", "obj_from_points"]

_VERTEX_VALUES = (3, 4, 6, 7)


class ObjError(ValueError):
    """An OBJ file that cannot be read (the message says why and where)."""


@dataclass
class ObjData:
    """An OBJ file as lines, with its vertex coordinates and triangles.

    Attributes
    ----------
    lines : list of bytes
        The file split at ``b"\\n"``.
    rows : (n,) int64
        Line index of each vertex.
    points : (n, 3) float64
    triangles : (f, 3) int64
        Zero-based vertex indices, polygons fan-triangulated.
    """

    lines: list
    rows: np.ndarray
    points: np.ndarray
    triangles: np.ndarray

    def faces(self):
        """(f, 3) int64 triangles (zero-based), empty when the file has no faces."""
        return self.triangles


def read_obj(data):
    """Parse OBJ bytes.

    Every line is checked block by block first (bounded memory); a positive
    face index beyond the last vertex is named once the vertices are counted.

    Parameters
    ----------
    data : bytes or binary file

    Returns
    -------
    ObjData
    """
    try:
        rows, points, triangles = read_blocks(data, _obj_block, _Vertices)
    except TextFormatError as exc:
        raise ObjError(str(exc)) from None
    return ObjData(split_lines(whole_text(data)), rows, points, triangles)


class _Vertices:
    """What a pass over an OBJ carries from block to block."""

    def __init__(self, totals=None):
        self.defined = 0                                     # vertices before the block
        self.n_vertices = None if totals is None else totals[0]
        self.highest = 0                                     # largest positive face index seen

    def finish(self, totals):
        return self.highest > totals[0]


def _obj_block(tokens, state):
    """(rows (k,), points (k, 3), triangles (t, 3)) of a block; the first bad line named."""
    keyword = (tokens.size == 1)
    v = np.flatnonzero(keyword & (tokens.head == ord("v")))
    f = np.flatnonzero(keyword & (tokens.head == ord("f")))
    pending = _first_error([_bad_vertex_lines(tokens, v), _short_faces(tokens, f)])
    if pending is not None:
        v, f = v[v < pending.line - tokens.line], f[f < pending.line - tokens.line]
    try:
        points = coordinates(tokens, v, (1, 2, 3))
    except TextFormatError as exc:
        pending = exc
        f = f[f < exc.line - tokens.line]
    triangles = _triangles(tokens, f, state.defined + np.searchsorted(v, f), state)
    if pending is not None:
        raise pending
    state.defined += len(v)
    return tokens.row + v.astype(np.int64), points, triangles


def _first_error(errors):
    found = [e for e in errors if e is not None]
    return min(found, key=lambda e: e.line) if found else None


def _bad_vertex_lines(tokens, v):
    bad = np.flatnonzero(~np.isin(tokens.count[v] - 1, _VERTEX_VALUES))
    if not len(bad):
        return None
    lineno = tokens.line + int(v[bad[0]])
    return TextFormatError(f"line {lineno}: a vertex has {tokens.count[v[bad[0]]] - 1} values "
                           "(x y z, x y z w, x y z r g b or x y z w r g b expected)", lineno)


def _short_faces(tokens, f):
    bad = np.flatnonzero(tokens.count[f] < 4)
    if not len(bad):
        return None
    lineno = tokens.line + int(f[bad[0]])
    return TextFormatError(f"line {lineno}: a face needs at least 3 vertices, it has {tokens.count[f[bad[0]]] - 1}",
                           lineno)


def _triangles(tokens, f, defined, state):
    """(t, 3) zero-based triangles of the face lines ``f``, fan-triangulated; every index checked.

    ``defined`` (len(f),) counts the vertices defined before each face line.
    Positive indices are checked against ``state.n_vertices`` when it is
    known, else the largest is kept for the end of the pass.
    """
    m = tokens.count[f] - 1                                  # vertex references per face
    offsets = np.cumsum(m) - m
    refs = np.arange(int(m.sum())) + np.repeat(tokens.first[f] + 1 - offsets, m)
    words = gather(tokens.words, refs)
    k = _indices(words, b"/" in tokens.data)
    face = np.repeat(np.arange(len(f)), m)
    before = np.repeat(defined, m)
    index = np.where(k > 0, k - 1, before + k)
    limit = np.inf if state.n_vertices is None else state.n_vertices
    bad = (k == 0) | (index < 0) | (index >= limit) if len(k) else np.zeros(0, dtype=bool)
    if bad.any():
        at = int(np.argmax(bad))
        lineno = tokens.line + int(f[face[at]])
        if k[at] == _NOT_AN_INDEX:
            raise TextFormatError(f"line {lineno}: a face vertex ({describe_value(words[at])}) is not an index",
                                  lineno)
        value = int(words[at].split(b"/", 1)[0])
        raise TextFormatError(f"line {lineno}: face vertex index {value} is out of range "
                              f"({int(before[at])} vertices defined before this line)", lineno)
    state.highest = max(state.highest, int(k.max()) if len(k) else 0)
    n_tri = m - 2
    fan = np.repeat(offsets, n_tri)
    step = np.arange(int(n_tri.sum())) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    return np.stack([index[fan], index[fan + step + 1], index[fan + step + 2]], axis=1).reshape(-1, 3)


_NOT_AN_INDEX = np.iinfo(np.int64).min          # marks a face reference that is not an integer


def _indices(words, slashes=True):
    """(r,) int64 vertex numbers of face references ``v``, ``v/vt``, ``v//vn``, ``v/vt/vn``."""
    heads = [w.split(b"/", 1)[0] for w in words] if slashes else words
    try:
        return np.fromiter(map(int, heads), dtype=np.int64, count=len(heads))
    except (ValueError, OverflowError):
        return np.fromiter(map(_index, heads), dtype=np.int64, count=len(heads))


def _index(head):
    try:
        k = int(head)
    except ValueError:
        return _NOT_AN_INDEX
    return max(min(k, 1 << 62), -(1 << 62))      # out of range either way; the message quotes the token


def write_obj(obj, points):
    """Serialise an OBJ with new vertex coordinates, every other byte unchanged.

    Parameters
    ----------
    obj : ObjData
    points : (n, 3) float

    Returns
    -------
    bytes
    """
    try:
        return rewrite_lines(obj.lines, obj.rows, (1, 2, 3), ("f8",) * 3, obj.points, points)
    except TextFormatError as exc:
        raise ObjError(str(exc)) from None


def obj_from_points(points):
    """A new OBJ of bare vertices (``v x y z`` lines, full precision).

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    bytes
    """
    rows = np.asarray(points, dtype=np.float64).tolist()
    return "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in rows).encode()
