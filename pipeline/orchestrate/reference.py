"""References: one function builds them, one loads them, both verify digests.

:func:`build_reference` computes an original's reference (frame, clusters,
spectral bases, normals) and, given a basis store, keeps it there; what the
store already held must have the digests of what was rebuilt.
:func:`load_reference` reads a reference from the store (computing what it
lacks) and verifies it against the digests recorded when the copy was made.
``embed``, ``detect --original`` and the evaluation build; scans,
``detect --ledger``, the evaluation's trials and the evidence pictures load.

The catalogue graph runs the same two steps of :func:`build_reference` as
tasks, :func:`plan_reference` (frame and clusters) and one
:func:`cluster_reference` (basis, normals) per cluster, so every cluster's
eigendecomposition is its own task; the issue task then verifies them with
:func:`verified_clusters`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..io.basis_store import BasisStore
from ..kernels import digest, resampling
from ..watermark import (ClusterSpec, Reference, WatermarkError, check_count, check_digest, cluster_basis,
                         cluster_normals, compute_reference, frame_of, plan_clusters)

__all__ = ["build_reference", "load_reference", "plan_reference", "cluster_reference", "verified_clusters",
           "cluster_points_name", "MissingClusterPoints"]


class MissingClusterPoints(WatermarkError):
    """A tiled cluster's points are not in the store (or do not load): read the asset instead."""


def plan_reference(points, params, store, key, cluster_points=False):
    """Frame and clusters of an original, from the store or computed and saved.

    With ``cluster_points`` (the catalogue's plan task) a tiled asset's
    clusters also get their points stored, so each cluster task reads its
    cluster, not the whole asset.

    Parameters
    ----------
    points : (n, 3) float
    params : WatermarkParams
    store : BasisStore or path
    key : str
        The store entry (``BasisStore.key(source_sha256, params)``).
    cluster_points : bool

    Returns
    -------
    centre : (3,) float
    phi : float
    specs : list of ClusterSpec
    """
    store = BasisStore(store) if not isinstance(store, BasisStore) else store
    meta = store.load_meta(key)
    if meta is not None:
        centre, phi, seeds, members = meta
        specs = [ClusterSpec(i, int(s), int(params.cluster_size), m) for i, (s, m) in enumerate(zip(seeds, members))]
    else:
        frame = frame_of(points)
        centre, phi = frame.centre, frame.phi
        specs = plan_clusters(points - centre, params)
        store.save_meta(key, centre, phi, [s.seed_index for s in specs], [s.members for s in specs])
    if cluster_points and params.tile_points is not None:
        for s in specs:
            if not store.has(key, cluster_points_name(s.index)):
                store.save_array(key, cluster_points_name(s.index), points[s.members] - centre)
    return centre, phi, specs


def cluster_points_name(index):
    """Store name of a tiled cluster's points (centred), written by the plan task."""
    return f"points-{index}"


def cluster_reference(points, centre, spec, params, store, key):
    """Radius, basis and normals of one cluster, from the store or computed and saved.

    ``points`` may be None for a tiled asset (``params.tile_points``): the
    cluster's points then come from the store, where the plan put them
    (:class:`MissingClusterPoints` when they cannot be loaded).

    Returns
    -------
    radius : float
    basis : (n_c, n_coefficients) float
    normals : (n_c, 3) float or None
    """
    store = BasisStore(store) if not isinstance(store, BasisStore) else store
    cached = store.load_cluster(key, spec.index)
    if cached is not None and cached[1].shape == (len(spec.members), params.n_coefficients):
        return cached
    if points is None:
        local = store.load_array(key, cluster_points_name(spec.index))
        if params.tile_points is None or local is None or local.shape != (len(spec.members), 3):
            raise MissingClusterPoints(f"the basis store {store.folder} lacks the points of cluster {spec.index}")
        centred, members = local, np.arange(len(local))
    elif params.tile_points is not None:
        # tiled: the cluster alone decides its basis and normals; no copy of the whole asset per cluster
        centred = points[spec.members] - centre
        members = np.arange(len(centred))
    else:
        centred, members = points - centre, spec.members
    radius, basis = cluster_basis(centred[members], params)
    normals = cluster_normals(centred, members, params)
    store.save_cluster(key, spec.index, radius, basis, normals)
    return radius, basis, normals


def verified_clusters(points, centre, specs, params, store, key, recorded, source="the ledger"):
    """Each cluster's (spec, radius, basis, normals), checked against the recorded digests, one at a time.

    The memory holds one basis at a time, however many clusters a large asset has.

    Raises
    ------
    ReferenceMismatch
        At the first cluster whose members or basis differ from ``recorded``.
    """
    check_count(len(specs), recorded, source)
    for spec in specs:
        check_digest(spec.index, "membership", digest.membership_digest(spec.members), recorded, source)
        radius, basis, normals = cluster_reference(points, centre, spec, params, store, key)
        check_digest(spec.index, "basis", digest.basis_digest(basis), recorded, source)
        yield spec, radius, basis, normals


def _aid(store, key, name, compute):
    """A detection aid from the store, or computed (and stored, when there is a store)."""
    value = None if store is None else store.load_array(key, name)
    if value is None:
        value = compute()
        if store is not None:
            store.save_array(key, name, value)
    return value


def detection_aids(points, centre, specs, bases, params, store, key, cluster_normals=None):
    """The original's normals and spacing, and the clusters' normal-model Grams, from the store or computed.

    A tiled asset's clusters were moved along the normals of their own
    points (``cluster_normals``, one (n_c, 3) per cluster): those rows of the
    model normals are theirs, so detection models the motion embedding made.
    """
    centred = points - centre

    def model_normals():
        normals = resampling.estimate_normals(centred)
        if params.tile_points is not None and cluster_normals is not None:
            for s, n in zip(specs, cluster_normals):
                normals[s.members] = n
        return normals

    normals = _aid(store, key, "model-normals", model_normals)
    spacing = _aid(store, key, "model-spacing", lambda: resampling.nearest_spacing(centred))
    grams = None
    if params.displacement == "normal":
        grams = [_aid(store, key, f"gram-{s.index}", lambda s=s, b=b: resampling.normal_gram(b, normals[s.members]))
                 for s, b in zip(specs, bases)]
    return normals, spacing, grams


def build_reference(points, params, store=None, key=None, *, detection=False):
    """Compute the reference of an original; with a store, keep it there.

    Parameters
    ----------
    points : (n, 3) float, the original
    params : WatermarkParams
    store : BasisStore or path, optional
    key : str, optional
        The store entry (``BasisStore.key(source_sha256, params)``); needed with ``store``.
    detection : bool
        Also compute what detection needs besides the bases
        (:meth:`Reference.detection_aids`).

    Returns
    -------
    Reference

    Raises
    ------
    ReferenceMismatch
        The store already held this entry with other members or bases than
        the ones rebuilt (another clustering, mesh or eigen-solver).
    """
    ref = compute_reference(points, params)
    if store is not None:
        store = BasisStore(store) if not isinstance(store, BasisStore) else store
        if store.load_meta(key) is not None:       # kept by an earlier build: it must be this one
            load_reference(points, params, store, key, ref.digests(),
                           source=f"the reference rebuilt from the original (basis store {store.folder})")
        else:
            store.save_meta(key, ref.centre, ref.phi, [s.seed_index for s in ref.specs],
                            [s.members for s in ref.specs])
            for i, (s, radius, basis) in enumerate(zip(ref.specs, ref.radii, ref.bases)):
                store.save_cluster(key, s.index, radius, basis, None if ref.normals is None else ref.normals[i])
    if not detection:
        return ref
    aids = detection_aids(points, ref.centre, ref.specs, ref.bases, params, store, key, ref.normals)
    return replace(ref, **dict(zip(("model_normals", "spacing", "grams"), aids)))


def load_reference(points, params, store, key, recorded, source="the ledger", detection=False):
    """The whole reference of an original, verified against recorded digests.

    Parameters
    ----------
    points : (n, 3) float, the original
    params : WatermarkParams
    store : BasisStore or path
    key : str
    recorded : dict
        ``{"membership": [...], "basis": [...]}`` as recorded at embedding
        (:meth:`Reference.digests`).
    detection : bool
        Also load (or compute once and store) what detection needs besides the
        bases: :meth:`Reference.detection_aids`.

    Returns
    -------
    Reference

    Raises
    ------
    ReferenceMismatch
        When the rebuilt (or stored) reference differs from ``recorded``.
    """
    store = BasisStore(store) if not isinstance(store, BasisStore) else store
    centre, phi, specs = plan_reference(points, params, store, key)
    parts = [cluster_reference(points, centre, s, params, store, key) for s in specs]
    normals = None if params.displacement != "normal" else [p[2] for p in parts]
    bases = [p[1] for p in parts]
    aids = {}
    if detection:
        aids = dict(zip(("model_normals", "spacing", "grams"),
                        detection_aids(points, np.asarray(centre), specs, bases, params, store, key,
                                       normals)))
    ref = Reference(np.asarray(centre), float(phi), specs, bases, normals, [float(p[0]) for p in parts], **aids)
    ref.verify(recorded, source)
    return ref
