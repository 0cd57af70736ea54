"""Point-cloud files: read, check, and write atomically in the input's own format.

PLY through :mod:`pipeline.io.ply` (every vertex property kept), PCD, XYZ
and PTS through open3d, LAS and LAZ through laspy (header scale and offset
and every point record kept).  Coordinates come back as float64 in the file's
own frame, in file order.  Writes go to a temporary name in the target
folder and are renamed into place; an input is never overwritten.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .ply import PlyError, read_ply, write_ply

__all__ = ["PointCloud", "InputError", "read_points", "write_points", "write_array",
           "atomic_write_bytes", "sha256_file", "FORMATS"]

FORMATS = {".ply": "ply", ".pcd": "pcd", ".xyz": "xyz", ".pts": "pts", ".las": "las", ".laz": "laz"}


class InputError(ValueError):
    """A file that cannot be used; the message names the file and the problem."""


@dataclass
class PointCloud:
    """Coordinates of a point-cloud file plus what is needed to write it back.

    Attributes
    ----------
    points : (n, 3) float64
    path : pathlib.Path
    format : str
    native : object
        PlyData, laspy.LasData or open3d.geometry.PointCloud.
    """

    points: np.ndarray
    path: Path
    format: str
    native: object

    def faces(self):
        """(f, 3) int triangles when the file is a PLY mesh, else empty."""
        if self.format == "ply":
            return self.native.faces()
        return np.zeros((0, 3), dtype=np.int64)


def format_of(path):
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise InputError(f"{path}: unknown point-cloud format {suffix!r} (use one of {sorted(FORMATS)})")
    return FORMATS[suffix]


def read_points(path):
    """Read a point-cloud file and check its coordinates.

    Parameters
    ----------
    path : str or Path

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
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    try:
        if fmt == "ply":
            native = read_ply(path.read_bytes())
            points = native.points
        elif fmt in ("las", "laz"):
            native, points = _read_las(path)
        else:
            native, points = _read_open3d(path, fmt)
    except (PlyError, OSError, ValueError) as exc:
        raise InputError(f"{path}: {exc}") from None
    _check(path, points)
    return PointCloud(points, path, fmt, native)


def _check(path, points):
    if len(points) == 0:
        raise InputError(f"{path}: the file holds no points")
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        raise InputError(f"{path}: {int(bad.sum())} points have NaN or infinite coordinates "
                         f"(first at index {int(np.flatnonzero(bad)[0])})")


def _read_las(path):
    import laspy

    try:
        las = laspy.read(str(path))
    except Exception as exc:  # laspy raises many types for corrupt files
        raise ValueError(f"cannot read LAS/LAZ: {exc}") from None
    points = np.column_stack([np.asarray(las.x, dtype=np.float64),
                              np.asarray(las.y, dtype=np.float64),
                              np.asarray(las.z, dtype=np.float64)])
    return las, points


def _read_open3d(path, fmt):
    import open3d as o3d

    cloud = o3d.io.read_point_cloud(str(path), format=fmt)
    points = np.asarray(cloud.points, dtype=np.float64)
    if len(points) == 0 and path.stat().st_size > 0:
        raise ValueError(f"open3d could not read any point from this {fmt.upper()} file")
    return cloud, points


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
    if path.exists() and path.resolve() == cloud.path.resolve():
        raise InputError(f"{path}: refusing to overwrite the original")
    fmt = format_of(path)
    if fmt != cloud.format:
        raise InputError(f"{path}: output format {fmt} differs from the input format {cloud.format}")
    if fmt == "ply":
        atomic_write_bytes(path, write_ply(cloud.native, points))
    else:
        with _atomic_target(path) as tmp:
            if fmt in ("las", "laz"):
                _write_las(cloud.native, points, tmp)
            else:
                _write_open3d(cloud.native, points, tmp)
    return path


def _write_las(las, points, tmp):
    import laspy

    out = laspy.LasData(header=las.header, points=las.points.copy())
    out.x, out.y, out.z = points[:, 0], points[:, 1], points[:, 2]
    out.write(str(tmp))


def _write_open3d(native, points, tmp):
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(native)
    cloud.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
    if not o3d.io.write_point_cloud(str(tmp), cloud, write_ascii=tmp.suffix != ".pcd"):
        raise OSError(f"open3d could not write {tmp}")


class _atomic_target:
    """Context manager giving a temporary path that is renamed to ``path`` on success."""

    def __init__(self, path):
        self.path = Path(path)

    def __enter__(self):
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=f".tmp{self.path.suffix}",
                                    dir=self.path.parent)
        os.close(fd)
        self.tmp = Path(name)
        return self.tmp

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)
        return False


def atomic_write_bytes(path, data):
    """Write bytes to ``path`` through a temporary file and a rename."""
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
    import open3d as o3d

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
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
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        with _atomic_target(path) as tmp:
            if not o3d.io.write_point_cloud(str(tmp), cloud, write_ascii=fmt != "pcd"):
                raise OSError(f"open3d could not write {path}")
    return path
