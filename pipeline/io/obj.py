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

from .text import TextFormatError, check_text, describe_value, parse_coords, rewrite_lines, split_lines

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

    Parameters
    ----------
    data : bytes

    Returns
    -------
    ObjData
    """
    try:
        check_text(data)
    except TextFormatError as exc:
        raise ObjError(str(exc)) from None
    lines = split_lines(data)
    rows, coords, polygons = [], [], []
    for i, line in enumerate(lines):
        tokens = line.split()
        if not tokens:
            continue
        if tokens[0] == b"v":
            if len(tokens) - 1 not in _VERTEX_VALUES:
                raise ObjError(f"line {i + 1}: a vertex has {len(tokens) - 1} values "
                               "(x y z, x y z w, x y z r g b or x y z w r g b expected)")
            coords.append(_coords(tokens, i + 1))
            rows.append(i)
        elif tokens[0] == b"f":
            polygons.append((i + 1, len(rows), tokens[1:]))
    triangles = _triangulate(polygons, len(rows))
    points = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    return ObjData(lines, np.asarray(rows, dtype=np.int64), points, triangles)


def _coords(tokens, lineno):
    try:
        return parse_coords(tokens, (1, 2, 3), lineno)
    except TextFormatError as exc:
        raise ObjError(str(exc)) from None


def _triangulate(polygons, n_vertices):
    triangles = []
    for lineno, defined, refs in polygons:
        if len(refs) < 3:
            raise ObjError(f"line {lineno}: a face needs at least 3 vertices, it has {len(refs)}")
        idx = [_vertex_index(ref, defined, n_vertices, lineno) for ref in refs]
        triangles += [(idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1)]
    return np.asarray(triangles, dtype=np.int64).reshape(-1, 3)


def _vertex_index(ref, defined, n_vertices, lineno):
    head = ref.split(b"/", 1)[0]
    try:
        k = int(head)
    except ValueError:
        raise ObjError(f"line {lineno}: a face vertex ({describe_value(ref)}) is not an index") from None
    index = k - 1 if k > 0 else defined + k
    if k == 0 or not 0 <= index < n_vertices:
        raise ObjError(f"line {lineno}: face vertex index {k} is out of range "
                       f"({defined} vertices defined before this line)")
    return index


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
