"""The registration's nearest-neighbour tree answers as SciPy's cKDTree does."""

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from pipeline.kernels import registration, resampling, revolution
from pipeline.nearest import NearestTree


@pytest.fixture(scope="module")
def cloud():
    rng = np.random.default_rng(7)
    points = rng.normal(size=(3000, 3))
    queries = np.concatenate([points[:500] + rng.normal(scale=0.01, size=(500, 3)),   # on the cloud
                              rng.normal(scale=6.0, size=(1500, 3))])                 # far from it
    return points, queries


@pytest.mark.parametrize("bound", [np.inf, 0.05, 1.0])
def test_the_nearest_point_and_its_distance_are_cKDTrees(cloud, bound):
    points, queries = cloud
    dist, idx = NearestTree(points).query(queries, distance_upper_bound=bound)
    want_dist, want_idx = cKDTree(points).query(queries, distance_upper_bound=bound)
    assert dist.dtype == np.float64 and idx.dtype == np.int64
    np.testing.assert_array_equal(dist, want_dist)
    np.testing.assert_array_equal(idx, want_idx)
    if np.isfinite(bound):                      # a missing neighbour: inf and one past the last index
        assert np.isinf(dist).any() and (idx[np.isinf(dist)] == len(points)).all()


def test_k_nearest_points_and_odd_inputs(cloud):
    points, queries = cloud
    tree = NearestTree(points.astype(np.float32))                   # stored as float64 all the same
    dist, idx = tree.query(queries.T.copy().T, k=4)                 # a non-contiguous query
    want_dist, want_idx = cKDTree(points.astype(np.float32).astype(np.float64)).query(queries, k=4)
    assert dist.shape == idx.shape == (len(queries), 4)
    np.testing.assert_array_equal(dist, want_dist)
    np.testing.assert_array_equal(idx, want_idx)
    dist, idx = tree.query(np.empty((0, 3)))
    assert dist.shape == idx.shape == (0,)


def test_a_neighbour_it_has_none_for_is_missing_as_in_cKDTree():
    rng = np.random.default_rng(2)
    points, queries = rng.normal(size=(3, 3)), rng.normal(size=(5, 3))
    dist, idx = NearestTree(points).query(queries, k=5)             # more neighbours than points
    want_dist, want_idx = cKDTree(points).query(queries, k=5)
    np.testing.assert_array_equal(idx, want_idx)
    np.testing.assert_array_equal(dist, want_dist)
    assert (idx[:, 3:] == 3).all() and np.isinf(dist[:, 3:]).all()
    queries[1] = np.nan                                             # cKDTree refuses it; no neighbour here
    dist, idx = NearestTree(points).query(queries)
    assert idx[1] == 3 and np.isinf(dist[1]) and (idx[[0, 2, 3, 4]] == want_idx[[0, 2, 3, 4], 0]).all()


def test_registration_finds_the_same_poses_through_either_tree():
    # a turned crop of a vase: the robust steps, ICP and the axis-and-profile search (2-D trees too)
    rng = np.random.default_rng(3)
    z, theta = rng.uniform(-1.0, 1.0, 3000), rng.uniform(0.0, 2.0 * np.pi, 3000)
    r = (0.5 + 0.2 * np.sin(2.5 * z)) * (1.0 + 0.01 * np.cos(3.0 * theta))
    shape = np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=1)
    kept = shape[shape[:, 0] + 0.3 * shape[:, 2] > 0.2]
    turn = registration.Similarity(Rotation.random(random_state=1).as_matrix(), 2.0, np.array([1.0, -2.0, 0.5]))
    part = registration.apply(turn, kept)
    spacing = float(np.median(resampling.nearest_spacing(shape)))
    axis = revolution.revolution_axis(shape, resampling.estimate_normals(shape))
    answers = []
    for make in (cKDTree, NearestTree):
        tree = make(shape)
        robust = registration.register_robust(part, shape, spacing=spacing, tree=tree)
        refined = registration.refine_part(part, tree, shape, robust, spacing=spacing)
        starts = revolution.revolution_poses(part, resampling.estimate_normals(part), shape, axis, tree, spacing, 0.5,
                                             axes=1, matches=2, nearest=make)
        answers.append([robust, refined, *(pose for _, pose in starts)])
        answers[-1].append([cost for cost, _ in starts])
    assert len(answers[0]) == len(answers[1]) > 3
    for a, b in zip(answers[0][:-1], answers[1][:-1]):
        np.testing.assert_array_equal(a.rotation, b.rotation)
        assert (a.scale, *a.translation, a.fitness, a.residual) == (b.scale, *b.translation, b.fitness, b.residual)
    assert answers[0][-1] == answers[1][-1]
