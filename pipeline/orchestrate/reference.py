"""References through the basis store: computed once, shared by run, detect, scan and evaluate.

The plan step (frame and clusters) and the cluster step (basis, normals) are
separate so the catalogue graph can run every cluster's eigendecomposition as
its own task; detection calls :func:`load_reference`, which fills in whatever
the store lacks and verifies the result against the digests the ledger
recorded at embedding.
"""

from __future__ import annotations

import numpy as np

from ..io.basis_store import BasisStore
from ..kernels import resampling
from ..watermark import (ClusterSpec, Reference, cluster_basis, cluster_normals, frame_of,
                         plan_clusters)

__all__ = ["plan_reference", "cluster_reference", "load_reference"]


def plan_reference(points, params, store, key):
    """Frame and clusters of an original, from the store or computed and saved.

    Parameters
    ----------
    points : (n, 3) float
    params : WatermarkParams
    store : BasisStore or path
    key : str
        The store entry (``BasisStore.key(source_sha256, params)``).

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
        return centre, phi, specs
    frame = frame_of(points)
    specs = plan_clusters(points - frame.centre, params)
    store.save_meta(key, frame.centre, frame.phi, [s.seed_index for s in specs], [s.members for s in specs])
    return frame.centre, frame.phi, specs


def cluster_reference(points, centre, spec, params, store, key):
    """Radius, basis and normals of one cluster, from the store or computed and saved.

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
    centred = points - centre
    radius, basis = cluster_basis(centred[spec.members], params)
    normals = cluster_normals(centred, spec.members, params)
    store.save_cluster(key, spec.index, radius, basis, normals)
    return radius, basis, normals


def _aid(store, key, name, compute):
    value = store.load_array(key, name)
    if value is None:
        value = compute()
        store.save_array(key, name, value)
    return value


def detection_aids(points, centre, specs, bases, params, store, key):
    """The original's normals and spacing, and the clusters' normal-model Grams, from the store or computed."""
    centred = points - centre
    normals = _aid(store, key, "model-normals", lambda: resampling.estimate_normals(centred))
    spacing = _aid(store, key, "model-spacing", lambda: resampling.nearest_spacing(centred))
    grams = None
    if params.displacement == "normal":
        grams = [_aid(store, key, f"gram-{s.index}", lambda s=s, b=b: resampling.normal_gram(b, normals[s.members]))
                 for s, b in zip(specs, bases)]
    return normals, spacing, grams


def load_reference(points, params, store, key, recorded=None, source="the ledger", detection=False):
    """The whole reference of an original, verified against recorded digests.

    Parameters
    ----------
    points : (n, 3) float, the original
    params : WatermarkParams
    store : BasisStore or path
    key : str
    recorded : dict, optional
        ``{"membership": [...], "basis": [...]}`` as recorded at embedding.
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
                        detection_aids(points, np.asarray(centre), specs, bases, params, store, key)))
    ref = Reference(np.asarray(centre), float(phi), specs, bases, normals, [float(p[0]) for p in parts], **aids)
    if recorded is not None:
        ref.verify(recorded, source)
    return ref
