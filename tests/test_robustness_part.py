"""Part-to-whole detection (issue 13): crops, scenes and junk, with every suspect shuffled.

Embeds with the default config's parameters (32 bits, c 10, interleaved
chips, displacement along the normals at the paper's distance to the
surface, the tail-biting payload code), attacks, shuffles and
detects through ``estimate_differences`` / ``decode``, the engine's own
path; registration is the default ``robust``: unless the principal frames
overlap the original from both sides, a separate object of the suspect that
looks like the original is registered whole, and failing that the
feature-based global step competes.  One model per case keeps each under
about 30 s.
"""

from dataclasses import replace

import numpy as np
import pytest

from pipeline import config, surface
from pipeline.config import DetectParams
from pipeline.io.pointcloud import read_points
from pipeline.kernels import attacks, keys, modulation
from pipeline.orchestrate import evaluate
from pipeline.watermark import decode, embed_with_bases, estimate_differences, frame_of
from tests.conftest import ROOT

pytestmark = pytest.mark.slow
DEFAULT = config.load_config(ROOT / "configs" / "default.yaml")
SIZES = {"bunny_zipper_faceref_34834": 4000, "kitten_12623": 2400, "nikolov_owl_12442": 2400}
MATERIAL = keys.derive_key_material(b"robustness-part-secret", "part")
MESSAGE = "5ca1ab1e"


@pytest.fixture(scope="module")
def marked(shared_data, shared_bases):
    """Per model: original, marked copy, its frame, clusters and bases (computed once per run)."""
    cache = {}

    def get(name):
        if name not in cache:
            path = shared_data / "models" / f"{name}.ply"
            points = read_points(path).points
            params = replace(config.watermark_params(DEFAULT), cluster_size=SIZES[name])
            frame = frame_of(points)
            centred = points - frame.centre
            centre, phi, specs, bases = evaluate.load_bases(shared_bases(path, params), points, params)
            assert np.array_equal(centre, frame.centre) and phi == frame.phi
            bits = modulation.hex_to_bits(MESSAGE, params.n_bits)
            copy = embed_with_bases(centred, specs, bases, MATERIAL, bits, params, frame.phi) + frame.centre
            cache[name] = (points, copy, frame, specs, bases, params, bits)
        return cache[name]

    return get


def _detect(marked, name, suspect, registration="robust"):
    points, _, frame, specs, bases, params, bits = marked(name)
    dparams = replace(config.detect_params(DEFAULT), registration=registration)
    estimate = estimate_differences(suspect - frame.centre, points - frame.centre, specs, bases, dparams,
                                    params)
    result = decode(estimate, specs, MATERIAL, params, dparams)
    return int((np.asarray(result["bits"]) != bits).sum()), result


def _attacked(copy, chain, seed=7):
    steps = [surface.parse_attack(s) for s in chain.split("+")] + [("shuffle", None)]
    return surface.apply_chain(copy, steps, rng=seed)


@pytest.mark.parametrize("name,chain", [
    ("bunny_zipper_faceref_34834", "crop:0.5+random_similarity+noise:0.3%"),
    ("kitten_12623", "crop:0.3+random_similarity"),
    ("nikolov_owl_12442", "random_similarity+clutter:3"),
    ("kitten_12623", "outliers:0.5"),
])
def test_zero_bit_errors_with_the_default_registration(marked, name, chain):
    errors, result = _detect(marked, name, _attacked(marked(name)[1], chain))
    assert errors == 0, result
    assert result["detected"] and result["p_value"] < 1e-6


def test_zero_bit_errors_inside_a_scene_of_other_scans(marked, shared_data):
    # seed 21 once stopped RANSAC 15 degrees off on the near-symmetric owl (the
    # rotated ICP restarts of register_global recovered it), and at the default's
    # beta on a wrong pose: the scene's separate objects are now registered whole
    copy = marked("nikolov_owl_12442")[1]
    rng = np.random.default_rng(21)
    others = [read_points(shared_data / "models" / f"{k}.ply").points
              for k in ("fertility_4494", "spot_cow_2930", "nikolov_blackvase_17337")]
    moved = attacks.similarity(copy, attacks.random_rotation(rng), 0.6, [2.0, -1.0, 0.5])
    scene = attacks.scene(moved, others, 3.0, rng)
    errors, result = _detect(marked, "nikolov_owl_12442", scene[rng.permutation(len(scene))])
    assert errors == 0, result
    assert result["detected"]
    assert 0.2 < result["registration"]["fitness"] < 0.3   # a quarter of the scene is the asset


@pytest.mark.parametrize("name", ["spot_cow_2930", "bunny_res3_1889"])
def test_junk_near_a_small_scan_does_not_shrink_its_registration(shared_data, name):
    """50 % outliers in the box of a sparse scan: over 40 % of them land within 3 spacings, so the
    copy fits "whole" (overlap over 0.8) and the quantile-trimmed ICP alone leaves the scale 1.7-2.4 % short
    (the leak benchmark's spot_cow and bunny_res3 copies were missed so); the fixed-cut polish
    brings it within 0.2 %."""
    from scipy.spatial import cKDTree

    from pipeline.kernels import resampling
    from pipeline.watermark import register

    points = read_points(shared_data / "models" / f"{name}.ply").points
    points = points - points.mean(axis=0)
    spacing = float(np.median(resampling.nearest_spacing(points)))
    for seed in range(2):
        suspect = attacks.apply_chain(points, [("outliers", 0.5), ("shuffle", None)], np.random.default_rng(seed))
        found = register(suspect, points, spacing, DetectParams(registration="robust"), cKDTree(points))
        assert abs(found.scale - 1.0) < 2e-3, (seed, found.scale)
        assert found.fitness > 0.6
