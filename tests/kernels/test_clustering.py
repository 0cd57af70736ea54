import numpy as np
import pytest

from pipeline.kernels.clustering import farthest_point_seeds, grid_cells, grow_clusters, nearest_indices
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
    labels = grow_clusters(pts, seeds, 500, on_touch="skip", cover=False)
    counts = np.bincount(labels[labels >= 0])
    assert counts.tolist() == [500] * 4
    assert (labels[seeds] == np.arange(4)).all()


def test_stop_on_touch_gives_no_larger_clusters_than_skip():
    pts = sphere_patch(3000)
    seeds = farthest_point_seeds(pts, 6)
    stop = np.bincount(grow_clusters(pts, seeds, 450, on_touch="stop", cover=False) + 1)[1:]
    skip = np.bincount(grow_clusters(pts, seeds, 450, on_touch="skip", cover=False) + 1)[1:]
    assert skip.tolist() == [450] * 6
    assert (stop <= 450).all() and stop.sum() < skip.sum()


def test_cover_assigns_every_point():
    pts = sphere_patch(1500)
    labels = grow_clusters(pts, farthest_point_seeds(pts, 3), 400, on_touch="stop", cover=True)
    assert (labels >= 0).all()


def test_clusters_grow_compactly_from_their_seed():
    pts = sphere_patch(3000)
    seed = np.array([0])
    members = np.flatnonzero(grow_clusters(pts, seed, 300, on_touch="stop", cover=False) == 0)
    dist = np.linalg.norm(pts - pts[0], axis=1)
    # the 300 members are nearly the 300 closest points to the seed
    assert len(np.intersect1d(members, np.argsort(dist)[:360])) >= 280


def test_seed_coordinates_map_to_nearest_points():
    pts = sphere_patch(500)
    assert nearest_indices(pts, pts[[7, 42]] + 1e-6).tolist() == [7, 42]


def test_duplicate_seeds_are_rejected():
    with pytest.raises(ValueError, match="distinct"):
        grow_clusters(sphere_patch(100), [3, 3], 10, on_touch="stop", cover=False)


def test_grid_cells_partition_a_tile_into_squares_of_about_the_asked_size():
    rng = np.random.default_rng(3)
    pts = np.column_stack([rng.uniform(0, 400, 50_000), rng.uniform(0, 100, 50_000), rng.normal(0, 1, 50_000)])
    cells = grid_cells(pts, 2000)
    assert np.array_equal(np.sort(np.concatenate(cells)), np.arange(len(pts)))
    assert all(np.all(np.diff(c) > 0) for c in cells)              # ascending within a cell
    assert 20 <= len(cells) <= 30                                  # 50,000 / 2,000 = 25
    side = np.sqrt(400 * 100 * 2000 / 50_000)
    for c in cells:                                                # squares over x and y, no slivers
        extent = np.ptp(pts[c][:, :2], axis=0)
        assert (extent <= 1.5 * side).all() and (extent >= 0.5 * side).all()
    assert max(len(c) for c in cells) < 2 * 2000
    assert [c.tolist() for c in grid_cells(pts, 2000)] == [c.tolist() for c in cells]


def test_dense_parts_of_a_scene_are_split_until_no_cell_exceeds_twice_the_size():
    rng = np.random.default_rng(4)
    sparse = np.column_stack([rng.uniform(0, 100, 10_000), rng.uniform(0, 100, 10_000), np.zeros(10_000)])
    dense = np.column_stack([rng.normal(50, 1, 40_000), rng.normal(50, 1, 40_000), rng.normal(0, 1, 40_000)])
    pts = np.vstack([sparse, dense])                               # a scanner's surroundings: dense near it
    cells = grid_cells(pts, 2000)
    assert np.array_equal(np.sort(np.concatenate(cells)), np.arange(len(pts)))
    assert max(len(c) for c in cells) <= 4000
    assert all(np.all(np.diff(c) > 0) for c in cells)


def test_a_set_no_larger_than_a_cell_is_one_cell():
    pts = sphere_patch(500)
    (only,) = grid_cells(pts, 500)
    assert np.array_equal(only, np.arange(500))
