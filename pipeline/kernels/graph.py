"""The non-manifold mesh of a cluster: a Euclidean radius graph (paper, "Meshing").

Each point is connected to every point within radius r, where r is chosen so
that the average valence equals N_n.  The radius is read off the sorted
neighbour distances (the (n * N_n)-th smallest ordered-pair distance), not
found by trial.  The mesh Laplacian is K = D - A (equation 1).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = ["valence_radius", "radius_graph", "connect_components", "laplacian"]


def valence_radius(points, valence):
    """Radius at which the average valence of the radius graph is ``valence``.

    Parameters
    ----------
    points : (n, 3) float
    valence : float
        Target average valence N_n.

    Returns
    -------
    radius : float
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    if n < 2:
        raise ValueError(f"a cluster needs at least 2 points, got {n}")
    tree = cKDTree(points)
    target = int(round(valence * n))  # number of ordered pairs (i, j), i != j
    k = min(n, int(np.ceil(2 * valence)) + 2)
    while True:
        dist, _ = tree.query(points, k=k)
        dist = dist[:, 1:]  # drop self
        if target > dist.size:
            raise ValueError(f"valence={valence} exceeds the n - 1 = {n - 1} neighbours available")
        radius = float(np.partition(dist.ravel(), target - 1)[target - 1])
        # exact only if no point has all of its k - 1 neighbours within r
        if k >= n or dist[:, -1].min() > radius:
            return radius
        k = min(n, 2 * k)


def radius_graph(points, radius):
    """Adjacency of the graph joining points closer than ``radius``.

    Parameters
    ----------
    points : (n, 3) float
    radius : float

    Returns
    -------
    A : (n, n) scipy.sparse.csr_matrix of float64, symmetric, 0/1, zero diagonal
    """
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    return _adjacency(len(points), pairs)


def connect_components(points, adjacency):
    """Join the components of a graph by their shortest bridging edges.

    A sensible rule for disconnected radius graphs (isolated points, separate
    parts): each round, every component gains an edge from its point nearest
    to any other component (Boruvka), until one component remains.  The added
    edges are deterministic given the points.

    Parameters
    ----------
    points : (n, 3) float
    adjacency : (n, n) sparse

    Returns
    -------
    A : (n, n) scipy.sparse.csr_matrix
    n_components : int
        Components before joining.
    """
    n_comp, labels = connected_components(adjacency, directed=False)
    first = n_comp
    bridges = []
    while n_comp > 1:
        for c in range(n_comp):
            inside = np.flatnonzero(labels == c)
            outside = np.flatnonzero(labels != c)
            dist, idx = cKDTree(points[outside]).query(points[inside])
            best = int(np.argmin(dist))
            bridges.append((inside[best], outside[idx[best]]))
        extra = _adjacency(len(points), np.asarray(bridges, dtype=np.int64))
        n_comp, labels = connected_components(adjacency + extra, directed=False)
    if not bridges:
        return adjacency.tocsr(), first
    extra = _adjacency(len(points), np.asarray(bridges, dtype=np.int64))
    joined = ((adjacency + extra) > 0).astype(np.float64)
    return joined.tocsr(), first


def laplacian(adjacency):
    """Mesh Laplacian K = D - A.

    Parameters
    ----------
    adjacency : (n, n) sparse, symmetric 0/1

    Returns
    -------
    K : (n, n) scipy.sparse.csr_matrix
    """
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    return (sp.diags(degree) - adjacency).tocsr()


def _adjacency(n, pairs):
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    rows = np.concatenate([pairs[:, 0], pairs[:, 1]])
    cols = np.concatenate([pairs[:, 1], pairs[:, 0]])
    data = np.ones(len(rows), dtype=np.float64)
    a = sp.coo_matrix((data, (rows, cols)), shape=(n, n)).tocsr()
    a.data[:] = 1.0  # duplicate pairs sum; keep 0/1
    return a
