import os
import subprocess
import sys

import numpy as np
import pytest

from pipeline.kernels.graph import connect_components, laplacian, radius_graph, valence_radius
from pipeline.kernels import spectral
from pipeline.kernels.digest import basis_digest
from pipeline.kernels.spectral import canonicalize, spectral_basis
from tests.conftest import ROOT, sphere_patch


def _laplacian(n, rng=0):
    pts = sphere_patch(n, rng)
    a, _ = connect_components(pts, radius_graph(pts, valence_radius(pts, 12)))
    return laplacian(a)


@pytest.mark.parametrize("n", [500, 2500])
def test_basis_solves_the_eigenproblem(n):
    k = _laplacian(n)
    values, basis = spectral_basis(k, 64)
    assert np.allclose(basis.T @ basis, np.eye(64), atol=1e-8)
    assert np.allclose(k @ basis, basis * values, atol=1e-7)
    assert np.all(np.diff(values) >= -1e-12)
    assert abs(values[0]) < 1e-8


def test_sparse_and_dense_paths_agree():
    k = _laplacian(1200)
    v1, b1 = spectral_basis(k, 40)
    from scipy.linalg import eigh
    v2, b2 = eigh(k.toarray(), subset_by_index=[0, 47])
    v2, b2 = canonicalize(v2, b2)
    assert np.allclose(v1, v2[:40], atol=1e-9)
    assert np.allclose(b1, b2[:, :40], atol=1e-7)


@pytest.mark.parametrize("fold,folded_returned", [(spectral.FOLD, True), (3.0, False), (0.0, False)])
def test_folded_shift_fallback_and_plain_shift_give_the_dense_basis(monkeypatch, fold, folded_returned):
    # FOLD: the shift inside the band; 3.0: past its top, so the nearest eigenvalues miss
    # the bottom and the solve must fall back; 0.0: the plain shift below zero
    monkeypatch.setattr(spectral, "FOLD", fold)
    shifts = []
    real = spectral.eigsh

    def recording(*args, **kwargs):   # the real ARPACK call, its shifts noted
        shifts.append(kwargs["sigma"])
        return real(*args, **kwargs)

    monkeypatch.setattr(spectral, "eigsh", recording)
    k = _laplacian(1500, rng=2)
    values, basis = spectral_basis(k, 200)
    assert (shifts[-1] > 0) == folded_returned and len(shifts) == (3 if fold == 3.0 else 2)
    from scipy.linalg import eigh
    v2, b2 = canonicalize(*eigh(k.toarray(), subset_by_index=[0, 207]))
    assert np.allclose(values, v2[:200], atol=1e-9)
    assert np.allclose(basis, b2[:, :200], atol=1e-7)
    assert basis_digest(basis) == basis_digest(b2[:, :200])


def test_canonical_form_undoes_sign_flips_and_rotations_in_degenerate_spaces():
    rng = np.random.default_rng(3)
    n = 200
    q, _ = np.linalg.qr(rng.normal(size=(n, 6)))
    values = np.array([0.0, 1.0, 2.0, 2.0, 2.0, 3.0])   # a triple eigenvalue
    ref_v, ref_b = canonicalize(values, q)
    rot, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    mixed = q.copy()
    mixed[:, 2:5] = q[:, 2:5] @ rot                      # another basis of the same space
    mixed *= np.array([1, -1, 1, -1, 1, -1])
    got_v, got_b = canonicalize(values, mixed)
    assert np.allclose(got_v, ref_v)
    assert np.allclose(got_b, ref_b, atol=1e-10)


_CHILD = """
import json, sys
import numpy as np
from pipeline.kernels.graph import connect_components, laplacian, radius_graph, valence_radius
from pipeline.kernels.spectral import spectral_basis
from tests.conftest import sphere_patch
pts = sphere_patch(4000, 11)
a, _ = connect_components(pts, radius_graph(pts, valence_radius(pts, 12)))
_, basis = spectral_basis(laplacian(a), 320)
np.save(sys.argv[1], basis)
"""


@pytest.mark.slow
def test_basis_is_identical_across_processes_and_thread_counts(tmp_path):
    outs = []
    for threads in ("1", "2"):
        env = dict(os.environ, OMP_NUM_THREADS=threads, OPENBLAS_NUM_THREADS=threads,
                   MKL_NUM_THREADS=threads, PYTHONPATH=str(ROOT))
        out = tmp_path / f"basis{threads}.npy"
        subprocess.run([sys.executable, "-c", _CHILD, str(out)], check=True, env=env, cwd=ROOT)
        outs.append(np.load(out))
    assert outs[0].shape == (4000, 320)
    assert np.abs(outs[0] - outs[1]).max() < 1e-8
