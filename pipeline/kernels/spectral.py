"""Mesh spectral basis: the low-frequency eigenvectors of K = D - A (paper, "Mesh-Spectral Analysis").

The basis must come out the same wherever it is computed (embedding in one
process, detection in another, with other thread counts), so it is made
canonical:

* order: ascending eigenvalue;
* near-degenerate eigenvalues (relative gap below ``degenerate_tol``): the
  eigenspace is rotated to the eigenvectors of a fixed auxiliary diagonal
  operator restricted to it, which fixes a basis inside the space;
* sign: each vector is flipped so that its dot product with a fixed
  pseudo-random probe vector is positive.

The solver is ARPACK's Lanczos in shift-invert mode around a small negative
shift (K is positive semi-definite), started from a fixed vector, with a
dense ``eigh`` only for small clusters.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sl
from scipy.sparse.linalg import eigsh

__all__ = ["spectral_basis", "canonicalize", "probe_vector"]

DENSE_BELOW = 800       # clusters smaller than this use dense eigh
GUARD = 8               # extra vectors so a degenerate space at the cut is whole
_SHIFT = -1e-3          # shift-invert centre, below the zero eigenvalue


def probe_vector(n, salt):
    """A fixed pseudo-random vector, the same on every machine.

    Parameters
    ----------
    n : int
    salt : float

    Returns
    -------
    (n,) float, entries in [-1, 1]
    """
    i = np.arange(n, dtype=np.float64)
    return np.cos(i * 0.6180339887498949 * np.pi + salt * (1.0 + i) ** 0.5)


def spectral_basis(laplacian, n_vectors, *, degenerate_tol=1e-8):
    """The ``n_vectors`` lowest eigenpairs of a graph Laplacian, canonical.

    Parameters
    ----------
    laplacian : (n, n) sparse symmetric positive semi-definite
    n_vectors : int
        Number of basis vectors e_i wanted (lowest frequencies first).
    degenerate_tol : float
        Eigenvalues closer than ``degenerate_tol * max(1, lambda_max)`` are
        treated as one eigenspace.

    Returns
    -------
    eigenvalues : (n_vectors,) float, ascending
    basis : (n, n_vectors) float, orthonormal columns
    """
    n = laplacian.shape[0]
    if n_vectors > n:
        raise ValueError(f"n_vectors={n_vectors} exceeds the cluster size {n}")
    k = min(n, n_vectors + GUARD)
    if n < DENSE_BELOW or k > n // 2:
        values, vectors = sl.eigh(laplacian.toarray(), subset_by_index=[0, k - 1])
    else:
        v0 = 1.0 + probe_vector(n, 0.5)
        values, vectors = eigsh(
            laplacian.tocsc(), k=k, sigma=_SHIFT, which="LM", v0=v0,
            ncv=min(n, k + 100), tol=0.0,
        )
    values, vectors = canonicalize(values, vectors, degenerate_tol=degenerate_tol)
    return values[:n_vectors], vectors[:, :n_vectors]


def canonicalize(values, vectors, *, degenerate_tol=1e-8):
    """Put eigenpairs in canonical order, in-space rotation and sign.

    Parameters
    ----------
    values : (k,) float
    vectors : (n, k) float, orthonormal columns

    Returns
    -------
    values : (k,) float, ascending
    vectors : (n, k) float
    """
    order = np.argsort(values, kind="stable")
    values = np.asarray(values, dtype=np.float64)[order]
    vectors = np.array(vectors, dtype=np.float64)[:, order]
    n = vectors.shape[0]
    scale = max(1.0, float(np.abs(values).max()))
    auxiliary = probe_vector(n, 1.5)
    start = 0
    for stop in _group_ends(values, degenerate_tol * scale):
        if stop - start > 1:
            block = vectors[:, start:stop]
            mixed = block.T @ (auxiliary[:, None] * block)
            _, rotation = np.linalg.eigh(mixed)
            vectors[:, start:stop] = block @ rotation
            values[start:stop] = values[start:stop].mean()
        start = stop
    signs = np.sign(probe_vector(n, 2.5) @ vectors)
    signs[signs == 0] = 1.0
    return values, vectors * signs


def _group_ends(values, tol):
    """End indices (exclusive) of runs of eigenvalues closer than ``tol``."""
    gaps = np.diff(values) > tol
    return list(np.flatnonzero(gaps) + 1) + [len(values)]
