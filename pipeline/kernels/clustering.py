"""Clusters of a point set grown from seed points (paper, section 2.2, "Clustering").

A cluster starts at a seed point (its centre) and grows by adding, one point
at a time, the point closest to it.  Clusters grow in turn (round robin).  A
cluster stops when it reaches its size limit or, with ``on_touch="stop"`` (the
paper), when the point closest to it already belongs to a cluster.  With
``on_touch="skip"`` the claimed point is passed over and growth goes on around
it, so clusters stay disjoint but reach their size.

"Closest" is measured along the surface: the shortest path from the seed
over the k-nearest-neighbour graph with Euclidean edge lengths (Dijkstra).
This grows compact discs on irregular samplings, where the smallest distance
to any member (Prim) would creep along chains of close points, and it does
not jump across thin gaps between separate surfaces.
"""

from __future__ import annotations

import heapq

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["farthest_point_seeds", "nearest_indices", "grow_clusters", "grid_cells"]

_FRONTIER_K = 16


def farthest_point_seeds(points, n_seeds):
    """Choose seeds by farthest-point sampling, deterministically.

    The first seed is the point nearest the centroid (lowest index on ties);
    each next seed is the point farthest from all seeds chosen so far.

    Parameters
    ----------
    points : (n, 3) float
    n_seeds : int

    Returns
    -------
    seeds : (n_seeds,) int
    """
    points = np.asarray(points, dtype=np.float64)
    if not 1 <= n_seeds <= len(points):
        raise ValueError(f"n_seeds={n_seeds} must be between 1 and the point count {len(points)}")
    centroid = points.mean(axis=0)
    first = int(np.argmin(np.einsum("ij,ij->i", points - centroid, points - centroid)))
    seeds = [first]
    dist = np.linalg.norm(points - points[first], axis=1)
    for _ in range(1, n_seeds):
        nxt = int(np.argmax(dist))  # argmax returns the lowest index on ties
        seeds.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(points - points[nxt], axis=1))
    return np.asarray(seeds, dtype=np.int64)


def grid_cells(points, cell_points):
    """Split a point set into cells of a grid over its two widest axes.

    The grid has about ``n / cell_points`` nearly square cells over the
    bounding box (no thin slivers at its edges); a cell holding more than
    twice ``cell_points`` (dense parts of a scanned scene) is halved at its
    median along its longer side until it holds no more.  The work per cell
    is therefore bounded whatever the size and density of the scene, and a
    tile is planned cell by cell in time linear in its points.

    Parameters
    ----------
    points : (n, 3) float
    cell_points : int
        Mean points per cell.

    Returns
    -------
    cells : list of (n_t,) int
        Point indices of each non-empty cell, ascending; grid cells in
        row-major order, the halves of a split cell low side first.
    """
    points = np.asarray(points, dtype=np.float64)
    n = len(points)
    if n <= cell_points:
        return [np.arange(n, dtype=np.int64)]
    lo, hi = points.min(axis=0), points.max(axis=0)
    axes = np.sort(np.argsort(hi - lo, kind="stable")[1:])    # the two widest axes, in axis order
    extent = np.maximum(hi[axes] - lo[axes], np.finfo(np.float64).tiny)
    side = float(np.sqrt(extent.prod() * cell_points / n))
    shape = np.maximum(np.round(extent / side), 1).astype(np.int64)
    ij = np.minimum(((points[:, axes] - lo[axes]) / (extent / shape)).astype(np.int64), shape - 1)
    label = ij[:, 0] * shape[1] + ij[:, 1]
    order = np.argsort(label, kind="stable")                   # stable: ascending within a cell
    cells = []
    for cell in np.split(order, np.flatnonzero(np.diff(label[order])) + 1):
        cells += _halve(points[:, axes], cell, 2 * cell_points)
    return cells


def _halve(plane, cell, limit):
    """A cell, or its halves at the median of its longer side, recursively, until none exceeds ``limit``."""
    if len(cell) <= limit:
        return [cell]
    xy = plane[cell]
    along = int(np.argmax(np.ptp(xy, axis=0)))
    order = np.argsort(xy[:, along], kind="stable")
    half = len(cell) // 2
    return _halve(plane, np.sort(cell[order[:half]]), limit) + _halve(plane, np.sort(cell[order[half:]]), limit)


def nearest_indices(points, coordinates):
    """Indices of the points nearest to given coordinates (seeds given as xyz).

    Parameters
    ----------
    points : (n, 3) float
    coordinates : (k, 3) float

    Returns
    -------
    (k,) int
    """
    _, idx = cKDTree(points).query(np.asarray(coordinates, dtype=np.float64).reshape(-1, 3))
    return np.asarray(idx, dtype=np.int64)


def grow_clusters(points, seeds, sizes, *, on_touch, cover):
    """Grow disjoint clusters from seed points.

    Parameters
    ----------
    points : (n, 3) float
    seeds : (k,) int
        Seed point indices, distinct.
    sizes : (k,) int
        Size limit of each cluster.
    on_touch : {"stop", "skip"}
        What a cluster does when its closest point belongs to a cluster:
        stop growing (the paper) or pass over that point.
    cover : bool
        Assign every point: after growth, each unassigned point joins the
        cluster of its nearest assigned point (sizes are then exceeded).

    Returns
    -------
    labels : (n,) int
        Cluster index of each point, -1 where unassigned.
    """
    points = np.asarray(points, dtype=np.float64)
    seeds = np.asarray(seeds, dtype=np.int64)
    sizes = np.broadcast_to(np.asarray(sizes, dtype=np.int64), seeds.shape)
    if on_touch not in ("stop", "skip"):
        raise ValueError(f"on_touch={on_touch!r} must be 'stop' or 'skip'")
    if len(np.unique(seeds)) != len(seeds):
        raise ValueError("seed indices must be distinct")
    n = len(points)
    k = min(_FRONTIER_K + 1, n)
    dist, nbr = cKDTree(points).query(points, k=k)
    labels = np.full(n, -1, dtype=np.int64)
    counts = np.zeros(len(seeds), dtype=np.int64)
    heaps = [[] for _ in seeds]
    active = []
    for c, s in enumerate(seeds):
        labels[s] = c
        counts[c] = 1
        _push_neighbours(heaps[c], 0.0, s, dist, nbr, labels)
        if counts[c] < sizes[c]:
            active.append(c)
    while active:
        still = []
        for c in active:
            if _grow_one(c, heaps[c], labels, dist, nbr, on_touch):
                counts[c] += 1
                if counts[c] < sizes[c]:
                    still.append(c)
        active = still
    if cover:
        _assign_rest(points, labels)
    return labels


def _push_neighbours(heap, path, i, dist, nbr, labels):
    # the row as Python numbers, one call each: the same floats and ints as element by element
    for d, j in zip(dist[i, 1:].tolist(), nbr[i, 1:].tolist()):
        if labels[j] < 0:
            heapq.heappush(heap, (path + d, j))


def _grow_one(c, heap, labels, dist, nbr, on_touch):
    """Add the closest free point to cluster ``c``; False when it stops."""
    while heap:
        path, j = heapq.heappop(heap)
        owner = labels[j]
        if owner == c:
            continue  # reached twice through the frontier
        if owner >= 0:
            if on_touch == "stop":
                return False
            continue
        labels[j] = c
        _push_neighbours(heap, path, j, dist, nbr, labels)
        return True
    return False


def _assign_rest(points, labels):
    free = labels < 0
    if free.any() and (~free).any():
        taken = np.flatnonzero(~free)
        _, idx = cKDTree(points[taken]).query(points[free])
        labels[free] = labels[taken[idx]]
