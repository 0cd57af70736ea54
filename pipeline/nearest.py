"""Exact nearest neighbours for the registration loops, through pykdtree.

ICP asks the same question thousands of times per check: the nearest
original point of each moved suspect point.  SciPy's ``cKDTree`` answers it;
pykdtree answers it with the same distances and indices (both exact; a tie
between equidistant points is the only place they may pick differently) in a
third to a half of the time, and most of all for points far from the
surface, which is where an innocent suspect's points lie.  Kept out of
:mod:`pipeline.kernels` (pure NumPy/SciPy): the kernels take any tree with
cKDTree's ``query``.  pykdtree parallelises with OpenMP; the entry points pin
it to one thread (:mod:`pipeline.threads`).
"""

from __future__ import annotations

import numpy as np
from pykdtree.kdtree import KDTree

__all__ = ["NearestTree"]


class NearestTree:
    """A k-d tree over fixed points answering ``cKDTree.query``'s k-nearest questions.

    Parameters
    ----------
    points : (m, d) float
    """

    def __init__(self, points):
        self.data = np.ascontiguousarray(points, dtype=np.float64)
        self._tree = KDTree(self.data)

    def query(self, x, k=1, distance_upper_bound=np.inf):
        """Distances and indices of the ``k`` nearest points of each row of ``x``.

        Parameters
        ----------
        x : (n, d) float
        k : int
        distance_upper_bound : float
            Neighbours farther than this are missing.

        Returns
        -------
        dist : (n,) or (n, k) float64
        idx : (n,) or (n, k) int64
            A missing neighbour has distance ``inf`` and index ``m``, as in
            cKDTree: one past the bound, past the tree's ``m`` points (``k``
            greater than ``m``), or of a query row that is not finite (which
            cKDTree refuses).
        """
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, self.data.shape[1])
        bound = float(distance_upper_bound)
        dist, idx = self._tree.query(x, k=int(k), distance_upper_bound=bound if np.isfinite(bound) else None)
        idx = idx.astype(np.int64)
        # pykdtree gives a neighbour it has none for (k past m, a NaN or inf row) its largest
        # index, 4294967295, and a finite distance, 1.3e154
        missing = idx >= len(self.data)
        if missing.any():
            idx[missing] = len(self.data)
            dist = np.where(missing, np.inf, dist)
        return dist, idx
