"""Pure-NumPy pieces of the part-to-whole registration (issue 13): batched Umeyama, RANSAC with scale, ICP."""

import numpy as np
from scipy.spatial import cKDTree

from pipeline.kernels import attacks
from pipeline.kernels.registration import (apply, overlap, ransac_similarity, refine_part, umeyama,
                                           umeyama_batch)
from tests.conftest import sphere_patch


def test_batched_umeyama_equals_the_single_one():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(50, 4, 3))
    dst = rng.normal(size=(50, 4, 3))
    rot, scale, trans = umeyama_batch(src, dst)
    for h in (0, 17, 49):
        one = umeyama(src[h], dst[h])
        assert np.allclose(rot[h], one.rotation) and np.isclose(scale[h], one.scale)
        assert np.allclose(trans[h], one.translation)
    assert np.allclose(np.linalg.det(rot), 1.0)


def test_ransac_recovers_scale_and_pose_from_mostly_wrong_correspondences():
    rng = np.random.default_rng(1)
    pts = sphere_patch(2000, rng=2)
    rot = attacks.random_rotation(rng)
    moved = attacks.similarity(pts, rot, 0.37, [3.0, -1.0, 2.0])
    n = len(pts)
    target = pts.copy()
    wrong = rng.random(n) < 0.8                          # 80 % of the pairs are wrong
    target[wrong] = pts[rng.integers(0, n, wrong.sum())]
    found, inliers = ransac_similarity(moved, target, threshold=0.01, iterations=5000, rng=3)
    assert abs(found.scale - 1 / 0.37) < 1e-6 * (1 / 0.37)
    assert np.abs(apply(found, moved) - pts).max() < 1e-6
    assert inliers.sum() >= (~wrong).sum() and inliers.mean() < 0.3


def test_ransac_with_no_consistent_sample_says_so():
    rng = np.random.default_rng(4)
    found, inliers = ransac_similarity(rng.normal(size=(30, 3)), rng.normal(size=(30, 3)), threshold=1e-9,
                                       iterations=50, edge_tolerance=1e-9, rng=5)
    assert found is None and not inliers.any()


def test_refine_part_aligns_a_crop_and_ignores_clutter():
    pts = sphere_patch(6000, rng=6)
    part = attacks.crop(pts, 0.3, rng=7)
    scene = np.concatenate([part, np.random.default_rng(8).uniform(3.0, 5.0, (3 * len(part), 3))])
    rot = attacks.rotation_matrix("z", 4.0)
    start_moved = attacks.similarity(scene, rot, 1.02, [0.01, 0.0, 0.0])
    start = umeyama(start_moved[:3], scene[:3])         # exact inverse as a reference
    # start from the identity: a few degrees and 2 % off
    tree = cKDTree(pts)
    fine = refine_part(start_moved, tree, pts, umeyama(start_moved, start_moved), spacing=0.02)
    assert abs(fine.scale - start.scale) < 0.01
    assert np.abs(apply(fine, start_moved[: len(part)]) - part).max() < 0.01
    fitness, coverage, residual = overlap(apply(fine, start_moved), tree, pts[::5], 0.06)
    assert 0.2 < fitness < 0.3            # the clutter is three quarters of the scene
    assert 0.25 < coverage < 0.4          # and the part a third of the original
    assert residual < 0.01
