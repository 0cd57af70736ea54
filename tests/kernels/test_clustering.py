import numpy as np
import pytest

from pipeline.kernels.clustering import farthest_point_seeds, grow_clusters, nearest_indices
from tests.conftest import sphere_patch


def test_farthest_point_seeds_are_deterministic_and_spread():
    pts = sphere_patch(2000)
    a = farthest_point_seeds(pts, 5)
    assert np.array_equal(a, farthest_point_seeds(pts, 5))
    assert len(set(a.tolist())) == 5
    d = np.linalg.norm(pts[a][:, None] - pts[a][None], axis=2)
    assert d[np.triu_indices(5, 1)].min() > 0.5


def test_clusters_are_disjoint_and_respect_size_limit():
    pts = sphere_patch(3000)
    seeds = farthest_point_seeds(pts, 4)
    labels = grow_clusters(pts, seeds, 500, on_touch="skip")
    counts = np.bincount(labels[labels >= 0])
    assert counts.tolist() == [500] * 4
    assert (labels[seeds] == np.arange(4)).all()


def test_stop_on_touch_gives_no_larger_clusters_than_skip():
    pts = sphere_patch(3000)
    seeds = farthest_point_seeds(pts, 6)
    stop = np.bincount(grow_clusters(pts, seeds, 450, on_touch="stop") + 1)[1:]
    skip = np.bincount(grow_clusters(pts, seeds, 450, on_touch="skip") + 1)[1:]
    assert skip.tolist() == [450] * 6
    assert (stop <= 450).all() and stop.sum() < skip.sum()


def test_cover_assigns_every_point():
    pts = sphere_patch(1500)
    labels = grow_clusters(pts, farthest_point_seeds(pts, 3), 400, cover=True)
    assert (labels >= 0).all()


def test_clusters_grow_compactly_from_their_seed():
    pts = sphere_patch(3000)
    seed = np.array([0])
    members = np.flatnonzero(grow_clusters(pts, seed, 300) == 0)
    dist = np.linalg.norm(pts - pts[0], axis=1)
    # the 300 members are nearly the 300 closest points to the seed
    assert len(np.intersect1d(members, np.argsort(dist)[:360])) >= 280


def test_seed_coordinates_map_to_nearest_points():
    pts = sphere_patch(500)
    assert nearest_indices(pts, pts[[7, 42]] + 1e-6).tolist() == [7, 42]


def test_duplicate_seeds_are_rejected():
    with pytest.raises(ValueError, match="distinct"):
        grow_clusters(sphere_patch(100), [3, 3], 10)
