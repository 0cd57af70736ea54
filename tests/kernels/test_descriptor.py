"""D2 shape distributions: whole, cut (what a crop leaves), and their distance."""

import numpy as np

from pipeline.kernels import attacks
from pipeline.kernels.descriptor import (CUT_DIRECTIONS, CUT_FRACTIONS, D2_BINS, cumulative_distance,
                                         cut_descriptors, d2_descriptor, descriptor_distance, sphere_directions)
from tests.conftest import sphere_patch


def test_sphere_directions_are_unit_and_spread():
    d = sphere_directions(48)
    assert d.shape == (48, 3) and np.allclose(np.linalg.norm(d, axis=1), 1.0)
    cos = d @ d.T - 2.0 * np.eye(48)
    # every direction has a neighbour within 35 degrees and none closer than 15
    assert np.degrees(np.arccos(cos.max(axis=1))).max() < 35
    assert np.degrees(np.arccos(cos.max())) > 15


def test_d2_is_invariant_to_similarity_and_order():
    pts = sphere_patch(3000, 1)
    rng = np.random.default_rng(2)
    moved = attacks.similarity(pts, attacks.random_rotation(rng), 3.7, [1.0, -2.0, 5.0])[rng.permutation(3000)]
    a, b = d2_descriptor(pts - pts.mean(axis=0)), d2_descriptor(moved - moved.mean(axis=0))
    assert a.shape == (D2_BINS,) and abs(a.sum() - 1.0) < 1e-12
    assert descriptor_distance(a, b) < 0.05


def test_a_crop_is_nearer_its_cut_views_than_the_whole():
    rng = np.random.default_rng(3)
    pts = np.concatenate([sphere_patch(3000, 4), sphere_patch(1500, 5) * 0.4 + [0.0, 0.0, 1.5]])
    cuts = cut_descriptors(pts)
    assert cuts.shape == (CUT_DIRECTIONS * len(CUT_FRACTIONS), D2_BINS)
    piece = attacks.crop(pts, 0.3, rng)
    piece = attacks.similarity(piece, attacks.random_rotation(rng), 0.5, [3.0, 0.0, 0.0])
    d = d2_descriptor(piece - piece.mean(axis=0))
    whole = descriptor_distance(d, d2_descriptor(pts - pts.mean(axis=0)))
    nearest_cut = descriptor_distance(d, cuts).min()
    assert nearest_cut < 0.5 * whole, (nearest_cut, whole)


def test_distances_to_cumulative_rows_computed_once_equal_the_distances_to_the_rows():
    gen = np.random.default_rng(7)
    rows = gen.random((200_000, 32))
    rows /= rows.sum(axis=1, keepdims=True)
    a = rows[123] + gen.normal(0.0, 1e-3, 32)
    cumulative = np.cumsum(rows, axis=-1)
    d = cumulative_distance(a, cumulative, chunk=4096)      # chunks, one of them partial, give the same rows
    assert d.shape == (len(rows),)
    assert np.array_equal(d, cumulative_distance(a, cumulative)) and np.array_equal(d, descriptor_distance(a, rows))
    assert int(np.argmin(d)) == 123 and d[123] < 0.1 < np.median(d)
    views = np.stack([a, rows[5], rows[77] * 0.5 + rows[78] * 0.5])     # several histograms: one pass, the same rows
    many = cumulative_distance(views, cumulative, chunk=4096)
    assert many.shape == (3, len(rows))
    assert all(np.array_equal(many[i], descriptor_distance(v, rows)) for i, v in enumerate(views))


def _d2_by_rows(points, pairs, seed=0):
    """D2 as first written: pair distances by ``np.linalg.norm`` of whole rows."""
    rng = np.random.default_rng(seed)
    i, j = rng.integers(0, len(points), pairs), rng.integers(0, len(points), pairs)
    d = np.linalg.norm(points[i] - points[j], axis=1)
    d = d[d > 0]
    hist, _ = np.histogram(d / np.median(d), bins=D2_BINS, range=(0.0, 3.0))
    return hist / max(hist.sum(), 1)


def test_d2_by_columns_is_bitwise_the_d2_of_row_norms():
    gen = np.random.default_rng(11)
    for k in range(40):
        n = int(gen.integers(2, 6000))
        pts = gen.normal(size=(n, 3)) * gen.uniform(1e-3, 1e3) + gen.normal(size=3) * gen.uniform(0.0, 100.0)
        if k % 4 == 0:
            pts = np.round(pts, 1)               # coincident points: zero distances dropped
        for p in (pts, pts.astype(np.float32)):
            assert np.array_equal(d2_descriptor(p, pairs=20_000), _d2_by_rows(p, 20_000)), (k, p.dtype)


def test_cut_views_are_the_d2_of_each_plane_cut():
    pts = sphere_patch(2000, 6)
    height = pts @ sphere_directions(CUT_DIRECTIONS)[5]
    cuts = cut_descriptors(pts, pairs=10_000).reshape(CUT_DIRECTIONS, len(CUT_FRACTIONS), D2_BINS)
    for f, view in zip(CUT_FRACTIONS, cuts[5]):
        piece = pts[height >= np.quantile(height, 1.0 - f)]
        assert np.array_equal(view, _d2_by_rows(piece - piece.mean(axis=0), 10_000))
