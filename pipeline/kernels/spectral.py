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

The solver is ARPACK's Lanczos in shift-invert mode, started from a fixed
vector, with a dense ``eigh`` only for small clusters.  The shift sits inside
the wanted band, at ``FOLD`` times its top (extrapolated from the lowest
``PILOT`` eigenvalues by a power law): the band folds about the shift, so its
top stands about twice as far from the unwanted eigenvalues, relative to the
distance from the shift, as with a shift below zero, and Lanczos needs fewer
steps.  The k eigenvalues nearest the shift are the lowest k exactly when
the farthest of them lies farther from the shift than zero does (K is
positive semi-definite); otherwise the solve is repeated with a small
negative shift.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sl
from scipy.sparse.linalg import ArpackNoConvergence, eigsh

__all__ = ["spectral_basis", "canonicalize", "probe_vector"]

DENSE_BELOW = 800       # clusters smaller than this use dense eigh
GUARD = 8               # extra vectors so a degenerate space at the cut is whole
_SHIFT = -1e-3          # shift-invert centre, below the zero eigenvalue
FOLD = 0.45             # folded shift, as a share of the estimated top of the wanted band
PILOT = 24              # lowest eigenvalues from which the top of the band is extrapolated


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
        values, vectors = _lowest(laplacian.tocsc(), k)
    values, vectors = canonicalize(values, vectors, degenerate_tol=degenerate_tol)
    return values[:n_vectors], vectors[:, :n_vectors]


def _lowest(laplacian, k):
    """The k lowest eigenpairs of a sparse PSD matrix by shift-invert Lanczos, folded when it pays."""
    n = laplacian.shape[0]
    v0 = 1.0 + probe_vector(n, 0.5)
    # folding pays when the band is a small share of the spectrum (Weyl's law holds there)
    if 2 * PILOT < k <= n // 6:
        try:
            sigma = FOLD * _band_top(laplacian, k, v0)
            if sigma > 0.0:
                values, vectors = eigsh(laplacian, k=k, sigma=sigma, which="LM", v0=v0, ncv=min(n, k + 72),
                                        tol=0.0)
                # the k nearest the shift reach down to 0 (hence are the lowest k) when
                # the farthest of them is farther from the shift than 0 is
                if np.abs(values - sigma).max() > sigma * (1.0 + 1e-6):
                    return values, vectors
        except (ArpackNoConvergence, RuntimeError):   # (a singular factor) the plain shift below
            pass
    return eigsh(laplacian, k=k, sigma=_SHIFT, which="LM", v0=v0, ncv=min(n, k + 100), tol=0.0)


def _band_top(laplacian, k, v0):
    """Estimate of the k-th lowest eigenvalue: the lowest ``PILOT`` extrapolated by a power law.

    On a sampled surface the eigenvalues grow about linearly with their
    index (Weyl's law in 2D); the exponent fitted to the upper half of the
    pilot adapts to other shapes.  The smaller of the linear and the fitted
    extrapolation is returned: a low estimate only folds less.
    """
    n = laplacian.shape[0]
    low = np.sort(eigsh(laplacian, k=PILOT, sigma=_SHIFT, which="LM", v0=v0, ncv=min(n, 3 * PILOT), tol=1e-4,
                        return_eigenvectors=False))
    if not low[-1] > 0.0:
        return 0.0
    j = np.arange(PILOT // 2, PILOT)
    exponent = np.polyfit(np.log(j), np.log(np.maximum(low[j], low[-1] * 1e-9)), 1)[0]
    ratio = (k - 1) / (PILOT - 1)
    return float(low[-1] * min(ratio, ratio ** float(np.clip(exponent, 0.5, 2.0))))


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
