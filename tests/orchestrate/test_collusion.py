"""Collusion and innocents on a real scan, small setting (configs/evaluate-fingerprints.yaml has the full one)."""

from dataclasses import replace

import pytest

from pipeline import config
from pipeline.orchestrate import evaluate
from pipeline.kernels import keys
from tests.conftest import ROOT

pytestmark = pytest.mark.slow
DEFAULT = config.load_config(ROOT / "configs" / "default.yaml")
MATERIAL = keys.derive_key_material(b"collusion-test-secret-0001", "collusion")
RECIPIENTS = 300


@pytest.fixture(scope="module")
def prepared(shared_data, tmp_path_factory):
    path = shared_data / "models" / "bunny_res2_8171.ply"
    params = replace(config.watermark_params(DEFAULT), n_clusters=3, cluster_size=2500)
    handle = evaluate.prepare_bases(path, evaluate._basis_params(params, params.n_coefficients),
                                    tmp_path_factory.mktemp("bases"))
    return str(path), handle, params


def _trial(prepared, case, attack="none", seed=3):
    path, handle, params = prepared
    return evaluate.fingerprint_trial(path, handle, params, config.detect_params(DEFAULT), attack, case, seed,
                                      MATERIAL, RECIPIENTS)


@pytest.mark.parametrize("case, attack", [("single", "noise:0.5%"), ("average:2", "none"), ("average:3", "none"),
                                          ("interleave:2", "none"), ("average:2", "noise:0.25%")])
def test_every_colluder_is_accused_and_no_innocent(prepared, case, attack):
    row = _trial(prepared, case, attack)
    assert row["accused_colluders"] == row["colluders"] >= 1, row
    assert row["accused_innocents"] == 0
    assert row["min_colluder_score"] > row["threshold"] > row["max_innocent_score"]


@pytest.mark.parametrize("case", ["unmarked", "other-key"])
def test_nobody_is_accused_when_no_fingerprint_is_present(prepared, case):
    rows = [_trial(prepared, case, seed=s) for s in (1, 2)]
    assert all(r["accused_innocents"] == 0 and r["max_innocent_score"] < r["threshold"] for r in rows)
    # innocents' scores follow the bound the threshold is built on (2 x 300 checks)
    over_2 = sum(r["innocents_over_2"] for r in rows) / sum(r["innocent_checks"] for r in rows)
    assert over_2 <= 2 * 0.1353
