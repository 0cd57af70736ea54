"""Digests of a watermark reference: what detection must rebuild exactly.

A cluster's membership is hashed exactly.  A spectral basis is hashed through
a fixed probe: the projections of every basis vector on one fixed
pseudo-random vector, rounded to 4 decimals.  The projections are O(1), so
floating-point noise of other BLAS builds or thread counts (about 1e-13) does
not change them, while any real change of the clusters, the mesh or the
eigenvectors (order, sign, rotation) does.
"""

from __future__ import annotations

import hashlib

import numpy as np

__all__ = ["membership_digest", "basis_digest"]


def membership_digest(members):
    """16 hex digits of sha256 over the sorted member indices (int64, little-endian).

    Parameters
    ----------
    members : (n_c,) int
    """
    data = np.sort(np.asarray(members, dtype="<i8")).tobytes()
    return hashlib.sha256(b"pointmark/members/" + data).hexdigest()[:16]


def _probe(n):
    raw = hashlib.shake_256(b"pointmark/basis-probe/" + int(n).to_bytes(8, "big")).digest((n + 7) // 8)
    return 2.0 * np.unpackbits(np.frombuffer(raw, dtype=np.uint8))[:n] - 1.0


def basis_digest(basis):
    """16 hex digits over the rounded probe projections of a basis.

    Parameters
    ----------
    basis : (n_c, K) float
        Orthonormal columns.
    """
    basis = np.asarray(basis, dtype=np.float64)
    n, k = basis.shape
    projection = _probe(n) @ basis   # unit columns: each about N(0, 1)
    ticks = np.rint(projection * 1e4).astype("<i8")
    head = f"{n}x{k}/".encode()
    return hashlib.sha256(b"pointmark/basis/" + head + ticks.tobytes()).hexdigest()[:16]
