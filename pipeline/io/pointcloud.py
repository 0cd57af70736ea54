"""Point-cloud files: read, check, and write atomically in the input's own format.

PLY through :mod:`pipeline.io.ply` (every vertex property kept), PCD
through :mod:`pipeline.io.pcd` (every field, its type and the encoding kept),
XYZ and PTS through :mod:`pipeline.io.text`, OBJ through
:mod:`pipeline.io.obj` (only coordinate tokens rewritten), glTF and GLB
through :mod:`pipeline.io.gltf` (only POSITION bytes rewritten), LAS and LAZ
through laspy (header scale and offset and every point record kept).
Coordinates come back as float64 in the file's own frame, in file order.
Writes go to a temporary name in the target folder and are renamed into
place; an input is never overwritten.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import math
import os
import re
import stat
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import gltf as gltf_io
from . import pcd as pcd_io
from . import ply as ply_io
from .obj import obj_from_points, read_obj, write_obj
from .pcd import pcd_from_points, read_pcd, write_pcd
from .ply import PlyError, read_ply, write_ply
from .text import (check_text, excerpt, packed_kind, pts_from_points, read_pts, read_xyz, refusing_repeats, write_text,
                   xyz_from_points)

__all__ = ["PointCloud", "InputError", "WriteError", "read_points", "read_coordinates", "write_points", "write_array",
           "check_output",
           "check_distinct",
           "atomic_write_bytes", "sha256_file", "FORMATS"]

FORMATS = {".ply": "ply", ".pcd": "pcd", ".xyz": "xyz", ".pts": "pts", ".las": "las", ".laz": "laz",
           ".obj": "obj", ".glb": "glb", ".gltf": "gltf"}
_READERS = {"pcd": read_pcd, "xyz": read_xyz, "pts": read_pts, "obj": read_obj}
_WRITERS = {"pcd": write_pcd, "xyz": write_text, "pts": write_text, "obj": write_obj,
            "glb": gltf_io.write_gltf, "gltf": gltf_io.write_gltf}
_NEW_FILES = {"pcd": pcd_from_points, "xyz": xyz_from_points, "pts": pts_from_points, "obj": obj_from_points,
              "glb": gltf_io.glb_from_points, "gltf": gltf_io.gltf_from_points}


class InputError(ValueError):
    """A file that cannot be used; the message names the file and the problem."""


class WriteError(InputError, OSError):
    """A write that failed in the OS (a full disk, a refused permission); the message names the file.

    Also an ``OSError``, so callers that fall back on a failed write (the
    basis store's stand-in) still see one.
    """


@dataclass
class PointCloud:
    """Coordinates of a point-cloud file plus what is needed to write it back.

    Attributes
    ----------
    points : (n, 3) float64
    path : pathlib.Path
    format : str
    native : object
        PlyData, PcdData, TextTable (XYZ, PTS), ObjData, GltfData or laspy.LasData.
    """

    points: np.ndarray
    path: Path
    format: str
    native: object

    def faces(self):
        """(f, 3) int triangles when the file is a PLY, OBJ or glTF mesh, else empty."""
        if self.format in ("ply", "obj", "glb", "gltf"):
            return self.native.faces()
        return np.zeros((0, 3), dtype=np.int64)

    def units(self):
        """:class:`Units` of this file: its format, and for LAS/LAZ its unit and rounding."""
        return _las_units(self.format, self.native.header) if self.format in ("las", "laz") else Units(self.format)


@dataclass(frozen=True)
class Units:
    """What a file says about its coordinates, for the choice of parameters.

    Attributes
    ----------
    format : str
    unit_m : float or None
        Metres per coordinate unit, when the file's coordinate system names it.
    rounding : float
        Farthest the file's precision can move a point (LAS/LAZ: half the
        diagonal of its scale), in its units.
    step : float
        The coarsest step of the file's coordinates (LAS/LAZ: its largest
        scale); 0 for floating point.
    geographic : bool
        The coordinate system is geographic (longitude and latitude in
        degrees): no linear unit, so no rule in metres applies.
    """

    format: str
    unit_m: float | None = None
    rounding: float = 0.0
    step: float = 0.0
    geographic: bool = False


def _las_units(fmt, header):
    scales = np.asarray(header.scales, dtype=np.float64)
    return Units(fmt, las_unit_m(header), float(0.5 * np.sqrt((scales**2).sum())), float(scales.max()),
                 las_geographic(header))


def units_of(path):
    """:class:`Units` of a file, from a LAS/LAZ header alone (other formats: the format only).

    An unreadable LAS/LAZ file gets no unit; :func:`read_points` refuses it later with its reason.
    """
    import laspy

    fmt = format_of(path)
    if fmt not in ("las", "laz"):
        return Units(fmt)
    try:
        with _native_stderr_held(), laspy.open(str(path)) as reader:
            return _las_units(fmt, reader.header)
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException:  # noqa: BLE001 (laspy's decoders raise many types)
        return Units(fmt)


# EPSG linear units: metre, foot, US survey foot
_EPSG_UNITS = {9001: 1.0, 9002: 0.3048, 9003: 1200 / 3937}


def _records(header):
    """A LAS header's VLRs and (LAS 1.4) EVLRs."""
    return list(getattr(header, "vlrs", None) or []) + list(getattr(header, "evlrs", None) or [])


def _geo_keys(header):
    """{GeoTIFF key id: value} of the header's GeoKeyDirectory (the first value of each key)."""
    keys = {}
    for vlr in _records(header):
        for key in getattr(vlr, "geo_keys", None) or ():
            keys.setdefault(int(key.id), int(key.value_offset))
    return keys


def _horizontal_wkt(header):
    """The horizontal part of the header's WKT (WKT1 or WKT2; the vertical CRS cut off), or None."""
    for vlr in _records(header):
        text = getattr(vlr, "string", None)
        if isinstance(text, bytes):
            text = text.decode("latin-1")
        if isinstance(text, str) and re.search(r"\b(PROJCS|PROJCRS|PROJECTEDCRS|GEOGCS|GEOGCRS|GEOGRAPHICCRS|GEODCRS"
                                               r"|GEODETICCRS)\[", text):
            return re.split(r"\b(?:VERT_CS|VERTCRS|VERTICALCRS)\[", text)[0]
    return None


_PROJECTED_WKT = r"\b(PROJCS|PROJCRS|PROJECTEDCRS)\["


def las_geographic(header):
    """True when a LAS header's coordinate system is geographic (degrees): GeoTIFF or WKT.

    GeoTIFF: GTModelTypeGeoKey (1024) = 2, or geographic keys (2048
    GeographicType, 2054 GeogAngularUnits) without projected ones (3072 and
    later) nor model type 1. WKT: GEOGCS (WKT1) or GEOGCRS / a GEODCRS with
    an ellipsoidal coordinate system (WKT2), not inside a projected CRS.
    """
    keys = _geo_keys(header)
    if keys.get(1024) == 2:
        return True
    if keys and keys.get(1024) is None and any(k in keys for k in (2048, 2054)) \
            and not any(k >= 3072 for k in keys):
        return True
    text = _horizontal_wkt(header)
    if text is None or re.search(_PROJECTED_WKT, text):
        return False
    if re.search(r"\b(GEOGCS|GEOGCRS|GEOGRAPHICCRS)\[", text):
        return True
    return bool(re.search(r"\b(GEODCRS|GEODETICCRS)\[", text) and re.search(r"CS\[\s*ellipsoidal", text, re.I))


def las_unit_m(header):
    """Metres per horizontal unit of a LAS header (GeoTIFF ProjLinearUnits, else the WKT), or None.

    VLRs and LAS 1.4 EVLRs are read; WKT1 (the last ``UNIT`` of a PROJCS)
    and WKT2 (the last ``LENGTHUNIT`` of a PROJCRS). A geographic system
    has no linear unit (None; :func:`las_geographic` says so).
    """
    keys = _geo_keys(header)
    if keys.get(3076) in _EPSG_UNITS:
        return _EPSG_UNITS[keys[3076]]
    if las_geographic(header):
        return None
    text = _horizontal_wkt(header)
    if text is None or not re.search(_PROJECTED_WKT, text):
        return None
    wkt2 = re.search(r"\b(PROJCRS|PROJECTEDCRS)\[", text)
    pattern = r'LENGTHUNIT\["[^"]*",\s*([0-9.eE+-]+)' if wkt2 else r'(?<![A-Z])UNIT\["[^"]*",\s*([0-9.eE+-]+)'
    found = re.findall(pattern, text)
    if not found:
        return None
    try:
        value = float(found[-1])
    except ValueError:
        return None
    return value if math.isfinite(value) and value > 0 else None


def format_of(path):
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise InputError(f"{path}: unknown point-cloud format {suffix!r} (use one of {sorted(FORMATS)})")
    return FORMATS[suffix]


def read_points(path, *, distinct=False):
    """Read a point-cloud file and check its coordinates.

    Parameters
    ----------
    path : str or Path
    distinct : bool
        Also refuse a file in which more than :data:`MAX_REPEATED_SHARE` of the
        points repeat another (what :func:`check_distinct` refuses), in a
        text body's checking pass when few distinct points make the count
        exact: such a file is refused in bounded memory.  For originals to
        watermark; a suspect may repeat points (a quantised leak).  A glTF
        original that cannot be written back (Draco, meshopt) is refused too.

    Returns
    -------
    PointCloud

    Raises
    ------
    InputError
        Missing, unreadable, empty, truncated or non-finite files.
    """
    path = Path(path)
    fmt = format_of(path)
    with _open_input(path) as f:
        size = os.fstat(f.fileno()).st_size
        try:
            _check_head(fmt, f.read(HEAD_BYTES), size)
            if fmt in ("las", "laz"):
                native, points = _read_las(path)
            elif fmt in ("glb", "gltf"):
                native = gltf_io.read_gltf(f, path, original=distinct)
                points = native.points
            else:
                with refusing_repeats(MAX_REPEATED_SHARE) if distinct else contextlib.nullcontext():
                    native = read_ply(f) if fmt == "ply" else _READERS[fmt](f)  # text: checked block by block
                points = native.points
        except OSError as exc:
            raise InputError(f"{path}: cannot read: {_reason(exc)}") from None
        except (PlyError, ValueError) as exc:
            raise InputError(f"{path}: {exc}") from None
    _check(path, points)
    return PointCloud(points, path, fmt, native)


HEAD_BYTES = max(ply_io.MAX_HEADER, pcd_io.MAX_HEADER) + 64   # read and checked before the body


def _check_head(fmt, head, size):
    """Magic, header and declared sizes from the file's first bytes, before its body is read.

    Raises
    ------
    ValueError
        A compressed or empty file, the wrong magic, a header that disagrees
        with the file's length, or (text formats) a first block that is not text.
    """
    if size == 0:
        raise ValueError("the file is empty")
    kind = packed_kind(head)
    if kind:
        raise ValueError(f"{kind}-compressed data, not a {fmt.upper()} file; decompress it first")
    if fmt == "ply":
        ply_io.check_head(head, size)
    elif fmt == "pcd":
        pcd_io.check_head(head, size)
    elif fmt in ("xyz", "pts", "obj"):
        check_text(head)
    elif fmt in ("glb", "gltf"):
        gltf_io.check_head(fmt, head, size)
    elif head[:4] != b"LASF":
        raise ValueError("not a LAS/LAZ file (no 'LASF' signature)")


class _open_input:
    """Open a point-set file for reading: a regular file, never a folder, FIFO or device.

    Opened without blocking, then checked on the open descriptor, so a FIFO
    swapped in after the check cannot make the read wait forever.
    """

    def __init__(self, path):
        self.path = Path(path)

    def __enter__(self):
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
        except OSError as exc:
            raise InputError(f"{self.path}: {self._why(exc)}") from None
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            os.close(fd)
            what = "is a folder, not a point-set file" if stat.S_ISDIR(mode) else \
                "not a regular file (a FIFO, socket or device); give a point-set file"
            raise InputError(f"{self.path}: {what}")
        os.set_blocking(fd, True)
        self.file = os.fdopen(fd, "rb")
        return self.file

    def __exit__(self, exc_type, exc, tb):
        self.file.close()
        return False

    def _why(self, exc):
        if exc.errno == errno.ENOENT:
            return "a broken link (its target does not exist)" if self.path.is_symlink() else "no such file"
        if exc.errno == errno.ELOOP:
            return "symlink loop"
        if exc.errno == errno.EISDIR:
            return "is a folder, not a point-set file"
        return _reason(exc)


def _reason(exc):
    """The OS's words for an error (``no space left on device``), without the path or errno."""
    return (os.strerror(exc.errno) if exc.errno else str(exc)).lower()


def _check(path, points):
    if len(points) == 0:
        raise InputError(f"{path}: the file holds no points")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise InputError(f"{path}: {int(bad.sum())} points have NaN or infinite coordinates "
                         f"(first at index {int(np.flatnonzero(bad)[0])})")


# A LAZ file expands to at most this many times its length (LASzip reaches
# about 10): a larger declared point count is corrupt, and is refused before
# anything is allocated for it.
_LAZ_MAX_RATIO = 1000


def check_output(source, output, *, same_format=True):
    """Refuse an output path before any work is done on ``source``.

    The output must name a file (not a folder) with a known suffix, in a
    folder that exists or can be created and is writable, must not be the
    source itself (also through a link), and with ``same_format`` must have
    the source's format.

    Raises
    ------
    InputError
        Naming the output and the problem.
    """
    source, output = Path(source), Path(output)
    if output.is_dir():
        raise InputError(f"{output}: is a folder; give the output file's name")
    src_fmt = format_of(source)
    fmt = format_of(output)
    if same_format:
        if fmt != src_fmt:
            raise InputError(f"{output}: output format {fmt} differs from the input format {src_fmt} "
                             f"(use the suffix {Path(source).suffix})")
    if output.exists() and source.exists() and os.path.samefile(output, source):
        raise InputError(f"{output}: refusing to overwrite the original")
    if os.path.realpath(output) == os.path.realpath(source):     # realpath: no error on a link loop
        raise InputError(f"{output}: refusing to overwrite the original")
    parent = output.parent
    while not parent.exists():
        if parent.is_symlink():
            raise InputError(f"{output}: its folder {parent} is a broken link")
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"{output}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{output}: the folder {parent} is not writable")


# Repeats beyond this share of the points are refused: a doubled or merged
# export, not the few coincident points that rounding to a grid produces.
MAX_REPEATED_SHARE = 0.01


def check_distinct(path, points, max_share=MAX_REPEATED_SHARE):
    """Refuse a point set in which many points are stored more than once.

    Embedding moves every point by its own spectral coefficients: the copies
    of a point are pulled apart, and a file in which every point is present
    twice comes out as two interleaved surfaces whose payload does not read
    back cleanly.  A few repeats (coordinates rounded to a LAS scale or to
    float32 far from the origin) are harmless and are watermarked.

    Raises
    ------
    InputError
        When more than ``max_share`` of the points repeat another one.
    """
    _, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    repeats = len(points) - len(first)
    if len(first) == 1 and len(points) > 1:
        raise InputError(f"{path}: all points are identical ({repeats} of {len(points)} points repeat another "
                         f"point's coordinates; the bounding box has zero size)")
    if repeats > max_share * len(points):
        earliest = first[np.asarray(inverse).reshape(-1)]
        twin = int(np.flatnonzero(earliest != np.arange(len(points)))[0])
        original = int(earliest[twin])
        raise InputError(f"{path}: {repeats} of {len(points)} points repeat another point's coordinates "
                         f"(point {twin} = point {original}; at most {max_share:.0%} may); "
                         f"remove duplicate points before watermarking")


def _read_las(path):
    import laspy

    size = path.stat().st_size
    with open(path, "rb") as f:
        n_chunks = _check_las_block(f, size)
    try:
        with _native_stderr_held(), laspy.open(str(path)) as reader:
            _check_las_header(reader.header, size, n_chunks)
            las = _read_laz(reader) if reader.header.are_points_compressed else reader.read()
    except ValueError:
        raise
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as exc:  # laspy raises many types; the LAZ decoder's Rust panics are BaseExceptions
        raise ValueError(f"cannot read LAS/LAZ: {_library_message(exc)}") from None
    if len(las.points) != las.header.point_count:
        raise ValueError(f"the header declares {las.header.point_count} points, "
                         f"{len(las.points)} could be read")
    _check_las_writable(las.header)
    points = np.column_stack([np.asarray(las.x, dtype=np.float64),
                              np.asarray(las.y, dtype=np.float64),
                              np.asarray(las.z, dtype=np.float64)])
    return las, points


def _library_message(exc, limit=160):
    """A library's error text on one line, cut short, with characters that could form markup escaped."""
    text = " ".join(str(exc).split())
    return excerpt(text, limit)[1:-1] if text else type(exc).__name__


def _read_laz(reader):
    """A LAZ file's points chunk by chunk: memory follows the data actually decoded, not the declared count.

    Raises
    ------
    ValueError
        When the compressed data holds fewer or more points than the header declares.
    """
    import laspy

    count, parts, held = int(reader.header.point_count), [], 0
    try:
        for part in reader.chunk_iterator(LAS_CHUNK):
            parts.append(part.array)
            held += len(part.array)
            if held > count:
                break
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException:      # the decoder runs out of data: the count is a lie
        raise ValueError(f"the header declares {count} points, the compressed data ends after about "
                         f"{held}") from None
    if held != count:
        raise ValueError(f"the header declares {count} points, {held} could be read")
    array = np.concatenate(parts) if len(parts) != 1 else parts[0]
    header = reader.header
    las = laspy.LasData(header=header, points=laspy.ScaleAwarePointRecord(array, header.point_format,
                                                                          header.scales, header.offsets))
    if header.version.minor >= 4 and header.number_of_evlrs > 0 and reader.evlrs is None:
        reader.read_evlrs()
    return las


_POINT_SIZES = {0: 20, 1: 28, 2: 26, 3: 34, 4: 57, 5: 63, 6: 30, 7: 36, 8: 38, 9: 59, 10: 67}


def _check_las_block(f, size):
    """The public header block's own fields against the file's length, before laspy parses it.

    Returns the number of chunks the LAZ chunk table declares (None when
    the file is not compressed or has no chunk table).

    A corrupt count of variable-length records, an offset past the end or a
    LAZ chunk table claiming billions of chunks would otherwise have laspy
    loop, or the LAZ decoder allocate (and abort the process), for data the
    file cannot hold.
    """
    import struct

    head = f.read(375)
    if len(head) < 227 or head[:4] != b"LASF":
        raise ValueError("not a LAS/LAZ file (no 'LASF' signature or a header shorter than 227 bytes)")
    major, minor = head[24], head[25]
    if major != 1 or minor > 4:
        raise ValueError(f"LAS version {major}.{minor} is not supported (1.0 to 1.4)")
    header_size, offset, n_vlrs, point_format, record = struct.unpack_from("<HIIBH", head, 94)
    if point_format & 0x3F not in _POINT_SIZES or record < _POINT_SIZES[point_format & 0x3F]:
        raise ValueError(f"point format {point_format & 0x3F} with records of {record} bytes is not valid "
                         f"(formats 0 to 10, each record at least its format's size)")
    if not 227 <= header_size <= offset <= size:
        raise ValueError(f"the header size ({header_size}) and the offset to the points ({offset}) "
                         f"do not fit a {size}-byte file")
    if n_vlrs * 54 > offset - header_size:
        raise ValueError(f"the header declares {n_vlrs} variable-length records, more than fit before "
                         f"the points at byte {offset}")
    if minor >= 4 and len(head) >= 375:
        start_evlr, n_evlrs = struct.unpack_from("<QI", head, 235)
        if n_evlrs and (start_evlr > size or n_evlrs * 60 > size - start_evlr):
            raise ValueError(f"the header declares {n_evlrs} extended records at byte {start_evlr}, "
                             f"beyond the {size}-byte file")
    if head[104] & 0xC0:                                  # compressed (LAZ): check the chunk table
        count = struct.unpack_from("<I", head, 107)[0]
        if minor >= 4 and len(head) >= 255:
            count = max(count, struct.unpack_from("<Q", head, 247)[0])
        f.seek(offset)
        raw = f.read(8)
        if len(raw) < 8:
            raise ValueError("truncated: the LAZ chunk table offset is missing")
        table = struct.unpack("<q", raw)[0]
        if table == -1:
            return None
        if not offset + 8 <= table <= size - 8:
            raise ValueError(f"the LAZ chunk table offset {table} lies outside the {size}-byte file")
        f.seek(table)
        _, n_chunks = struct.unpack("<II", f.read(8))
        if n_chunks > min(count + 1, size):
            raise ValueError(f"the LAZ chunk table declares {n_chunks} chunks for {count} points "
                             f"in a {size}-byte file")
        return n_chunks
    return None


_LASZIP_MAX_CHUNK = 10_000_000      # points per chunk; 0xFFFFFFFF means variable-size chunks


def _check_laszip_vlr(header, record, n_chunks):
    """The LASzip VLR's layout, chunk size and item sizes, before the decoder allocates by them.

    With fixed-size chunks and a chunk table, the declared point count must
    fit the chunks: at most ``n_chunks`` x chunk size points.
    """
    import struct

    vlrs = [v for v in header.vlrs if getattr(v, "record_id", None) == 22204]
    if not vlrs:
        raise ValueError("compressed points without a LASzip VLR")
    data = bytes(getattr(vlrs[0], "record_data", b""))
    if len(data) < 34:
        raise ValueError(f"the LASzip VLR holds {len(data)} bytes, fewer than its 34-byte head")
    compressor, _, _, _, _, _, chunk, _, _, n_items = struct.unpack("<HHBBHIIqqH", data[:34])
    if len(data) != 34 + 6 * n_items:
        raise ValueError(f"the LASzip VLR declares {n_items} items but holds {len(data)} bytes")
    if compressor not in (1, 2, 3):
        raise ValueError(f"the LASzip VLR names compressor {compressor} (1, 2 or 3 expected)")
    if chunk != 0xFFFFFFFF and not 0 < chunk <= _LASZIP_MAX_CHUNK:
        raise ValueError(f"the LASzip VLR declares chunks of {chunk} points")
    sizes = sum(struct.unpack("<HHH", data[34 + 6 * i:40 + 6 * i])[1] for i in range(n_items))
    if sizes != record:
        raise ValueError(f"the LASzip items hold {sizes} bytes per point, the point format {record}")
    count = int(header.point_count)
    if chunk != 0xFFFFFFFF and n_chunks is not None and count > n_chunks * chunk:
        raise ValueError(f"the header declares {count} points, more than the {n_chunks} chunks of {chunk} "
                         f"points in the LAZ chunk table hold")


def _check_las_header(header, size, n_chunks=None):
    """Declared point count and record size against the file's length (exact for LAS)."""
    count = int(header.point_count)
    record = int(header.point_format.size)
    start = int(header.offset_to_point_data)
    scales, offsets = np.asarray(header.scales, dtype=np.float64), np.asarray(header.offsets, dtype=np.float64)
    with np.errstate(all="ignore"):
        reach = np.abs(scales) * 2.0**31 + np.abs(offsets)       # the largest coordinate a record can hold
    if not np.isfinite(reach).all() or (reach > 1e300).any() or (scales == 0).any():
        raise ValueError(f"the header's scale factors {scales.tolist()} and offsets {offsets.tolist()} must be "
                         f"finite, the scales not zero, and every stored coordinate finite")
    if header.are_points_compressed:
        if count * record > _LAZ_MAX_RATIO * size:
            raise ValueError(f"the header declares {count} points, more than a {size}-byte LAZ file can hold")
        _check_laszip_vlr(header, record, n_chunks)
        return
    end = size
    if getattr(header, "number_of_evlrs", 0) and getattr(header, "start_of_first_evlr", 0):
        end = min(size, int(header.start_of_first_evlr))
    held = end - start
    need = count * record
    if held < need:
        raise ValueError(f"truncated: the header declares {count} points of {record} bytes "
                         f"({need} bytes), the file holds {max(held, 0)} bytes of points")
    if held > need:
        extra = held - need
        if extra % record == 0:
            raise ValueError(f"the header declares {count} points, the file holds {count + extra // record}")
        raise ValueError(f"the header declares {count} points of {record} bytes, "
                         f"{extra} bytes more follow them")


def write_points(cloud, points, path):
    """Write ``points`` in the format and with the attributes of ``cloud``.

    Parameters
    ----------
    cloud : PointCloud
        The source file's data (its other attributes are kept).
    points : (n, 3) float
        New coordinates, same order as ``cloud.points``.
    path : str or Path
        Target; must not be the source file.  Its suffix must match the source format.

    Returns
    -------
    pathlib.Path
    """
    path = Path(path)
    if path.exists() and os.path.realpath(path) == os.path.realpath(cloud.path):
        raise InputError(f"{path}: refusing to overwrite the original")
    fmt = format_of(path)
    if fmt != cloud.format:
        raise InputError(f"{path}: output format {fmt} differs from the input format {cloud.format}")
    if fmt == "ply":
        atomic_write_bytes(path, write_ply(cloud.native, points))
    elif fmt in _WRITERS:
        atomic_write_bytes(path, _serialise(cloud, points, path))
    else:
        try:
            with _atomic_target(path) as tmp:
                _write_las(cloud.native, points, tmp)
        except ValueError as exc:
            raise InputError(f"{path}: {exc}") from None
    return path


class _native_stderr_held:
    """Hold what native code (the LAZ decoder's panic hook) writes to fd 2; replay it only on success.

    A corrupt file then ends as our one-line error, not a native panic report.
    """

    def __enter__(self):
        sys.stderr.flush()
        self.saved = os.dup(2)
        self.buffer = tempfile.TemporaryFile()
        os.dup2(self.buffer.fileno(), 2)
        return self

    def __exit__(self, exc_type, exc, tb):
        os.dup2(self.saved, 2)
        os.close(self.saved)
        if exc_type is None:
            self.buffer.seek(0)
            text = self.buffer.read()
            if text:
                os.write(2, text)
        self.buffer.close()
        return False


def _check_las_writable(header):
    """Refuse, before any work, a LAS version and point format that cannot be written back."""
    from laspy.point import dims

    version = str(header.version)
    try:
        dims.raise_if_version_not_compatible_with_fmt(header.point_format.id, version)
    except Exception:  # laspy's errors for versions it reads but cannot write
        raise ValueError(f"LAS version {version} does not allow point format {header.point_format.id}, so the "
                         f"file cannot be written back; convert it to a version that does first") from None


LAS_CHUNK = 1 << 20     # points written or read back at a time: no whole copy of a large tile's records


def _write_las(las, points, tmp):
    import laspy

    # header strings that are not ASCII (they were read as they are) must not stop the write
    with laspy.open(str(tmp), mode="w", header=las.header, encoding_errors="replace") as writer:
        for a in range(0, len(points), LAS_CHUNK):
            part = laspy.ScaleAwarePointRecord(las.points.array[a:a + LAS_CHUNK].copy(), las.header.point_format,
                                               las.header.scales, las.header.offsets)
            try:
                part.x, part.y, part.z = (points[a:a + LAS_CHUNK, i] for i in range(3))
            except (OverflowError, ValueError):
                raise ValueError("the coordinates do not fit the file's scale and offset (32-bit integers); "
                                 "the header cannot hold them") from None
            writer.write_points(part)
        if las.header.evlrs:
            writer.write_evlrs(las.header.evlrs)


def read_coordinates(path):
    """The coordinates of a file this tool wrote, (n, 3) float; LAS/LAZ chunk by chunk.

    For the read-back check of an issued copy: a large tile's point records
    are never all in memory at once.  Other formats go through
    :func:`read_points`.
    """
    path = Path(path)
    if format_of(path) not in ("las", "laz"):
        return read_points(path).points
    import laspy

    with _native_stderr_held(), laspy.open(str(path)) as reader:
        out = np.empty((reader.header.point_count, 3))
        a = 0
        for part in reader.chunk_iterator(LAS_CHUNK):
            out[a:a + len(part)] = np.column_stack([np.asarray(part.x), np.asarray(part.y), np.asarray(part.z)])
            a += len(part)
    if a != len(out):
        raise InputError(f"{path}: the header declares {len(out)} points, {a} could be read")
    return out


def _serialise(cloud, points, path):
    try:
        return _WRITERS[cloud.format](cloud.native, points)
    except ValueError as exc:
        raise InputError(f"{path}: {exc}") from None


class _atomic_target:
    """Context manager giving a temporary path that is renamed to ``path`` on success.

    Any OS error (a full disk, a refused permission) removes the temporary
    and ends as an :class:`InputError` naming ``path``: ``PATH: no space left on device``.
    """

    def __init__(self, path):
        self.path = Path(path)

    def __enter__(self):
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, name = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=f".tmp{self.path.suffix}",
                                        dir=self.path.parent)
        except OSError as exc:
            raise WriteError(f"{self.path}: cannot write: {_reason(exc)}") from None
        os.close(fd)
        self.tmp = Path(name)
        return self.tmp

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            umask = os.umask(0)
            os.umask(umask)
            try:
                os.chmod(self.tmp, 0o666 & ~umask)      # mkstemp's 0600 would survive the rename
                os.replace(self.tmp, self.path)
            except OSError as error:
                self.tmp.unlink(missing_ok=True)
                raise WriteError(f"{self.path}: cannot write: {_reason(error)}") from None
            return False
        self.tmp.unlink(missing_ok=True)
        if issubclass(exc_type, OSError):
            raise WriteError(f"{self.path}: cannot write: {_reason(exc)}") from None
        return False


def atomic_write_bytes(path, data):
    """Write bytes to ``path`` through a temporary file and a rename.

    Raises
    ------
    InputError
        Naming ``path`` when the write fails (no temporary is left behind).
    """
    with _atomic_target(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def sha256_file(path):
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def write_array(folder, name, points, fmt, *, keep_existing=True):
    """Write bare coordinates as a file ``folder/name.<fmt>`` (demo data, attacked copies).

    ``fmt`` is a format name, or ``ply-ascii`` for an ASCII PLY.  With
    ``keep_existing`` an existing file is left as it is.

    Returns
    -------
    pathlib.Path
    """
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise WriteError(f"{folder}: cannot create the folder: {_reason(exc)}") from None
    suffix = "ply" if fmt == "ply-ascii" else fmt
    path = folder / f"{name}.{suffix}"
    if path.exists() and keep_existing:
        return path
    points = np.asarray(points, dtype=np.float64)
    if fmt in ("ply", "ply-ascii"):
        kind = "ascii" if fmt == "ply-ascii" else "binary_little_endian"
        head = (f"ply\nformat {kind} 1.0\ncomment pointmark demo asset\nelement vertex {len(points)}\n"
                "property double x\nproperty double y\nproperty double z\nend_header\n").encode()
        if kind == "ascii":
            body = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in points.tolist()).encode()
        else:
            body = points.astype("<f8").tobytes()
        atomic_write_bytes(path, head + body)
    elif fmt in ("las", "laz"):
        import laspy

        header = laspy.LasHeader(point_format=3, version="1.2")
        header.scales = np.array([0.0001, 0.0001, 0.0001])
        header.offsets = np.floor(points.min(axis=0))
        las = laspy.LasData(header)
        las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
        las.intensity = (np.arange(len(points)) % 65535).astype(np.uint16)
        with _atomic_target(path) as tmp:
            las.write(str(tmp))
    else:
        atomic_write_bytes(path, _NEW_FILES[fmt](points))
    return path
