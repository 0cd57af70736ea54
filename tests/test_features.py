"""FPFH features (open3d): part-to-whole registration with scale, the catalogue index, the geometry hash."""

import numpy as np
import pytest

from pipeline import demo, features, surface
from pipeline.io.pointcloud import read_points
from pipeline.kernels import attacks, registration
from pipeline.kernels.resampling import nearest_spacing

INDEX_MODELS = ["bunny_zipper_faceref_34834", "kitten_12623", "nikolov_owl_12442", "fandisk_cad_6475",
                "fertility_4494", "nikolov_birdbath_18793", "nikolov_blackvase_17337", "spot_cow_2930",
                "pcl_tum_rabbit_10429"]


@pytest.fixture(scope="module")
def models(shared_data):
    return {name: read_points(shared_data / "models" / f"{name}.ply").points for name in INDEX_MODELS}


def _aligned_error(transform, suspect, truth):
    return float(np.median(np.linalg.norm(registration.apply(transform, suspect) - truth, axis=1)))


@pytest.mark.parametrize("scale", [0.5, 2.0])
def test_a_30_percent_crop_is_registered_at_any_scale(models, scale):
    kitten = models["kitten_12623"]
    spacing = float(np.median(nearest_spacing(kitten)))
    rng = np.random.default_rng(11)
    part = attacks.crop(kitten, 0.3, rng)
    rot = attacks.random_rotation(rng)
    suspect = attacks.similarity(part, rot, scale, [1.0, 2.0, -3.0])
    found = features.register_global(suspect, kitten, spacing=spacing)
    assert not found.failed()
    assert abs(found.transform.scale * scale - 1.0) < 0.01
    assert _aligned_error(found.transform, suspect, part) < 0.1 * spacing
    assert found.fitness > 0.95 and 0.2 < found.coverage < 0.45


def test_the_asset_is_found_in_a_scene_of_other_models(models):
    owl = models["nikolov_owl_12442"]
    spacing = float(np.median(nearest_spacing(owl)))
    rng = np.random.default_rng(12)
    others = [models[k] for k in ("fertility_4494", "spot_cow_2930", "nikolov_blackvase_17337")]
    moved = attacks.similarity(owl, attacks.random_rotation(rng), 0.7, [5.0, 0.0, 0.0])
    scene = attacks.scene(moved, others, 3.0, rng)
    assert len(scene) == pytest.approx(4 * len(owl), rel=0.01)
    found = features.register_global(scene[rng.permutation(len(scene))], owl, spacing=spacing)
    assert not found.failed() and found.coverage > 0.95
    assert _aligned_error(found.transform, moved, owl) < 0.1 * spacing


def test_geometry_hash_ignores_order_format_and_placement_but_not_edits(models):
    cow = models["spot_cow_2930"]
    h = features.geometry_hash(cow)
    rng = np.random.default_rng(0)
    assert features.geometry_hash(cow[rng.permutation(len(cow))]) == h
    assert features.geometry_hash(cow.astype(np.float32).astype(np.float64)) == h
    assert features.geometry_hash(cow * 3.0 + 7.0) == h
    assert features.geometry_hash(attacks.noise_uniform(cow, 0.001, rng)) != h
    assert features.geometry_hash(cow[1:]) != h


@pytest.fixture(scope="module")
def index(models, tmp_path_factory):
    built = features.build_index(models)
    path = tmp_path_factory.mktemp("index") / "index.npz"
    built.save(path)
    return features.FeatureIndex.load(path)


@pytest.fixture(scope="module")
def ivf_index(index, tmp_path_factory):
    """The same index searched through an inverted file (large catalogues), saved and loaded."""
    built = features.FeatureIndex(index.keys, index.features, index.owner, index.hashes, index.prior,
                                  features.InvertedFile.train(index.features))
    path = tmp_path_factory.mktemp("ivf") / "index.npz"
    built.save(path)
    loaded = features.FeatureIndex.load(path)
    assert loaded.cells is not None and np.array_equal(loaded.cells.cell, built.cells.cell)
    return loaded


def test_the_inverted_file_finds_the_exact_nearest_descriptor_almost_always(models, index, ivf_index):
    suspect = surface.apply_chain(models["kitten_12623"], [("crop", 0.5), ("random_similarity", None)], rng=5)
    _, feats = features.describe(suspect)
    exact, _ = features.nearest_exact(feats, index.features, 8)
    approx, sim = ivf_index.cells.nearest(feats, index.features, 8)
    assert (approx[:, 0] == exact[:, 0]).mean() > 0.97
    assert np.all(np.diff(sim, axis=1) <= 0)          # most similar first
    assert len(ivf_index.cells.centroids) == int(np.sqrt(len(index.features)))


@pytest.mark.parametrize("model,chain,search", [
    ("bunny_zipper_faceref_34834", "crop:0.3+random_similarity", "index"),
    ("kitten_12623", "crop:0.5+random_similarity+noise:0.3%", "index"),
    ("nikolov_owl_12442", "resample:5000", "index"),
    ("nikolov_birdbath_18793", "random_similarity+clutter:3", "index"),
    ("fertility_4494", "outliers:0.5", "index"),
    ("nikolov_blackvase_17337", "noise:0.5%+random_similarity", "index"),
    # the same ranking through the inverted file of large catalogues
    ("bunny_zipper_faceref_34834", "crop:0.3+random_similarity", "ivf_index"),
    ("nikolov_birdbath_18793", "random_similarity+clutter:3", "ivf_index"),
    ("fertility_4494", "outliers:0.5", "ivf_index"),
])
def test_the_right_asset_is_among_the_top_3(models, request, search, model, chain):
    steps = [surface.parse_attack(s) for s in chain.split("+")] + [("shuffle", None)]
    suspect = surface.apply_chain(models[model], steps, rng=3)
    ranked = request.getfixturevalue(search).rank(suspect, top_k=3)
    assert model in [k for k, _ in ranked], ranked


def test_an_exact_resave_ranks_first_by_its_hash(models, index):
    cow = models["spot_cow_2930"]
    ranked = index.rank(cow[::-1].astype(np.float32), top_k=3)
    assert ranked[0] == ("spot_cow_2930", float("inf"))


def test_outlier_and_clutter_attacks_are_parsed_and_keep_the_asset_first():
    pts = demo.procedural_shape("torus", 3000, seed=1)
    assert surface.parse_attack("outliers:0.5") == ("outliers", 0.5)
    junk = surface.apply_chain(pts, [("outliers", 0.5)], rng=2)
    assert len(junk) == 4500 and np.array_equal(junk[:3000], pts)
    assert (junk.min(axis=0) >= pts.min(axis=0)).all() and (junk.max(axis=0) <= pts.max(axis=0)).all()
    scene = surface.apply_chain(pts, [("clutter", 3.0)], rng=2)
    assert len(scene) == pytest.approx(12000, rel=0.01) and np.array_equal(scene[:3000], pts)
    # the clutter surrounds the asset without touching it
    from scipy.spatial import cKDTree

    gap, _ = cKDTree(pts).query(scene[3000:])
    assert gap.min() > 0.05 * float((pts.max(axis=0) - pts.min(axis=0)).max())


def test_near_equal_overlaps_are_decided_by_the_residual():
    # the owl cropped to 30 %: a pose slightly off covered 0.345 of the
    # original with residual 0.75 spacings, the true one 0.333 with 0.155
    assert features.best_overlap([(0.512, 0.75), (0.499, 0.155)]) == 1
    # a clearly larger overlap wins whatever its residual (a collapsed fit
    # has a tiny residual and covers little)
    assert features.best_overlap([(0.05, 0.01), (0.50, 0.80)]) == 1
    # equal residuals: the first
    assert features.best_overlap([(0.5, 0.2), (0.5, 0.2)]) == 0
