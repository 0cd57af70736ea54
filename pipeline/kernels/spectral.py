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
vector, with a dense ``eigh`` only for small clusters.  Large bands are
solved in slices (spectrum slicing): the band's top is extrapolated from the
lowest ``PILOT`` eigenvalues by a power law, cut into intervals of about
``SLICE`` eigenvalues each, whose counts come from the inertia of K - sI
(Sylvester's law, read off a symmetric LDL^T factor); each interval is
solved around its midpoint, where Lanczos converges in few steps with a
short basis.  The counts are proved, not trusted: each solve asks for one
eigenvalue more than its interval holds, and exactly that one must fall
outside, and the pairs' residuals ||K v - lambda v|| must be small.  Any
failed check repeats the whole solve with one shift below zero (K is
positive semi-definite).  That solve is proved too: the inertia just below
its top eigenvalue must count exactly the pairs found there, else a copy of
a repeated eigenvalue was missed and the dense solver answers (up to
``DENSE_MAX`` points; above, an error).  Every
shift-invert operator is a sparse LU factor in a symmetric minimum-degree
order, which fills less than ARPACK's own.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sl
import scipy.sparse as sp
from scipy.sparse.linalg import ArpackNoConvergence, LinearOperator, eigsh, splu

__all__ = ["spectral_basis", "canonicalize", "probe_vector", "surviving_band"]

DENSE_BELOW = 800       # clusters smaller than this use dense eigh
DENSE_MAX = 5000        # the largest cluster a dense eigh may answer for an incomplete sparse solve (200 MB)
GUARD = 8               # extra vectors so a degenerate space at the cut is whole
DEGENERATE_TOL = 1e-8   # eigenvalues this close (relative to max(1, the largest)) form one eigenspace
_SHIFT = -1e-3          # shift-invert centre, below the zero eigenvalue
PILOT = 24              # lowest eigenvalues from which the top of the band is extrapolated
SLICE = 96              # eigenvalues per slice of the band
ORTHO_TOL = 1e-9        # largest |V^T V - I| accepted from vectors of separate slices
RESIDUAL_TOL = 1e-8     # largest ||K v - lambda v|| accepted, relative to max(1, lambda_max)
PIVOT = 0.01            # SuperLU keeps the diagonal pivot unless 100x smaller than its column's largest
COUNT_GAP = 1e-6        # the count that proves a plain solve complete is taken this far (relative) below its top group


def surviving_band(cluster_points, spacing, noise, gain):
    """How many of a cluster's lowest eigenvectors keep ``gain`` of their amplitude under noise.

    Noise that moves the points across the surface (standard deviation
    ``noise`` per tangent axis) makes every suspect point stand for an
    original point about that far away: the mark's field is blurred by a
    Gaussian, which keeps exp(-lambda noise^2 / 2) of an eigenvector of
    eigenvalue lambda (of the surface's Laplace-Beltrami operator).  Weyl's
    law puts the k-th eigenvalue of a patch of area A near 4 pi k / A; a
    cluster of n_c points at median spacing s covers about n_c s^2.  So the
    eigenvectors below

        K = ln(1 / gain) n_c s^2 / (2 pi noise^2)

    keep at least ``gain``.

    Parameters
    ----------
    cluster_points : int
        n_c, points per cluster.
    spacing : float
        s, median distance to the nearest point.
    noise : float
        Standard deviation of the motion along one tangent axis (same units).
    gain : float
        In (0, 1).

    Returns
    -------
    float
        K (not rounded).
    """
    return float(np.log(1.0 / gain) * cluster_points * spacing**2 / (2.0 * np.pi * noise**2))


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


def spectral_basis(laplacian, n_vectors, *, degenerate_tol=DEGENERATE_TOL):
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
    """The k lowest eigenpairs of a sparse PSD matrix by shift-invert Lanczos, sliced when it pays."""
    n = laplacian.shape[0]
    v0 = 1.0 + probe_vector(n, 0.5)
    # slicing pays when the band is a small share of the spectrum (Weyl's law holds there)
    if 2 * PILOT < k <= n // 6:
        try:
            found = _sliced(laplacian, k, v0)
            if found is not None:
                return found
        except (ArpackNoConvergence, RuntimeError):   # (a singular factor) the plain shift below
            pass
    values, vectors = eigsh(laplacian, k=k, sigma=_SHIFT, which="LM", v0=v0, ncv=min(n, k + 100), tol=0.0,
                            OPinv=_shift_invert(laplacian, _SHIFT))
    complete = _complete(laplacian, values)
    if complete or (complete is None and n > DENSE_MAX):
        return values, vectors          # proved; or not disproved, and too large for the dense solver
    # (not proved, or disproved, up to DENSE_MAX points: the dense solver answers)
    # Lanczos from one start vector can miss copies of a repeated eigenvalue, and which copies
    # it finds then depends on ARPACK's random restarts, a state of the whole process: the
    # basis would differ from one call to the next.  The dense solver finds them all.
    if n > DENSE_MAX:
        raise np.linalg.LinAlgError(f"the {k} lowest eigenvectors of a cluster of {n} points cannot be solved "
                                    f"reproducibly (a repeated eigenvalue; the dense solver takes at most "
                                    f"{DENSE_MAX} points): use smaller clusters")
    return sl.eigh(laplacian.toarray(), subset_by_index=[0, k - 1])


def _complete(laplacian, values):
    """Whether ``values`` hold every eigenvalue below their top group (Sylvester's count).

    The top group (eigenvalues within :data:`DEGENERATE_TOL` of the largest)
    may go on past the band; :data:`GUARD` keeps it off the vectors used.
    Below it, the count just under the group must equal the values found
    there: a copy of a repeated eigenvalue that Lanczos missed shows as one
    more.  None when the factor pivoted or is singular (nothing proved).
    """
    values = np.sort(values)
    low = values[values >= values[-1] - DEGENERATE_TOL * max(1.0, abs(values[-1]))][0]
    shift = low - COUNT_GAP * max(1.0, abs(low))
    try:
        count = _inertia(laplacian, shift)
    except RuntimeError:          # a singular factor: an eigenvalue at the shift
        return None
    return None if count is None else count == int((values < shift).sum())


def _sliced(laplacian, k, v0):
    """The k lowest eigenpairs solved slice by slice; None when a check fails.

    Returns
    -------
    values : (k,) float, ascending
    vectors : (n, k) float
    """
    top = 1.1 * _band_top(laplacian, k, v0)
    total = _inertia(laplacian, top) if top > 0.0 else None
    for _ in range(4):                           # the estimate was low: widen the band
        if total is None or total >= k:
            break
        top *= 1.15 * k / max(total, PILOT)
        total = _inertia(laplacian, top)
    if total is None or total < k:
        return None
    n_slices = max(1, round(k / SLICE))
    edges = np.linspace(0.0, top, n_slices + 1)
    edges[0] = -0.01 * edges[1]                  # the zero eigenvalue, rounded either way, is inside
    counts = [0] + [_inertia(laplacian, e) for e in edges[1:-1]] + [total]
    if None in counts or np.any(np.diff(counts) < 0):
        return None
    values, vectors = [], []
    for lo, hi, m in zip(edges[:-1], edges[1:], np.diff(counts)):
        found = _interval(laplacian, lo, hi, int(m), v0)
        if found is None:
            return None
        values.append(found[0])
        vectors.append(found[1])
    values, vectors = np.concatenate(values), np.hstack(vectors)
    keep = np.argsort(values, kind="stable")[:k]
    values, vectors = values[keep], vectors[:, keep]
    if np.abs(vectors.T @ vectors - np.eye(k)).max() > ORTHO_TOL or not _converged(laplacian, values, vectors):
        return None
    return values, vectors


def _interval(laplacian, lo, hi, m, v0):
    """The m eigenpairs in [lo, hi), proved to be all of them; None otherwise.

    Lanczos around the midpoint returns the m + 1 nearest eigenvalues; every
    eigenvalue of the interval lies nearer than any outside it, so the
    interval holds exactly m when exactly m of those fall inside.
    """
    n = laplacian.shape[0]
    if m == 0:
        return np.empty(0), np.empty((n, 0))
    if m + 1 >= n - 1:
        return None
    mid = 0.5 * (lo + hi)
    values, vectors = eigsh(laplacian, k=m + 1, sigma=mid, which="LM", v0=v0, OPinv=_shift_invert(laplacian, mid),
                            ncv=min(n, m + 1 + max(20, m // 2)), tol=0.0)
    inside = (values >= lo) & (values < hi)
    if int(inside.sum()) != m:
        return None
    return values[inside], vectors[:, inside]


def _converged(laplacian, values, vectors):
    """True when every pair's residual ||K v - lambda v|| is below ``RESIDUAL_TOL`` (relative)."""
    residual = np.linalg.norm(laplacian @ vectors - vectors * values, axis=0)
    return bool(residual.max(initial=0.0) <= RESIDUAL_TOL * max(1.0, float(np.abs(values).max(initial=0.0))))


def _shift_invert(laplacian, shift):
    """(K - shift I)^-1 as an operator, from a fill-reducing symmetric LU factor.

    ARPACK's own factor orders the columns for an unsymmetric matrix; the
    symmetric minimum-degree order with diagonal pivots has less fill and
    solves faster.  Raises RuntimeError when K - shift I is singular.
    """
    n = laplacian.shape[0]
    return LinearOperator((n, n), matvec=_factor(laplacian, shift, PIVOT).solve, dtype=np.float64)


def _factor(laplacian, shift, pivot):
    """SuperLU factor of K - shift I in a symmetric minimum-degree order."""
    shifted = (laplacian - shift * sp.identity(laplacian.shape[0], format="csc")).tocsc()
    return splu(shifted, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=pivot, options={"SymmetricMode": True})


def _inertia(laplacian, shift):
    """Number of eigenvalues below ``shift`` (Sylvester's law); None when the factor pivoted.

    A symmetric ordering with no row pivoting makes the LU factor an LDL^T
    one, whose diagonal has as many negative entries as K - shift I has
    negative eigenvalues.  The count only plans the slices: each slice
    proves its own.
    """
    lu = _factor(laplacian, shift, 0.0)
    if not np.array_equal(lu.perm_r, lu.perm_c):
        return None
    return int((lu.U.diagonal() < 0).sum())


def _band_top(laplacian, k, v0):
    """Estimate of the k-th lowest eigenvalue: the lowest ``PILOT`` extrapolated by a power law.

    On a sampled surface the eigenvalues grow about linearly with their
    index (Weyl's law in 2D); the exponent fitted to the upper half of the
    pilot adapts to other shapes.  The smaller of the linear and the fitted
    extrapolation is returned: a low estimate only costs a recount.
    """
    n = laplacian.shape[0]
    low = np.sort(eigsh(laplacian, k=PILOT, sigma=_SHIFT, which="LM", v0=v0, ncv=min(n, 3 * PILOT), tol=1e-4,
                        OPinv=_shift_invert(laplacian, _SHIFT), return_eigenvectors=False))
    if not low[-1] > 0.0:
        return 0.0
    j = np.arange(PILOT // 2, PILOT)
    exponent = np.polyfit(np.log(j), np.log(np.maximum(low[j], low[-1] * 1e-9)), 1)[0]
    ratio = (k - 1) / (PILOT - 1)
    return float(low[-1] * min(ratio, ratio ** float(np.clip(exponent, 0.5, 2.0))))


def canonicalize(values, vectors, *, degenerate_tol=DEGENERATE_TOL):
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
