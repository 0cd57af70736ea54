"""The verdict of a suspect: the correction counts what was planned, not only what was scored."""

import numpy as np

from pipeline.kernels import fingerprint
from pipeline.orchestrate.attribute import decide
from pipeline.orchestrate.candidates import planned_recipients


def _check(scores, asset="a"):
    return {"groups": [{"asset_key": asset, "key_id": "k", "reference_key": "ref", "generation": 1, "reference": {},
                        "n_recipients": len(scores), "presence_p": 1.0, "registration": {},
                        "best": [{"recipient": f"r{i}", "score": float(s), "copies": [(1, "x")],
                                  "cluster_scores": None} for i, s in enumerate(scores)]}]}


def test_a_scan_that_stops_at_the_first_match_counts_every_planned_recipient():
    checks = [_check([6.5, 0.3, -0.5])]
    alone = decide(checks, 1e-6)
    planned = decide(checks, 1e-6, planned=10_000)
    assert alone["n_checked"] == 3 and planned["n_checked"] == 10_000
    assert planned["threshold"] == fingerprint.threshold(10_000, 1e-6) > alone["threshold"]
    # 6.5 clears the threshold for 3 recipients (5.46) but not for 10,000 (6.79)
    assert alone["verdict"] == "match" and planned["verdict"] == "no match"
    assert np.isclose(planned["p_value"], min(1.0, 10_000 * np.exp(-6.5 ** 2 / 2)))


def test_every_pose_the_mark_was_read_at_counts_as_a_check_of_every_recipient():
    check = _check([6.7, 0.3, -0.5])
    once = decide([check], 1e-6, planned=1000)
    check["groups"][0]["n_poses"] = 3000          # a piece of a solid of revolution read at 3,000 poses
    many = decide([check], 1e-6, planned=1000)
    assert once["n_checked"] == 1000 and many["n_checked"] == 9000
    assert many["threshold"] == fingerprint.threshold(9000, 1e-6)
    # 6.7 clears the threshold for 1,000 checks (6.44) but not for 9,000 (6.77)
    assert once["verdict"] == "match" and many["verdict"] == "no match"


def test_earlier_scans_add_to_the_planned_count():
    assert decide([_check([1.0])], 1e-6, prior_checked=50, planned=20)["n_checked"] == 70


def test_planned_recipients_counts_held_keys_once_per_reference_generation_and_recipient():
    rows = [{"reference_key": "A", "key_id": "k1", "generation_id": "g1", "recipient": r} for r in ("x", "y")]
    rows += [{"reference_key": "A", "key_id": "k1", "generation_id": "g1", "recipient": "x"}]     # a rerun row
    rows += [{"reference_key": "A", "key_id": "k1", "generation_id": "g2", "recipient": "x"}]     # new generation
    rows += [{"reference_key": "A", "key_id": "k2", "generation_id": "g1", "recipient": "z"}]     # key not held
    assert planned_recipients([rows, rows[:1]], {"k1": b"m"}) == 3 + 1


def test_a_suspect_that_lands_nowhere_on_the_original_is_a_failed_registration():
    from dataclasses import replace

    from pipeline import config
    from pipeline.demo import procedural_shape
    from pipeline.watermark import cluster_basis, estimate_differences, plan_clusters

    points = procedural_shape("blob", 3000, seed=3)
    params = replace(config.watermark_params(config.load_config(None)), n_clusters=1, cluster_size=1000)
    specs = plan_clusters(points, params)
    bases = [cluster_basis(points[s.members], params)[1] for s in specs]
    dparams = replace(config.detect_params(config.load_config(None)), registration="none")
    here = estimate_differences(points[::-1], points, specs, bases, dparams, params)["registration"]
    away = estimate_differences(points + 10.0, points, specs, bases, dparams, params)["registration"]
    assert not here["failed"] and here["fitness"] > 0.99 and here["coverage"] > 0.99
    assert away["failed"] and away["fitness"] == 0.0 and away["coverage"] == 0.0


def test_a_row_written_before_a_parameter_existed_keeps_the_value_it_was_issued_under():
    import json

    from pipeline.orchestrate.attribute import params_from_row

    old = {"n_bits": 32, "chip_rate": 2, "beta": 0.002, "valence": 12, "n_clusters": 5, "cluster_size": 4000,
           "seeds": None, "on_touch": "skip", "cover": False, "chip_layout": "consecutive", "first_coefficient": 0,
           "crc_bits": 0, "displacement": "xyz"}               # a 0.2.0 row: no amplitude, cap, tiles or code
    params = params_from_row({"params_json": json.dumps(old)})
    assert (params.code, params.amplitude, params.max_displacement, params.tile_points) == (
        "repetition", "model", None, None)                   # not today's defaults (the coded defaults need c >= 3)
    assert (params.beta, params.displacement, params.chip_rate) == (0.002, "xyz", 2)
