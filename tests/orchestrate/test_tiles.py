"""The tiled path for large assets (issue 15): planned cell by cell, cluster tasks that read only their
cluster, issue tasks that hold one basis at a time, and the mark read back from a tenth of the tile."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml

from pipeline import config, demo
from pipeline.io.basis_store import BasisStore
from pipeline.io.ledger import Ledger
from pipeline.io.pointcloud import read_points, write_array
from pipeline.kernels import clustering
from pipeline.kernels import digest
from pipeline.orchestrate import tasks
from pipeline.orchestrate.progress import Progress
from pipeline.orchestrate.reference import load_reference
from pipeline.orchestrate.run import plan_job, run_job
from pipeline.config import WatermarkParams
from pipeline.watermark import ReferenceMismatch
from tests.conftest import ROOT
from tests.orchestrate.test_run import SECRET, _outputs, make_catalogue, write_config

pytestmark = pytest.mark.slow

TILED = {"n_bits": 8, "chip_rate": 4, "cluster_size": 600, "tile_points": 5000, "cover": True,
         "amplitude": "cluster", "displacement": "normal", "chip_layout": "interleaved", "beta": 0.004,
         "code": "repetition"}


@pytest.fixture(scope="module")
def tile(tmp_path_factory):
    """A 400 m terrain tile of 40,000 points in survey coordinates, as LAZ."""
    pts = demo.procedural_shape("terrain", 40_000, seed=9) * 200.0 + np.array([6.37e5, 8.51e5, 100.0])
    return write_array(tmp_path_factory.mktemp("tile"), "tile", pts, "laz")


def _tiled_run(tmp_path, tile, serial=False):
    cfg_path = write_config(tmp_path, tile, extra={"watermark": TILED})
    cfg = config.load_config(cfg_path)
    job = plan_job(cfg, SECRET.encode())
    return job, run_job(job, cfg, serial=serial, progress=Progress())


def test_a_tiled_run_covers_the_tile_cell_by_cell_and_a_tenth_names_the_recipient(tmp_path, tile):
    job, counts = _tiled_run(tmp_path, tile)
    assert counts == {"ok": 1, "failed": 0, "skipped": 0}
    rows = Ledger(job.manifests).rows()
    assert sorted(r["recipient"] for r in rows) == ["alice", "bob"]
    points = read_points(tile).points
    sizes = rows[0]["cluster_sizes"]
    assert sum(sizes) >= 0.99 * len(points)                        # cover: the whole tile is marked
    params = WatermarkParams(**{k: v for k, v in TILED.items()})
    meta = BasisStore(job.store).load_meta(rows[0]["reference_key"])
    cells = clustering.grid_cells(points - meta[0], params.tile_points)
    cell_of = np.empty(len(points), dtype=np.int64)
    for i, c in enumerate(cells):
        cell_of[c] = i
    assert all(len(set(cell_of[m].tolist())) == 1 for m in meta[3])   # no cluster crosses a cell
    assert len(cells) >= 6 and len(meta[3]) >= 4 * len(cells)
    # a tenth of bob's copy, shuffled: the detect command names bob from the ledger and the store
    bob = next(r for r in rows if r["recipient"] == "bob")["output_path"]
    crop = tmp_path / "crop.laz"
    subprocess.run([sys.executable, "-m", "pipeline.cli", "attack", bob, str(crop), "--attack", "crop:0.1",
                    "--seed", "4"], check=True, cwd=ROOT, capture_output=True)
    out = subprocess.run([sys.executable, "-m", "pipeline.cli", "detect", "--ledger", str(job.manifests),
                          "--json", str(crop)], cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, "POINTMARK_SECRET": SECRET})
    assert out.returncode == 0, out.stderr
    verdict = json.loads(out.stdout)
    assert verdict["verdict"] == "match" and [a["recipient"] for a in verdict["accused"]] == ["bob"]


def _planned(tmp_path, tile):
    params = WatermarkParams(**TILED)
    store = BasisStore(tmp_path / "bases")
    copy = tmp_path / "asset.laz"
    copy.write_bytes(tile.read_bytes())
    return params, store, copy, tasks.plan_asset("asset", copy, "", params, store.folder, "k")


def test_cluster_tasks_of_a_tiled_asset_need_only_the_store(tmp_path, tile):
    params, store, copy, plan = _planned(tmp_path, tile)
    copy.unlink()                                 # the cluster tasks must not read the file
    for i in range(len(plan.clusters)):
        assert tasks.cluster_task(plan, i, params)["basis"]
    assert all(store.has("k", f"cluster-{i}") for i in range(len(plan.clusters)))


def test_a_damaged_stored_cluster_is_read_from_the_asset_and_stored_again(tmp_path, tile):
    params, store, copy, plan = _planned(tmp_path, tile)
    good = tasks.cluster_task(plan, 0, params)
    (store.folder / "k" / "cluster-0.npz").unlink()
    (store.folder / "k" / "points-0.npz").write_bytes(b"damaged")
    again = tasks.cluster_task(plan, 0, params)
    assert again["basis"] == good["basis"]
    assert store.load_array("k", "points-0").shape == (len(plan.clusters[0].members), 3)


def test_detection_models_the_normals_a_tiled_embedding_moved_along(tmp_path, tile):
    params, store, copy, plan = _planned(tmp_path, tile)
    parts = [tasks.cluster_task(plan, i, params) for i in range(len(plan.clusters))]
    recorded = {"membership": [p["membership"] for p in parts], "basis": [p["basis"] for p in parts]}
    ref = load_reference(read_points(copy).points, params, store, "k", recorded, detection=True)
    for spec, normals in zip(ref.specs, ref.normals):
        assert np.array_equal(ref.model_normals[spec.members], normals)


def test_an_issue_task_refuses_a_stored_basis_its_cluster_task_did_not_record(tmp_path, tile):
    params, store, copy, plan = _planned(tmp_path, tile)
    parts = [tasks.cluster_task(plan, i, params) for i in range(len(plan.clusters))]
    radius, basis, normals = store.load_cluster("k", 3)
    store.save_cluster("k", 3, radius, basis[:, ::-1], normals)       # another basis under cluster 3
    assert digest.basis_digest(basis[:, ::-1]) != parts[3]["basis"]
    with pytest.raises(ReferenceMismatch, match="cluster 3 spectral basis"):
        tasks.issue_task(plan, parts, b"m" * 32, [("alice", tmp_path / "out" / "a.laz")], params,
                         {"generation": 1})
    assert not (tmp_path / "out" / "a.laz").exists()


def test_a_large_tiled_copy_has_its_surface_measures_pooled_over_cells(monkeypatch, tile):
    points = read_points(tile).points
    rng = np.random.default_rng(2)
    marked = points + rng.normal(0, 0.01, points.shape)
    exact = tasks._distortion_measure(points, WatermarkParams(**TILED))(marked)
    monkeypatch.setattr(tasks, "POOLED_POINTS", 10_000)
    pooled = tasks._distortion_measure(points, WatermarkParams(**TILED))(marked)
    assert pooled["rmse_rel_diag"] == exact["rmse_rel_diag"]
    for name in ("mrms_rel_diag", "surface_rmse_rel_diag", "normal_deviation_deg"):
        assert pooled[name] == pytest.approx(exact[name], rel=0.05), name
    assert pooled["hausdorff_rel_diag"] >= exact["hausdorff_rel_diag"]


def test_copies_built_from_scratch_files_are_the_same_bytes(tmp_path, monkeypatch):
    src = make_catalogue(tmp_path / "assets", n_assets=2)
    cfg = config.load_config(write_config(tmp_path, src, out="together"))
    assert run_job(plan_job(cfg, SECRET.encode()), cfg, serial=True, progress=Progress())["ok"] == 2
    monkeypatch.setattr(tasks, "MARKED_BYTES", 1)        # displacements through scratch files, one copy at a time
    cfg = config.load_config(write_config(tmp_path, src, out="apart"))
    assert run_job(plan_job(cfg, SECRET.encode()), cfg, serial=True, progress=Progress())["ok"] == 2
    a, b = _outputs(tmp_path / "together" / "marked"), _outputs(tmp_path / "apart" / "marked")
    assert len(a) == 4 and a == b                        # and no scratch folder is left behind


@pytest.mark.parametrize("settings, problem", [
    ({"tile_points": 5000, "cover": True, "seeds": [1, 2]}, "seeds"),
    ({"tile_points": 5000, "cover": False}, "cover"),
    ({"tile_points": 2000, "cover": True, "cluster_size": 4000}, "cluster_size"),
])
def test_tile_points_that_cannot_apply_are_refused(tmp_path, settings, problem):
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump({"watermark": settings}))
    with pytest.raises(config.ConfigError, match=f"tile_points: .*{problem}"):
        config.load_config(path)
