"""Parts of a near solid of revolution registered by their axis and profile."""

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pipeline.kernels import registration, resampling, revolution
from pipeline.nearest import NearestTree


def _vase(n=20000, seed=0):
    """A vase-like surface about the z axis, with a faint ripple about it (a scan is never exactly symmetric)."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(-1.0, 1.0, n)
    theta = rng.uniform(0.0, 2.0 * np.pi, n)
    r = (0.5 + 0.2 * np.sin(2.5 * z) + 0.1 * z * z) * (1.0 + 0.01 * np.cos(3.0 * theta) + 0.006 * np.sin(7.0 * theta))
    return np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=1)


def _turned(points, rng):
    rotation = Rotation.random(random_state=rng).as_matrix()
    return registration.Similarity(rotation, 2.5, np.array([3.0, -1.0, 0.5]))


def test_the_axis_of_a_whole_vase_is_found():
    shape = _vase()
    truth = _turned(shape, 1)
    moved = registration.apply(truth, shape)
    anchor, direction, _ = revolution.revolution_axis(moved, resampling.estimate_normals(moved))
    expected = truth.rotation @ np.array([0.0, 0.0, 1.0])
    assert np.degrees(np.arccos(min(1.0, abs(direction @ expected)))) < 0.5
    # the anchor lies on the moved axis (through the moved origin)
    rel = anchor - truth.translation
    assert np.linalg.norm(rel - (rel @ expected) * expected) < 0.01 * truth.scale


def test_a_turned_rescaled_crop_of_a_vase_is_laid_back_where_it_was_cut():
    # 30 % crops: of this open tube a 10 % band or side slice can fit another axis as well (the
    # real black vase's 10 % crops are tests/test_features.py's); the trees the detector gives it
    shape = _vase(8000)
    spacing = float(np.median(resampling.nearest_spacing(shape)))
    tree = NearestTree(shape)
    axis = revolution.revolution_axis(shape, resampling.estimate_normals(shape))
    for seed in range(2):
        rng = np.random.default_rng(seed)
        normal = rng.normal(size=3)
        normal /= np.linalg.norm(normal)
        kept = shape[shape @ normal >= np.quantile(shape @ normal, 0.7)]     # a 30 % crop by a plane
        truth = _turned(kept, seed)
        part = registration.apply(truth, kept)
        hint = 1.0 / truth.scale * float(np.exp(rng.uniform(-0.2, 0.2)))      # the spacing ratio, roughly
        starts = revolution.revolution_poses(part, resampling.estimate_normals(part), shape, axis, tree, spacing, hint,
                                             axes=1 + seed, nearest=NearestTree)     # one axis, then two
        assert starts
        fits = [registration.refine_part(part, tree, shape, pose, spacing=spacing, iterations=30)
                for _, pose in starts[:8]]
        best = min(fits, key=lambda p: float(np.median(tree.query(registration.apply(p, part))[0])))
        error = np.linalg.norm(registration.apply(best, part) - kept, axis=1).mean() / spacing
        assert error < 0.1, (seed, error)


def test_profile_is_height_and_radius():
    points = np.array([[1.0, 0.0, 2.0], [0.0, -3.0, -1.0]])
    np.testing.assert_allclose(revolution.profile(points, np.zeros(3), np.array([0.0, 0.0, 1.0])),
                               [[2.0, 1.0], [-1.0, 3.0]])


def test_thickness_is_least_about_the_true_axis():
    shape = _vase(6000)
    true = revolution.thickness(shape, np.zeros(3), np.array([0.0, 0.0, 1.0]))
    tilted = np.array([np.sin(0.2), 0.0, np.cos(0.2)])
    assert true < 0.5 * revolution.thickness(shape, np.zeros(3), tilted)


def test_a_part_of_another_shape_is_not_turned_and_a_part_of_the_original_is():
    # the same vase squeezed to an elliptic section: no profile about any axis lies on the vase's,
    # so it is not turned (revolution.PROFILE_CUT); the vase's own crop, cut alike, is
    shape = _vase(8000)
    spacing = float(np.median(resampling.nearest_spacing(shape)))
    tree = NearestTree(shape)
    axis = revolution.revolution_axis(shape, resampling.estimate_normals(shape))
    squeezed = shape * np.array([1.35, 0.75, 1.0])
    normal = np.array([0.6, 0.0, 0.8])
    found = {}
    for name, cloud in (("own", shape), ("other", squeezed)):
        part = cloud[cloud @ normal >= np.quantile(cloud @ normal, 0.7)]
        found[name] = revolution.revolution_poses(part, resampling.estimate_normals(part), shape, axis, tree,
                                                  spacing, 1.0, nearest=NearestTree)
    assert found["own"] and found["own"][0][0] < spacing
    assert found["other"] == []
