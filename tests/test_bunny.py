"""Issue 3's acceptance on the real bunny with configs/paper.yaml.

Embedding runs in a separate process (the CLI); detection runs here, in
another process, rebuilding clusters and spectral bases from the original.
Every attacked copy is shuffled: detection must not rely on point order.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from pipeline import config, watermark as wm
from pipeline.io.pointcloud import read_points
from pipeline.kernels import attacks, keys, modulation
from tests.conftest import ROOT

pytestmark = pytest.mark.slow
SECRET = "bunny-test-secret"
MESSAGE = "5ca1ab1e"
CONFIG = ROOT / "configs" / "paper.yaml"


@pytest.fixture(scope="module")
def marked(bunny_path, tmp_path_factory):
    out = tmp_path_factory.mktemp("bunny") / "marked.ply"
    env = dict(os.environ, POINTMARK_SECRET=SECRET, OMP_NUM_THREADS="2")
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "embed", str(bunny_path), str(out),
                          "--key-id", "asset-1", "--message", MESSAGE, "--config", str(CONFIG), "--json"],
                         env=env, cwd=ROOT, capture_output=True, text=True, check=True)
    return out, json.loads(res.stdout)


@pytest.fixture(scope="module")
def reference(bunny_path):
    cfg = config.load_config(CONFIG)
    params, dparams = config.watermark_params(cfg), config.detect_params(cfg)
    original = read_points(bunny_path).points
    frame = wm.frame_of(original)
    ref = original - frame.centre
    specs = wm.plan_clusters(ref, params)
    bases = [wm.cluster_basis(ref[s.members], params)[1] for s in specs]
    return original, frame, ref, specs, bases, params, dparams


def _detect(reference, suspect, key_id="asset-1"):
    original, frame, ref, specs, bases, params, dparams = reference
    material = keys.derive_key_material(SECRET.encode(), key_id)
    return wm.detect_with_bases(suspect - frame.centre, ref, specs, bases, material, params, dparams)


def _errors(result):
    return int((np.array(result["bits"]) != modulation.hex_to_bits(MESSAGE, 32)).sum())


def test_embedding_reports_paper_clusters_and_small_distortion(marked):
    _, res = marked
    assert res["n_points"] == 34834 and len(res["clusters"]) == 5
    assert all(abs(c["size"] - 4000) <= 0 for c in res["clusters"])
    assert res["distortion"]["rmse_rel_diag"] < 0.001


ATTACKS = {
    "unattacked": [],
    "shuffle": [("shuffle", None)],
    "paper_similarity": [("similarity", None), ("shuffle", None)],
    "noise_0.5%": [("noise", 0.005), ("shuffle", None)],
    "removal_to_4839": [("removal", 4839 / 34834), ("shuffle", None)],
}


@pytest.mark.parametrize("name", list(ATTACKS))
def test_zero_bit_errors_after(name, marked, reference):
    points = read_points(marked[0]).points
    suspect = attacks.apply_chain(points, ATTACKS[name], rng=20261122)
    result = _detect(reference, suspect)
    assert _errors(result) == 0, result["bit_scores"]
    assert result["detected"] and result["p_value"] < 1e-6


def test_original_is_not_watermarked(reference):
    result = _detect(reference, reference[0])
    assert not result["detected"] and result["p_value"] > 1e-3


def test_wrong_key_is_not_watermarked(marked, reference):
    result = _detect(reference, read_points(marked[0]).points, key_id="asset-2")
    assert not result["detected"] and result["p_value"] > 1e-3


def test_cli_detect_in_a_third_process_with_one_thread(marked, bunny_path):
    env = dict(os.environ, POINTMARK_SECRET=SECRET, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "detect", str(marked[0]), "--original",
                          str(bunny_path), "--key-id", "asset-1", "--config", str(CONFIG), "--json",
                          "--expect", MESSAGE], env=env, cwd=ROOT, capture_output=True, text=True, check=True)
    out = json.loads(res.stdout)
    assert out["bit_errors"] == 0 and out["detected"] and out["message"] == MESSAGE


def test_embedding_twice_is_byte_identical(marked, bunny_path, tmp_path):
    again = tmp_path / "again.ply"
    env = dict(os.environ, POINTMARK_SECRET=SECRET, OMP_NUM_THREADS="1")
    subprocess.run([sys.executable, "-m", "pipeline.cli", "embed", str(bunny_path), str(again), "--key-id",
                    "asset-1", "--message", MESSAGE, "--config", str(CONFIG)], env=env, cwd=ROOT, check=True,
                   capture_output=True)
    assert again.read_bytes() == marked[0].read_bytes()
