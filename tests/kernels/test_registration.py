import numpy as np

from pipeline.kernels import attacks, registration
from pipeline.kernels.registration import (apply, connected_parts, register_covariance, register_robust,
                                          separate_objects, shape_signature, umeyama)
from tests.conftest import sphere_patch


def test_umeyama_recovers_a_similarity():
    pts = sphere_patch(500)
    rot = attacks.rotation_matrix("z", 40) @ attacks.rotation_matrix("x", -25)
    moved = attacks.similarity(pts, rot, 2.5, [1.0, -2.0, 3.0])
    t = umeyama(moved, pts)
    assert np.allclose(apply(t, moved), pts, atol=1e-9)
    assert abs(t.scale - 0.4) < 1e-9


def test_covariance_registration_undoes_the_papers_transform():
    pts = sphere_patch(3000)
    moved = attacks.paper_similarity(pts)
    t = register_covariance(moved, pts, spacing=0.03)
    assert np.abs(apply(t, moved) - pts).max() < 1e-6


def test_robust_registration_survives_similarity_with_removal_and_noise():
    pts = sphere_patch(6000)
    rng = np.random.default_rng(5)
    keep = np.sort(rng.choice(len(pts), 720, replace=False))
    rot = attacks.rotation_matrix("y", 140) @ attacks.rotation_matrix("z", 70)
    noisy = attacks.noise_uniform(pts[keep], 0.002, rng)
    moved = attacks.similarity(noisy, rot, 3.7, [5.0, 1.0, -2.0])
    order = rng.permutation(len(keep))
    t = register_robust(moved[order], pts, spacing=0.02)
    err = np.linalg.norm(apply(t, moved[order]) - noisy[order], axis=1)
    assert abs(t.scale - 1 / 3.7) < 0.01 * (1 / 3.7)
    assert np.median(err) < 0.005
    assert t.fitness > 0.95


def test_robust_registration_rejects_a_collapsed_scale_far_from_the_original():
    # A distant, shrunken copy: free-scale ICP from the identity can collapse
    # the suspect onto one patch of the original; that fit must not win.
    pts = sphere_patch(6000)
    rng = np.random.default_rng(11)
    keep = np.sort(rng.choice(len(pts), 1500, replace=False))
    rot = attacks.rotation_matrix("x", -60) @ attacks.rotation_matrix("z", 200)
    moved = attacks.similarity(pts[keep], rot, 0.2, [150.0, -80.0, 60.0])
    t = register_robust(moved[rng.permutation(len(keep))], pts, spacing=0.02)
    assert abs(t.scale - 5.0) < 0.05 * 5.0
    assert t.fitness > 0.95


def test_connected_parts_splits_separate_objects_largest_first():
    rng = np.random.default_rng(4)
    blob = rng.uniform(-1, 1, size=(900, 3)) * [3.0, 1.0, 0.5]
    small = rng.uniform(-1, 1, size=(300, 3)) * 0.5 + [40.0, 0.0, 0.0]
    junk = rng.uniform(-100, 100, size=(5, 3)) + [0.0, 300.0, 0.0]
    points = np.vstack([small, junk, blob])
    parts = connected_parts(points, 2.0, min_points=50)
    assert [len(p) for p in parts] == [900, 300]
    assert set(parts[0]) == set(range(305, 1205)) and set(parts[1]) == set(range(300))
    # the order does not depend on the order of the points
    perm = rng.permutation(len(points))
    again = connected_parts(points[perm], 2.0, min_points=50)
    assert [sorted(perm[p]) for p in again] == [sorted(p) for p in parts]


def test_shape_signature_ignores_similarity_and_tells_shapes_apart():
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(2000, 3)) * [4.0, 2.0, 1.0]
    moved = attacks.similarity(pts, attacks.random_rotation(rng), 0.3, [5.0, -2.0, 9.0])
    assert np.allclose(shape_signature(moved), shape_signature(pts), atol=1e-9)
    assert np.allclose(shape_signature(pts), [1.0, 0.5, 0.25], atol=0.05)
    assert np.abs(shape_signature(rng.normal(size=(2000, 3))) - shape_signature(pts)).max() > 0.3


def test_connected_parts_of_duplicates_and_of_a_zero_radius():
    point = np.zeros((5000, 3))
    assert [len(p) for p in connected_parts(point, 0.0, min_points=10)] == [5000]
    grid = np.repeat(np.stack(np.meshgrid(*[np.arange(10.0)] * 3), -1).reshape(-1, 3), 20, axis=0)
    far = grid + [100.0, 0.0, 0.0]
    parts = connected_parts(np.vstack([grid, far]), 1.5)
    assert [len(p) for p in parts] == [20000, 20000]


def test_separate_objects_are_the_parts_of_a_scene_and_none_of_one_object():
    rng = np.random.default_rng(6)
    grid = np.stack(np.meshgrid(*[np.arange(12.0)] * 3), -1).reshape(-1, 3)    # spacing 1
    scene = np.vstack([grid, grid[:800] + [30.0, 0.0, 0.0]])
    objects = separate_objects(scene, 1.0, min_points=100)
    assert [len(p) for p in objects] == [len(grid), 800]
    # one object (a gap of 2 spacings is inside the object gap); at a finer spacing the gap
    # splits it, but the rest is the whole suspect and the crumb is too small to count
    near = np.vstack([grid, grid[:40] + [13.0, 0.0, 0.0]])
    assert separate_objects(near, 1.0) == []
    assert separate_objects(near[rng.permutation(len(near))], 0.25, min_points=100) == []
    assert [len(p) for p in separate_objects(near, 0.25)] == [40]


def test_rotation_search_finds_a_crop_of_a_smooth_shape_at_a_known_scale():
    from scipy.spatial import cKDTree

    from pipeline.demo import procedural_shape
    from pipeline.kernels.registration import refine_part, rotation_search
    from pipeline.kernels.resampling import nearest_spacing

    blob = procedural_shape("blob", 4000, seed=1) * 20     # smooth: no feature tells its parts apart
    spacing = float(np.median(nearest_spacing(blob)))
    rng = np.random.default_rng(3)
    part = attacks.crop(blob, 0.3, rng)
    suspect = attacks.similarity(part, attacks.random_rotation(rng), 4.0, [5.0, -2.0, 1.0])
    found = rotation_search(suspect, blob, 0.25, top=48)
    assert len(found) == 48 and [s for s, _ in found] == sorted((s for s, _ in found), reverse=True)
    assert all(0.0 < s <= 1.0 for s, _ in found)
    assert all(t.scale == 0.25 for _, t in found)
    # the same poses on every call (the rotations are fixed)
    again = rotation_search(suspect, blob, 0.25, top=48)
    assert all(np.array_equal(a.rotation, b.rotation) and np.array_equal(a.translation, b.translation)
               for (_, a), (_, b) in zip(found, again))
    tree = cKDTree(blob)
    errors = [float(np.median(np.linalg.norm(apply(refine_part(suspect, tree, blob, start, spacing=spacing,
                                                               iterations=60), suspect) - part, axis=1)))
              for _, start in found]
    assert min(errors) < 0.01 * spacing
    assert np.median(errors) > 2.0 * spacing      # most poses are wrong: the search, not ICP, found it


def _bumpy_torus(n, rng):
    u, v = rng.uniform(0, 2 * np.pi, (2, n))
    r = 0.3 * (1.0 + 0.05 * np.sin(3 * u) * np.cos(2 * v))      # low bumps: nearly symmetric about z
    return np.column_stack([(1 + r * np.cos(v)) * np.cos(u), (1 + r * np.cos(v)) * np.sin(u), r * np.sin(v)])


def test_plane_icp_finishes_a_crop_of_a_nearly_symmetric_shape_that_point_icp_leaves_off():
    from scipy.spatial import cKDTree

    from pipeline.kernels.registration import Similarity, refine_part, refine_plane
    from pipeline.kernels.resampling import estimate_normals, nearest_spacing

    rng = np.random.default_rng(3)
    original = _bumpy_torus(8000, rng)
    part = attacks.crop(original, 0.3, rng)
    spacing = float(np.median(nearest_spacing(original)))
    tree, normals = cKDTree(original), estimate_normals(original)
    # a scaled copy with noise of 0.3 % of the size; the start is 4 degrees about the axis and 1 % too large
    suspect = attacks.noise_uniform(part, 0.003, rng) / 2.5
    start = Similarity(attacks.rotation_matrix("z", 4.0), 2.5 * 1.01, np.zeros(3))

    def err(t):      # how far the transform lays the noise-free part from its place
        return np.median(np.linalg.norm(apply(t, part / 2.5) - part, axis=1)) / spacing

    assert err(start) > 3.0
    # the fixture needs it: point-to-point ICP from the same start stops more than a spacing off
    assert err(refine_part(suspect, tree, original, start, spacing=spacing, widths=(3.0,), iterations=100)) > 1.0
    fine = refine_plane(suspect, tree, original, normals, start, spacing=spacing)
    assert err(fine) < 0.1 and abs(fine.scale / 2.5 - 1) < 2e-3 and fine.fitness > 0.99


def test_plane_icp_gives_the_same_pose_in_metres_and_millimetres():
    # a spherical cap turned 2 degrees about the sphere's centre, started half a spacing off
    # sideways: the turn moves points almost along their planes, the weakest direction of
    # the step; the unknowns are solved as lengths, so the model's unit cannot change the pose
    from scipy.spatial import cKDTree

    from pipeline.kernels.registration import Similarity, refine_plane
    from pipeline.kernels.resampling import nearest_spacing

    rng = np.random.default_rng(5)
    d = rng.normal(size=(6000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cap = d[d[:, 2] > 0.6] + np.array([0.0, 0.0, -3.0])
    turn = attacks.rotation_matrix("x", 2.0)
    turned = (cap + [0, 0, 3.0]) @ turn.T - [0, 0, 3.0]
    poses = []
    for unit in (1.0, 1000.0):
        original, suspect = cap * unit, turned * unit
        spacing = float(np.median(nearest_spacing(original)))
        start = Similarity(np.eye(3), 1.0, np.array([0.0, 0.5 * spacing, 0.0]))
        fine = refine_plane(suspect, cKDTree(original), original, d[d[:, 2] > 0.6], start, spacing=spacing)
        poses.append((fine.rotation, fine.scale, fine.translation / unit))
    (r1, s1, t1), (r2, s2, t2) = poses
    assert np.allclose(r1, r2, atol=1e-6) and abs(s1 - s2) < 1e-6 and np.allclose(t1, t2, atol=1e-6)
    assert np.allclose(r1, turn.T, atol=1e-5) and abs(s1 - 1.0) < 1e-6     # and it is the true pose


def test_turns_about_an_axis_exist_only_for_a_near_symmetric_shape_and_keep_its_centroid():
    rng = np.random.default_rng(0)
    theta, z = rng.uniform(0, 2 * np.pi, 4000), rng.uniform(-1, 1, 4000)
    tube = np.column_stack([2 * np.cos(theta), 2 * np.sin(theta), 3 * z])       # symmetric about z
    box = rng.uniform(-1, 1, (4000, 3)) * [4.0, 2.0, 1.0]                         # three distinct spreads
    pose = registration.Similarity(np.eye(3), 1.0, np.zeros(3))
    assert registration.axis_turns(box, pose) == []
    turns = registration.axis_turns(tube, pose, steps=12)
    assert len(turns) == 11
    centroid = tube.mean(axis=0)
    for turn in turns:
        moved = registration.apply(turn, tube)
        assert np.allclose(moved.mean(axis=0), centroid, atol=1e-9)
        assert np.allclose(moved[:, 2], tube[:, 2], atol=0.2)        # turned about the long axis only
        assert np.abs(moved - tube).max() > 0.5


def test_poses_alike_keeps_distinct_poses_that_fit_as_well_and_drops_the_rest():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(1)
    theta, z = rng.uniform(0, 2 * np.pi, 6000), rng.uniform(-1, 1, 6000)
    tube = np.column_stack([np.cos(theta), np.sin(theta), z]) * 20.0
    spacing = float(np.median(cKDTree(tube).query(tube, k=2)[0][:, 1]))
    theta, z = rng.uniform(-0.6, 0.6, 1500), rng.uniform(-1, 1, 1500)
    part = np.column_stack([np.cos(theta), np.sin(theta), z]) * 20.0      # other samples of the same surface
    identity = registration.Similarity(np.eye(3), 1.0, np.zeros(3))
    turn = registration.Similarity(attacks.rotation_matrix("z", 90.0), 1.0, np.zeros(3))
    same = registration.Similarity(np.eye(3), 1.0, np.array([0.0, 0.0, 0.5 * spacing]))
    off = registration.Similarity(np.eye(3), 1.0, np.array([10.0 * spacing, 0.0, 0.0]))
    kept = registration.poses_alike(part, cKDTree(tube), tube[::10], identity, [same, off, turn], spacing)
    assert len(kept) == 1 and kept[0] is turn


def test_fine_turns_find_the_narrow_dip_of_the_true_turn_about_an_axis_of_revolution():
    # a vase-like surface of revolution with fine bumps of its own, as a scan has: every turn about
    # the axis fits nearly alike; a 14 % subset of its points lies exactly on it only at the true turn
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(4)
    z, phi = rng.uniform(-2.0, 2.0, 20000), rng.uniform(0.0, 2.0 * np.pi, 20000)
    radius = 1.0 + 0.3 * np.sin(1.5 * z) + 0.01 * np.sin(7.0 * phi + 3.0 * z) * np.cos(11.0 * phi)
    shape = np.stack([radius * np.cos(phi), radius * np.sin(phi), z], axis=1)
    spacing = float(np.median(cKDTree(shape).query(shape, k=2)[0][:, 1]))
    sub = shape[rng.choice(len(shape), 2800, replace=False)]
    axis = np.array([0.0, 0.0, 1.0])
    true_turn = 37.3
    back = Rotation.from_rotvec(-np.radians(true_turn) * axis).as_matrix()
    copy = sub @ back * 2.0 + [1.0, -3.0, 0.5]                      # turned, scaled, moved
    truth = registration.Similarity(back, 0.5, -0.5 * back @ np.array([1.0, -3.0, 0.5]))
    assert np.abs(apply(truth, copy) - sub).max() < 1e-9
    tree = cKDTree(shape)

    def median(pose):
        return float(np.median(tree.query(apply(pose, copy))[0])) / spacing

    for off in (2.6, -4.2):
        turn = Rotation.from_rotvec(np.radians(off) * axis).as_matrix()
        start = registration.Similarity(turn @ truth.rotation, truth.scale, turn @ truth.translation)
        assert median(start) > 1.0                      # a few degrees off, the subset lies off the surface
        found = registration.fine_turns(copy, tree, start, np.zeros(3), axis, bound=3.0 * spacing)
        assert 1 <= len(found) <= registration.TURN_KEPT
        best = found[0]
        error = np.degrees(np.arccos(np.clip((np.trace(best.rotation @ truth.rotation.T) - 1.0) / 2.0, -1.0, 1.0)))
        assert error <= registration.TURN_FINE, (off, error)
        assert median(best) < 0.2 * median(start)


def test_lies_on_tells_a_copy_noisy_or_resampled_from_a_shape_spread_through_the_band():
    # other poses alike are read only where the suspect lies on the original: a part of the tube
    # (other samples of it, then with noise uniform in +-2 spacings a coordinate) does; another shape
    # crossing the 3-spacing band about it, which fits at every turn alike, does not
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(2)
    theta, z = rng.uniform(0, 2 * np.pi, 6000), rng.uniform(-1, 1, 6000)
    tube = np.column_stack([np.cos(theta), np.sin(theta), z]) * 20.0
    normals = np.column_stack([np.cos(theta), np.sin(theta), np.zeros_like(z)])
    tree, sample = cKDTree(tube), tube[::10]
    spacing = float(np.median(tree.query(tube, k=2)[0][:, 1]))
    theta, z = rng.uniform(-0.6, 0.6, 1500), rng.uniform(-1, 1, 1500)
    on = np.column_stack([np.cos(theta), np.sin(theta), z])
    part = on * 20.0                                                       # other samples of the surface
    noisy = part + rng.uniform(-2.0, 2.0, part.shape) * spacing     # further from the surface than a spacing
    radial = np.column_stack([np.cos(theta), np.sin(theta), np.zeros_like(z)])
    # another smooth surface at the same place, waving through the band (a noisy copy is a band too,
    # but a rough one: its own roughness accounts for its distance)
    wave = 2.9 * spacing * np.sin(2.0 * np.pi * 20.0 * theta / 8.0) * np.cos(2.0 * np.pi * 20.0 * z / 8.0)
    band = part + radial * wave[:, None]
    identity = registration.Similarity(np.eye(3), 1.0, np.zeros(3))
    turn = registration.Similarity(attacks.rotation_matrix("z", 90.0), 1.0, np.zeros(3))
    for suspect, lies in ((part, True), (noisy, True), (band, False)):
        assert registration.lies_on(suspect, tree, identity, spacing, normals) is lies
        assert registration.lies_on(suspect, tree, identity, spacing) is True          # the share alone: all fit
        alike = registration.poses_alike(suspect, tree, sample, identity, [turn], spacing, normals)
        assert alike == ([turn] if lies else [])
        # a copy scaled by half lies on the original alike (the test is in the original's units)
        assert registration.lies_on(suspect / 2.0, tree, registration.Similarity(np.eye(3), 2.0, np.zeros(3)),
                                    spacing, normals) is lies
    assert registration.roughness(noisy) > 0.5 * spacing > 10 * registration.roughness(part)
    # the original's roughness from the registration's own tree (pykdtree): the same neighbourhoods
    from pipeline.nearest import NearestTree

    assert registration.roughness(tube, tree=NearestTree(tube)) == registration.roughness(tube) > 0.0
    # the noisy copy lies on it only because its own roughness is allowed for
    off = np.linalg.norm(noisy, axis=1) - 20.0
    assert np.sqrt(np.mean(off ** 2)) > registration.POSES_CLOSE * spacing
    far = registration.Similarity(np.eye(3), 1.0, np.array([0.0, 0.0, 25.0]))        # most of it off the original
    assert not registration.lies_on(part, tree, far, spacing, normals)
    # what lies_on tests, as numbers: the share within one spacing, and the excess over the roughness
    near, excess = registration.closeness(part, tree, identity, spacing, normals)
    assert near > 0.3 and excess < 0.01 * spacing ** 2      # other samples: half within a spacing, all on it
    near, excess = registration.closeness(noisy, tree, identity, spacing, normals)
    assert near < 0.9 and excess <= (registration.POSES_CLOSE * spacing) ** 2
    near, excess = registration.closeness(band, tree, identity, spacing, normals)
    assert near < 0.3 and excess > (registration.POSES_CLOSE * spacing) ** 2
    assert registration.closeness(part, tree, far, spacing, normals)[0] < 0.5
    assert registration.closeness(part + 1e3, tree, identity, spacing, normals) == (0.0, float("inf"))
