"""Surface attacks that need open3d (resampling, mesh simplification) or an external tool (glTF's).

Kept out of :mod:`pipeline.kernels` (which is pure NumPy/SciPy).  The open3d
ones are seeded: open3d's global generator is seeded from the given ``rng``.
The ``gltf-*`` attacks write the points (and faces) as a GLB, run the tool
of :mod:`pipeline.io.gltf_tools` on it and read back what it wrote.
"""

from __future__ import annotations

import numpy as np

from .io.gltf_tools import FILE_ATTACKS
from .kernels import attacks

__all__ = ["resample", "simplify", "apply_chain", "ATTACK_NAMES", "parse_attack"]


def _o3d():
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


def _seed(rng):
    rng = np.random.default_rng(rng)
    _o3d().utility.random.seed(int(rng.integers(0, 2**31 - 1)))
    return rng


def resample(points, n_points, rng=None, *, depth=8):
    """Screened Poisson reconstruction of the cloud, then ``n_points`` fresh samples.

    No input point survives: samples are drawn uniformly on the reconstructed
    triangles, away from the (trimmed) low-density parts of the surface.

    The reconstruction runs on one thread.  On its default of a thread per
    core it gave its vertices in another order at each call, with a few
    tenths of a per cent of the triangles joining other vertices, and it can
    crash the process at random (Open3D issue 6828; most likely what took
    a test process down in CI on 2026-12-06).  The samples are drawn by
    :func:`~pipeline.kernels.attacks.sample_triangles`, from each triangle's
    geometry and the seed, not in the order open3d lists the triangles.

    Parameters
    ----------
    points : (n, 3) float
    n_points : int

    Returns
    -------
    (n_points, 3) float
    """
    o3d = _o3d()
    rng = _seed(rng)
    centre = points.mean(axis=0)
    scale = float((points.max(axis=0) - points.min(axis=0)).max())
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector((points - centre) / scale))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=20))
    cloud.orient_normals_consistent_tangent_plane(12)
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=depth, n_threads=1)
    density = np.asarray(density)
    mesh.remove_vertices_by_mask(density < np.quantile(density, 0.05))
    out = attacks.sample_triangles(np.asarray(mesh.vertices), np.asarray(mesh.triangles), int(n_points), rng)
    return out * scale + centre


def simplify(points, n_vertices, rng=None, *, faces):
    """Quadric mesh decimation to ``n_vertices`` vertices; faces are dropped.

    Parameters
    ----------
    points : (n, 3) float
    n_vertices : int
    faces : (f, 3) int
        Triangles of the asset (the paper's "simulated simplification").

    Returns
    -------
    (m, 3) float, m close to ``n_vertices``
    """
    if faces is None or len(faces) == 0:
        raise ValueError("simplify needs an asset with faces (a PLY mesh)")
    o3d = _o3d()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(points),
                                     o3d.utility.Vector3iVector(np.asarray(faces, dtype=np.int32)))
    target = int(2 * n_vertices)          # a closed-ish mesh has about twice as many faces as vertices
    small = mesh.simplify_quadric_decimation(target_number_of_triangles=target)
    small.remove_unreferenced_vertices()
    return np.asarray(small.vertices).copy()


ATTACK_NAMES = sorted([*attacks.ATTACKS, "resample", "simplify", *FILE_ATTACKS])


def file_attack(points, faces, name, strength=None):
    """A glTF tool's attack on points and faces: ((m, 3) float, (g, 3) int faces) of what it wrote."""
    import tempfile
    from pathlib import Path

    from .io.gltf import glb_from_mesh
    from .io.gltf_tools import attack_suffix
    from .io.gltf_tools import file_attack as run_tool
    from .io.pointcloud import read_points

    with tempfile.TemporaryDirectory(prefix="pointmark-gltf-") as folder:
        source = Path(folder) / "in.glb"
        source.write_bytes(glb_from_mesh(points, faces))
        cloud = read_points(run_tool(source, Path(folder) / f"out{attack_suffix(name)}", name, strength))
        return cloud.points, cloud.faces()


def parse_attack(text):
    """``NAME[:STRENGTH]`` -> (name, float or None); a ``%`` suffix divides by 100."""
    name, _, value = text.partition(":")
    if name not in ATTACK_NAMES:
        raise ValueError(f"unknown attack {name!r}; known: {', '.join(ATTACK_NAMES)}")
    if name in FILE_ATTACKS:
        return name, _file_strength(text, name, value)
    if not value:
        return name, attacks.check_strength(name, None)
    try:
        strength = float(value[:-1]) / 100.0 if value.endswith("%") else float(value)
    except ValueError:
        raise ValueError(f"attack {text[:40]!r}: strength {value[:20]!r} is not a number") from None
    return name, attacks.check_strength(name, strength)     # type, finiteness and range


# glTF tool attacks that take a strength: (low, high, whole number, what it is); the others take none
FILE_STRENGTHS = {"gltf-draco": (1, 30, True, "position bits, a whole number from 1 to 30"),
                  "gltf-simplify": (0.0, 1.0, False, "the ratio of vertices kept, in (0, 1]")}


def _file_strength(text, name, value):
    """A glTF tool attack's strength checked before any work: Draco bits 1..30, a simplify ratio in (0, 1]."""
    default = FILE_ATTACKS[name][1]
    if not value:
        return default
    if name not in FILE_STRENGTHS:
        raise ValueError(f"{name} takes no strength (got {value[:20]!r})")
    try:
        strength = float(value[:-1]) / 100.0 if value.endswith("%") else float(value)
    except ValueError:
        raise ValueError(f"attack {text[:40]!r}: strength {value[:20]!r} is not a number") from None
    low, high, whole, what = FILE_STRENGTHS[name]
    ok = np.isfinite(strength) and (low <= strength <= high if whole else low < strength <= high)
    if not ok or whole and strength != int(strength):
        raise ValueError(f"attack {text[:40]!r}: the strength is {what}")
    return strength


def apply_chain(points, chain, rng=None, *, faces=None):
    """Apply a chain of attacks, the open3d ones included.

    Parameters
    ----------
    points : (n, 3) float
    chain : list of (name, strength or None)
    rng : int or numpy.random.Generator
    faces : (f, 3) int, optional
        Needed by ``simplify`` (the first step, or after a ``gltf-`` step); ``gltf-`` steps keep a mesh.

    Returns
    -------
    (m, 3) float
    """
    rng = np.random.default_rng(rng)
    for i, (name, strength) in enumerate(chain):
        if name in FILE_ATTACKS:          # what the tool wrote has faces: a later simplify may use them
            points, faces = file_attack(points, faces, name, strength)
            continue
        if name == "resample":
            points = resample(points, int(strength), rng)
        elif name == "simplify":
            if faces is None or (i and chain[i - 1][0] not in FILE_ATTACKS):
                raise ValueError("simplify must come first (or after a gltf- attack): later steps lose the faces")
            points = simplify(points, int(strength), rng, faces=faces)
        else:
            points = attacks.apply_chain(points, [(name, strength)], rng)
        faces = None
    return points
