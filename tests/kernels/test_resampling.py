import numpy as np
import pytest
from scipy.spatial import cKDTree

from pipeline.kernels import graph, spectral
from pipeline.kernels.modulation import spread_reach
from pipeline.kernels.resampling import (
    estimate_normals, fit_spectral_displacement, nearest_spacing, normal_noise, snap_to_original,
)
from tests.conftest import sphere_patch

# the fit's settings, given as the detection config gives them
FIT = {"iterations": 3, "ridge": 1e-3, "tangential_gate": 0.25, "ratio_gate": 0.5, "gate_switch": 0.4}


def _basis(points, k=40):
    radius = graph.valence_radius(points, 12)
    adjacency, _ = graph.connect_components(points, graph.radius_graph(points, radius))
    _, vectors = spectral.spectral_basis(graph.laplacian(adjacency), k)
    return vectors


def test_snap_keeps_matches_under_half_the_spacing_only():
    pts = sphere_patch(2000)
    half = 0.5 * nearest_spacing(pts)
    rng = np.random.default_rng(1)
    direction = rng.normal(size=pts.shape)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    moved = pts + 0.2 * half[:, None] * direction
    order = rng.permutation(len(pts))
    resampled, matched = snap_to_original(pts, moved[order])
    assert matched.all()
    assert np.allclose(resampled, moved)
    far = 1.5 * pts                                   # a shell well away from the surface
    assert not snap_to_original(pts, far)[1].any()


def test_normal_noise_measures_offsets_along_the_normals():
    rng = np.random.default_rng(2)
    plane = np.c_[rng.uniform(-1, 1, (5000, 2)), np.zeros(5000)]
    noisy = plane + np.c_[np.zeros((5000, 2)), rng.normal(0, 0.01, 5000)]
    sigma = normal_noise(noisy, plane, estimate_normals(plane))
    assert abs(sigma - 0.01) < 0.001
    assert normal_noise(plane[:0], plane[:0], plane[:0]) == 0.0


def test_spectral_fit_recovers_coefficients_from_fresh_samples():
    # The suspect shares no point with the original: a denser, independent
    # sample of the same surface, deformed by E @ delta.  Motion along the
    # surface cannot be seen in such a sample, so single coefficients are
    # noisy; what detection needs, groups of chips correlated with the
    # sequence, must come out right.  Subtracting the fit of the undeformed
    # sample removes the bias of the surface's curvature.
    original = sphere_patch(3000, rng=0)
    basis = _basis(original)
    rng = np.random.default_rng(3)
    delta = rng.choice([-1.0, 1.0], size=(basis.shape[1], 3)) * 0.004
    fresh = sphere_patch(12000, rng=7)
    _, owner = cKDTree(original).query(fresh)
    suspect = (fresh + (basis @ delta)[owner])[rng.permutation(len(fresh))]
    normals = estimate_normals(original)
    unrelated = rng.choice([-1.0, 1.0], size=delta.shape)
    for gate_switch in (0.0, np.inf):
        fit = [
            fit_spectral_displacement(original, normals, cloud, [np.arange(len(original))], [basis],
                                      **{**FIT, "iterations": 2, "ridge": 1.0, "gate_switch": gate_switch})
            for cloud in (suspect, fresh)
        ]
        assert fit[0][1] == [len(suspect)]
        estimate = fit[0][0][0] - fit[1][0][0]
        assert np.corrcoef(estimate.ravel(), delta.ravel())[0, 1] > 0.5
        assert abs(np.corrcoef(estimate.ravel(), unrelated.ravel())[0, 1]) < 0.25
        chips = (estimate * np.sign(delta)).reshape(10, -1).sum(axis=1)
        assert (chips > 0).all()


def test_normal_only_fit_recovers_a_normal_direction_watermark_from_fresh_samples():
    # The watermark moved the original along its normals (along_normals); a
    # fresh, denser sample of that surface shares no point with it.  The
    # normal-only model fits it better than the xyz model, which also tries to
    # explain motion along the surface that is not there.
    normal = _normal_fit_score(None, junk=0, normal_only=True)
    assert normal > 0.5 and normal > _normal_fit_score(None, junk=0, normal_only=False)


def _normal_mark_and_samples(junk=0):
    """A normal-direction mark on a sphere patch, a fresh sample of it and of the unmarked patch.

    ``junk`` points are added to both samples, each off the surface along its
    normal by 1 to 3 median spacings: within the fit's reach, far beyond the mark.
    """
    from pipeline.kernels.modulation import along_normals

    original = sphere_patch(3000, rng=0)
    basis = _basis(original)
    normals = estimate_normals(original)
    rng = np.random.default_rng(4)
    delta = rng.choice([-1.0, 1.0], size=(basis.shape[1], 3)) * 0.004
    moved, _ = along_normals(basis @ delta, normals)
    fresh = sphere_patch(12000, rng=7)
    _, owner = cKDTree(original).query(fresh)
    at = rng.integers(0, len(original), junk)
    offset = rng.choice([-1.0, 1.0], junk) * rng.uniform(1, 3, junk) * np.median(nearest_spacing(original))
    extra = original[at] + offset[:, None] * normals[at]
    suspect = np.vstack([fresh + moved[owner], extra])[rng.permutation(len(fresh) + junk)]
    return original, normals, basis, delta, suspect, np.vstack([fresh, extra])


def _normal_fit_score(trim, junk, normal_only=True):
    """Correlation of the fitted mark with the embedded one."""
    original, normals, basis, delta, suspect, unmarked = _normal_mark_and_samples(junk)
    fit = [fit_spectral_displacement(original, normals, cloud, [np.arange(len(original))], [basis], **FIT,
                                     normal_only=normal_only, trim=trim, reach=spread_reach(basis, 0.004))[0][0]
           for cloud in (suspect, unmarked)]
    return np.corrcoef((fit[0] - fit[1]).ravel(), delta.ravel())[0, 1]


def test_trimming_leaves_junk_near_the_surface_out_of_the_fit():
    kept = _normal_fit_score(None, junk=6000)
    trimmed = _normal_fit_score(10.0, junk=6000)
    assert trimmed > 0.95 and trimmed > kept + 0.2


def test_trimming_leaves_a_clean_sample_nearly_as_it_was():
    kept = _normal_fit_score(None, junk=0)
    trimmed = _normal_fit_score(10.0, junk=0)
    assert trimmed > 0.95 and abs(trimmed - kept) < 0.01


def test_trimming_keeps_the_mark_beside_an_unmarked_original():
    # Half the matches have no misfit at all: their median square is 0, and
    # without the mark's reach every marked match would be trimmed.
    original, normals, basis, delta, _, _ = _normal_mark_and_samples(0)
    from pipeline.kernels.modulation import along_normals

    moved, _ = along_normals(basis @ delta, normals)
    suspect = np.vstack([original + moved, original])
    members = [np.arange(len(original))]
    fit = {trim: fit_spectral_displacement(original, normals, suspect, members, [basis], **FIT,
                                           normal_only=True, trim=trim, reach=reach)[0][0]
           for trim, reach in [(None, None), (10.0, spread_reach(basis, 0.004))]}
    for estimate in fit.values():
        assert np.corrcoef(estimate.ravel(), delta.ravel())[0, 1] > 0.5
    assert np.allclose(fit[None], fit[10.0])
    with pytest.raises(ValueError, match="at least 1"):
        fit_spectral_displacement(original, normals, suspect, members, [basis], **FIT, trim=0.5)


def _random_cluster(rng, n, start, k):
    """Random points and unit normals, a cluster of 400 of them from ``start``, an orthonormal (400, k) basis."""
    original = rng.normal(size=(n, 3))
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return original, normals, np.arange(start, start + 400), np.linalg.qr(rng.normal(size=(400, k)))[0]


@pytest.mark.parametrize("few", [False, True])
@pytest.mark.parametrize("trim", [None, 3.0])
def test_the_normal_model_gram_shortcut_equals_the_full_normal_equations(trim, few):
    """Points matched 0, 1 or 3 times, some trimmed: G^T G plus the update at those points is the full sum."""
    from pipeline.kernels import resampling

    rng = np.random.default_rng(5)
    original, normals, members, basis = _random_cluster(rng, 600, 100, 24)
    targets = np.concatenate([members[:300], np.repeat(members[300:320], 3)])     # 80 never matched
    if few:                              # a piece lying on a tenth of the cluster: the sum taken directly
        targets = np.concatenate([members[:30], np.repeat(members[30:40], 2)])
    points = original[targets] + 0.01 * rng.normal(size=(len(targets), 3))
    points[::25] += 0.2 * normals[targets[::25]]                                   # trimmed at 3
    none = np.zeros(len(targets), dtype=bool)
    trim = None if trim is None else (trim, 0.0)
    full = resampling._solve_cluster(original, normals, original, points, targets, none, members, basis, 1.0,
                                     trim=trim)
    gram = resampling.normal_gram(basis, normals[members])
    fast = resampling._solve_cluster(original, normals, original, points, targets, none, members, basis, 1.0,
                                     gram=gram, trim=trim)
    assert np.allclose(fast, full, rtol=1e-10, atol=1e-14) and np.abs(full).max() > 1e-3
    if trim is not None:
        kept = resampling._solve_cluster(original, normals, original, points, targets, none, members, basis,
                                         1.0)
        assert not np.allclose(kept, full, rtol=1e-3)


@pytest.mark.parametrize("share", [0.1, 1.0])
def test_the_cluster_solve_equals_dense_weighted_least_squares(share):
    """The xyz model's equations, summed over the matched cluster points only, solve the full weighted problem."""
    from pipeline.kernels import resampling

    rng = np.random.default_rng(7)
    original, normals, members, basis = _random_cluster(rng, 500, 50, 16)
    n_matched = int(share * len(members))
    targets = np.concatenate([members[:n_matched], members[: n_matched // 4]])      # some matched twice
    points = original[targets] + 0.01 * rng.normal(size=(len(targets), 3))
    reliable = rng.random(len(targets)) < 0.5
    got = resampling._solve_cluster(original, normals, original, points, targets, reliable, members, basis, 0.1)
    # the same weights, and every cluster point's rows of the design matrix, built densely
    n, r = normals[targets], points - original[targets]
    normal_part = np.einsum("ki,ki->k", r, n)
    var_n = np.median(normal_part ** 2)
    tangential = r - normal_part[:, None] * n
    var_t = max(np.median((tangential[reliable] ** 2).sum(axis=1)) / 2.0, var_n)
    k = basis.shape[1]
    lhs, rhs = np.zeros((3 * k, 3 * k)), np.zeros(3 * k)
    local = {m: i for i, m in enumerate(members)}
    for t, point_r, normal, rel in zip(targets, r, n, reliable):
        w = np.outer(normal, normal) / var_n + rel * (np.eye(3) - np.outer(normal, normal)) / var_t
        g = np.kron(np.eye(3), basis[local[t]][None, :])                      # (3, 3K): X -> displacement
        lhs += g.T @ w @ g
        rhs += g.T @ w @ point_r
    lhs[np.diag_indices_from(lhs)] += 0.1 * np.trace(lhs) / (3 * k)
    want = np.linalg.solve(lhs, rhs).reshape(3, k).T
    assert np.allclose(got, want, rtol=1e-9, atol=1e-12) and np.abs(want).max() > 1e-3
