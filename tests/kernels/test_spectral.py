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


def _miscount(real):
    """An inertia count one short at every interior edge (as a wrong LDL^T pivot sign would give)."""
    calls = []

    def wrong(laplacian, shift):
        calls.append(shift)
        return real(laplacian, shift) - (1 if len(calls) > 1 else 0)
    return wrong


@pytest.mark.parametrize("case", ["sliced", "miscounted", "plain"])
def test_sliced_fallback_and_plain_shift_give_the_dense_basis(monkeypatch, case):
    # sliced: several slices solved around their midpoints; miscounted: a slice's count is
    # wrong, its own check catches it and the solve falls back; plain: slicing disabled
    if case == "miscounted":
        monkeypatch.setattr(spectral, "_inertia", _miscount(spectral._inertia))
    if case == "plain":
        monkeypatch.setattr(spectral, "_sliced", lambda *a: None)
    k = _laplacian(1500, rng=2)   # (its eigenvalue 6 is highly degenerate: the band stays below it)
    values, basis = spectral_basis(k, 150)
    # whichever path the solve ends on (it depends on rounding), the result is the dense one
    from scipy.linalg import eigh
    v2, b2 = canonicalize(*eigh(k.toarray(), subset_by_index=[0, 157]))
    assert np.allclose(values, v2[:150], atol=1e-9)
    assert np.allclose(basis, b2[:, :150], atol=1e-7)
    assert basis_digest(basis) == basis_digest(b2[:, :150])


def test_a_band_with_a_degenerate_eigenvalue_is_solved_exactly():
    # eigenvalue 6 of this graph has a multiplicity that Lanczos from one start vector may not
    # resolve around a far shift; whichever way the solver takes (a slice, or the plain shift
    # after a refused slice: that depends on rounding, so on the BLAS kernel), the result must
    # be the dense solver's, to its canonical signs
    k = _laplacian(1500, rng=2)
    values, basis = spectral_basis(k, 200)
    from scipy.linalg import eigh
    v2, b2 = canonicalize(*eigh(k.toarray(), subset_by_index=[0, 207]))
    assert np.allclose(values, v2[:200], atol=1e-9)
    assert np.allclose(k @ basis, basis * values, atol=1e-7)
    assert np.allclose(basis.T @ basis, np.eye(200), atol=1e-9)
    assert basis_digest(basis) == basis_digest(b2[:, :200])


def test_a_plain_solve_that_misses_copies_of_a_repeated_eigenvalue_gives_way_to_the_dense_one():
    # the demo blob's first covering cluster of 2,000 (1,816 points): eigenvalue 7 of its graph has
    # multiplicity 10 (indices 314 to 323), too many vectors for a band of 320 to slice (328 > 1816 // 6).
    # Lanczos from one start vector found 7 of the 10, a different 7 at each call (ARPACK's random
    # restarts are a state of the whole process), so the basis changed from call to call
    from dataclasses import replace

    from scipy.linalg import eigh

    from pipeline import config
    from pipeline.demo import procedural_shape
    from pipeline.watermark import compute_reference

    params = replace(config.watermark_params(config.load_config(ROOT / "configs" / "default.yaml")),
                     n_clusters=3, cluster_size=2000)
    points = procedural_shape("blob", 9000, seed=1) * 100.0
    ref = compute_reference(points, params)
    cluster = (points - ref.centre)[ref.specs[0].members]
    a, _ = connect_components(cluster, radius_graph(cluster, valence_radius(cluster, params.valence)))
    k = laplacian(a)
    lam = np.linalg.eigvalsh(k.toarray())
    assert len(cluster) == 1816 and int((np.abs(lam[:params.n_coefficients + 8] - 7.0) < 1e-6).sum()) == 10
    digests = {basis_digest(spectral_basis(k, params.n_coefficients)[1]) for _ in range(3)}
    v2, b2 = canonicalize(*eigh(k.toarray(), subset_by_index=[0, params.n_coefficients + 7]))
    assert digests == {basis_digest(b2[:, :params.n_coefficients])}
    assert ref.digests()["basis"][0] in digests


def test_a_solve_is_complete_only_when_the_count_below_its_top_group_matches():
    k = _laplacian(1200, rng=4)
    lam = np.linalg.eigvalsh(k.toarray())
    found = lam[:60]
    assert spectral._complete(k.tocsc(), found) is True
    assert spectral._complete(k.tocsc(), np.delete(found, 30)) is False      # one missed inside the band
    assert spectral._complete(k.tocsc(), np.append(np.delete(found, 30), lam[60])) is False   # and replaced


@pytest.mark.parametrize("proved", [False, None])
def test_a_plain_solve_not_proved_complete_is_the_dense_one_or_an_error_above_the_dense_limit(monkeypatch, proved):
    # 308 vectors of 1,200 points: more than 1,200 // 6, so one plain solve; its count says it missed
    # one (False), or cannot be taken (None)
    from scipy.linalg import eigh

    k = _laplacian(1200, rng=4)
    monkeypatch.setattr(spectral, "_complete", lambda *a: proved)
    values, basis = spectral_basis(k, 300)
    v2, b2 = canonicalize(*eigh(k.toarray(), subset_by_index=[0, 307]))
    assert np.array_equal(values, v2[:300]) and np.array_equal(basis, b2[:, :300])
    monkeypatch.setattr(spectral, "DENSE_MAX", 1000)
    if proved is None:           # nothing proved and too large for the dense solver: the solve stands
        values, basis = spectral_basis(k, 300)
        assert np.allclose(k @ basis, basis * values, atol=1e-7)
    else:
        with pytest.raises(np.linalg.LinAlgError, match="cluster of 1200 points cannot be solved reproducibly"):
            spectral_basis(k, 300)


def test_slices_whose_pairs_miss_the_eigenproblem_are_refused(monkeypatch):
    # orthonormal vectors that are not eigenvectors (a slice's pairs mixed by a small
    # rotation, as an inexact factor would leave them) pass the count and orthogonality
    # checks; the residual check refuses them and the plain shift solves
    real = spectral._interval

    def mixed(laplacian, lo, hi, m, v0):
        values, vectors = real(laplacian, lo, hi, m, v0)
        c, s = np.cos(1e-4), np.sin(1e-4)
        vectors = vectors.copy()
        vectors[:, [0, 1]] = vectors[:, [0, 1]] @ np.array([[c, -s], [s, c]])
        return values, vectors

    k = _laplacian(1500, rng=3).tocsc()
    v0 = 1.0 + spectral.probe_vector(k.shape[0], 0.5)
    monkeypatch.setattr(spectral, "_interval", mixed)
    assert spectral._sliced(k, 158, v0) is None
    values, basis = spectral_basis(k, 150)
    assert np.allclose(k @ basis, basis * values, atol=1e-7)


def test_inertia_counts_the_eigenvalues_below_a_shift():
    k = _laplacian(1200, rng=4)
    lam = np.linalg.eigvalsh(k.toarray())
    for shift in (0.5 * (lam[10] + lam[11]), 0.5 * (lam[99] + lam[100]), 0.5 * (lam[300] + lam[301])):
        assert spectral._inertia(k.tocsc(), shift) == int((lam < shift).sum())


def test_an_interval_is_refused_when_its_count_is_wrong():
    k = _laplacian(1200, rng=4).tocsc()
    lam = np.linalg.eigvalsh(k.toarray())
    lo, hi = 0.5 * (lam[20] + lam[21]), 0.5 * (lam[59] + lam[60])
    v0 = 1.0 + spectral.probe_vector(k.shape[0], 0.5)
    values, vectors = spectral._interval(k, lo, hi, 39, v0)
    assert np.allclose(values, lam[21:60], atol=1e-9) and vectors.shape == (1200, 39)
    assert spectral._interval(k, lo, hi, 38, v0) is None   # one too few: the 39th is inside
    assert spectral._interval(k, lo, hi, 40, v0) is None   # one too many: only 39 are inside


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


def test_the_surviving_band_keeps_its_gain_under_tangential_noise():
    # a flat 50 x 50 grid of spacing 1: move every point across the surface by Gaussian noise and
    # read each eigenvector at the nearest original point, as a detector of a noisy copy does
    rng = np.random.default_rng(3)
    g = np.stack(np.meshgrid(np.arange(50.0), np.arange(50.0)), -1).reshape(-1, 2)
    pts = np.column_stack([g, np.zeros(len(g))])
    a, _ = connect_components(pts, radius_graph(pts, valence_radius(pts, 12)))
    noise = 1.0
    band = spectral.surviving_band(len(pts), 1.0, noise, 0.6)
    assert 150 < band < 260                                  # ln(1/0.6) 2500 / (2 pi)
    _, basis = spectral_basis(laplacian(a), int(2 * band) + 10)
    from scipy.spatial import cKDTree
    tree = cKDTree(g)
    near = np.concatenate([tree.query(g + rng.normal(0.0, noise, g.shape))[1] for _ in range(4)])
    source = np.tile(np.arange(len(g)), 4)
    gain = (basis[source] * basis[near]).sum(axis=0) / (basis[source] ** 2).sum(axis=0)

    def around(k):
        return float(np.mean(gain[int(k) - 10:int(k) + 10]))

    assert 0.45 < around(band) < 0.8, around(band)
    assert around(band / 2) > around(band) + 0.1 and around(2 * band) < around(band) - 0.1
