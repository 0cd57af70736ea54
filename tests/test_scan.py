"""Leak scans: attribute attacked copies to asset and recipient; say no to the rest."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from pipeline import config
from pipeline.demo import procedural_shape
from pipeline.io.catalog import catalogue_record, discover_assets, write_catalogue
from pipeline.io.pointcloud import read_points, write_array
from pipeline.kernels import attacks
from pipeline.orchestrate.progress import Progress
from pipeline.orchestrate.run import plan_job, run_job
from pipeline.orchestrate.scan import read_scan
from tests.conftest import ROOT, SMALL_DETECTION

pytestmark = pytest.mark.slow
SECRET = "scan-test-secret-91c"
RECIPIENTS = ["alice", "bob", "carol"]
SHAPES = [("blob", 1), ("torus", 2), ("shell", 3), ("terrain", 4), ("blob", 5), ("torus", 6)]

# suspect name -> (asset index, recipient index, attack chain)
SUSPECTS = {
    "leak-similarity": (0, 1, [("random_similarity", None)]),
    "leak-noise": (1, 2, [("noise", 0.005)]),
    "leak-removal": (2, 0, [("removal", 0.5)]),
    "leak-crop": (3, 1, [("crop", 0.7)]),
    "leak-exact": (4, 2, []),
    # part-to-whole, through the CLI: half of the asset, and the asset inside a scene.  (The
    # 5,000-point procedural shapes are poorer in local features than the real scans of
    # tests/test_robustness_part.py: a 1,500-point crop of a smooth blob, or a torus, symmetric
    # about its axis, among clutter, is registered at some seeds only; see bench/leaks.py.)
    "leak-part": (2, 2, [("crop", 0.5), ("random_similarity", None)]),
    "leak-scene": (3, 1, [("random_similarity", None), ("clutter", 3.0)]),
}


# every key written out (the schema's defaults may change): the paper's 32 bits at c 10, two clusters
WATERMARK = {"n_bits": 32, "chip_rate": 10, "beta": 0.002, "valence": 12, "n_clusters": 2, "cluster_size": 2000,
             "seeds": None, "on_touch": "skip", "cover": False, "chip_layout": "consecutive", "first_coefficient": 0,
             "crc_bits": 0, "displacement": "xyz", "amplitude": "model", "max_displacement": None,
             "tile_points": None, "code": "repetition", "band_noise": None}


@pytest.fixture(scope="module")
def scanned(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("scan")
    for i, (kind, seed) in enumerate(SHAPES):
        write_array(tmp / "assets", f"asset-{i}", procedural_shape(kind, 5000, seed=seed) * 20, "ply")
    rows = [catalogue_record(a) for a in discover_assets(tmp / "assets", default_recipients=RECIPIENTS)]
    write_catalogue(rows, tmp / "catalog.parquet")
    cfg_dict = {
        "catalog": {"source": str(tmp / "catalog.parquet")}, "recipients": RECIPIENTS,
        "output": {"dir": str(tmp / "marked"), "manifests": str(tmp / "manifests")},
        "key": {"id": "scan-key", "secret_file": str(tmp / "key")},
        "watermark": WATERMARK,
        # the deep registration at the tests' smaller effort (the cascade's gates are the defaults)
        "detection": SMALL_DETECTION,
        # one candidate from each ranking finds every leak's asset here; more would only add deep
        # checks of innocent candidates (8 to 25 s each: leak-part and the box still make one each)
        "scan": {"suspects": str(tmp / "suspects"), "catalogue": str(tmp / "catalog.parquet"),
                 "out": str(tmp / "scan"), "top_k": 1},
        "dask": {"n_workers": 2, "progress": "none"},
    }
    (tmp / "key").write_text(SECRET)
    (tmp / "scan.yaml").write_text(yaml.safe_dump(cfg_dict))
    cfg = config.load_config(tmp / "scan.yaml")
    job = plan_job(cfg, SECRET.encode())
    assert run_job(job, cfg, progress=Progress())["ok"] == 6
    rng = np.random.default_rng(11)
    for name, (a, r, chain) in SUSPECTS.items():
        marked = tmp / "marked" / RECIPIENTS[r] / f"asset-{a}.ply"
        if not chain:
            (tmp / "suspects").mkdir(exist_ok=True)
            (tmp / "suspects" / f"{name}.ply").write_bytes(marked.read_bytes())
            continue
        pts = attacks.apply_chain(read_points(marked).points, chain + [("shuffle", None)], rng)
        write_array(tmp / "suspects", name, pts, "ply")
    box = attacks.box(np.random.default_rng(99), 5000, sides=(3.0, 2.0, 1.0))   # like no catalogue shape
    write_array(tmp / "suspects", "unrelated", box * 20, "ply")
    write_array(tmp / "suspects", "unmarked", read_points(tmp / "assets" / "asset-5.ply").points[::-1], "ply")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "scan", str(tmp / "scan.yaml")], cwd=tmp,
                         env=env, capture_output=True, text=True, timeout=900)
    return tmp, res, env


def _best(tmp):
    return {Path(r["suspect_path"]).stem: r for r in read_scan(tmp / "scan")}


def test_scan_exits_1_on_a_match(scanned):
    _, res, _ = scanned
    assert res.returncode == 1, res.stdout + res.stderr


# leak-scene: a 5,000-point procedural terrain among procedural clutter was registered onto the
# wrong objects here (fitness 0.21, coverage 0.18) until the scene's separate objects were
# registered whole (watermark._register_parts)
@pytest.mark.parametrize("name", SUSPECTS)
def test_attacked_copies_are_attributed_to_asset_and_recipient(scanned, name):
    tmp, _, _ = scanned
    a, r, _ = SUSPECTS[name]
    row = _best(tmp)[name]
    assert row["verdict"] == "match", row
    assert row["candidate_asset"] == f"asset-{a}" and row["recipient"] == RECIPIENTS[r]
    if name != "leak-exact":
        assert row["score"] >= row["threshold"] and row["p_value"] < 1e-6 and row["margin"] > 0
        assert row["registration_status"] == "registered" and row["registration_coverage"] > 0.25


@pytest.mark.parametrize("name", ["unrelated", "unmarked"])
def test_unrelated_and_unmarked_are_no_match(scanned, name):
    tmp, _, _ = scanned
    assert _best(tmp)[name]["verdict"] == "no match"


def test_the_cascade_stops_candidates_of_an_unrelated_shape_before_the_deep_steps(scanned):
    # at the default gates: a box is like none of the catalogue in descriptors or in shape
    row = _best(scanned[0])["unrelated"]
    assert row["n_stopped"] >= 1 and "stopped by the cascade" in row["note"]


def test_a_second_scan_skips_suspects_already_scanned(scanned):
    tmp, _, env = scanned
    before = len(read_scan(tmp / "scan"))
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "scan", str(tmp / "scan.yaml")], cwd=tmp,
                         env=env, capture_output=True, text=True, timeout=600)
    assert f"{len(SUSPECTS) + 2} already scanned" in res.stdout, res.stdout + res.stderr
    assert res.returncode == 0 and len(read_scan(tmp / "scan")) == before
