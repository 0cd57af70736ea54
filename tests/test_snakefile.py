"""The Snakefile: lint, dry run and a small real run of the CLI through snakemake."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pyarrow.dataset as ds
import pytest
import yaml

from tests.conftest import ROOT
from tests.orchestrate.test_run import make_catalogue

pytestmark = pytest.mark.slow


@pytest.fixture()
def workdir(tmp_path):
    shutil.copy(ROOT / "Snakefile", tmp_path)
    shutil.copytree(ROOT / "configs", tmp_path / "configs")
    shutil.copytree(ROOT / "envs", tmp_path / "envs")
    make_catalogue(tmp_path / "assets", n_assets=3)
    cfg = yaml.safe_load((ROOT / "configs" / "workflow.yaml").read_text())
    cfg["workflow"].update(assets="assets", shards=2)
    cfg["watermark"].update(n_bits=16, n_clusters=2, cluster_size=1200)
    (tmp_path / "configs" / "workflow.yaml").write_text(yaml.safe_dump(cfg))
    return tmp_path


@pytest.fixture()
def fresh_clone(tmp_path):
    """The tracked tree (``git ls-files``) copied as a fresh clone has it: no catalog/demo, no out/."""
    try:
        listed = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    for name in filter(None, listed.decode().split("\0")):
        src = ROOT / name
        if src.is_file() and not name.startswith(("catalog/demo/", "out/")):
            (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, tmp_path / name)
    return tmp_path


def _snakemake(workdir, *args, secret="snakemake-test-secret"):
    bin_dir = Path(sys.executable).parent
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}", PYTHONPATH=str(ROOT))
    env.pop("POINTMARK_SECRET", None)
    if secret:
        env["POINTMARK_SECRET"] = secret
    return subprocess.run([str(bin_dir / "snakemake"), *args], cwd=workdir, env=env,
                          capture_output=True, text=True, timeout=600)


def test_lint_is_clean(workdir):
    res = _snakemake(workdir, "--lint")
    assert res.returncode == 0, res.stdout + res.stderr
    assert "Lints for" not in res.stdout + res.stderr


def test_dry_run_plans_catalogue_and_shards(workdir):
    res = _snakemake(workdir, "-n")
    assert res.returncode == 0, res.stderr
    assert "catalogue" in res.stdout and "embed" in res.stdout


def test_a_fresh_clone_dry_run_plans_the_demo_assets(fresh_clone):
    assert not (fresh_clone / "catalog" / "demo").exists()
    res = _snakemake(fresh_clone, "-n")
    assert res.returncode == 0, res.stdout + res.stderr
    for rule in ("demo_assets", "catalogue", "embed"):
        assert rule in res.stdout
    assert not (fresh_clone / "catalog" / "demo").exists() and not (fresh_clone / "out").exists()


@pytest.mark.parametrize("cause", ["assets folder missing", "no secret"])
def test_what_to_do_first_in_one_line_before_any_job(workdir, cause):
    args, secret = ("--cores", "1"), "snakemake-test-secret"
    if cause == "assets folder missing":
        shutil.rmtree(workdir / "assets")
        args, needle = ("-n",), "workflow.assets 'assets' is not a folder"
    else:
        secret, needle = None, "export POINTMARK_SECRET"
    res = _snakemake(workdir, *args, secret=secret)
    assert res.returncode == 1
    assert res.stderr.strip().splitlines()[-1].startswith("configs/workflow.yaml: ")
    assert needle in res.stderr.strip().splitlines()[-1]
    assert "Traceback" not in res.stderr and not (workdir / "out").exists()


def test_config_is_validated_against_the_schema(workdir):
    cfg = workdir / "configs" / "workflow.yaml"
    cfg.write_text(cfg.read_text().replace("shards: 2", "shards: 2\n  bogus: 1"))
    res = _snakemake(workdir, "-n")
    assert res.returncode != 0 and "bogus" in res.stdout + res.stderr


def test_a_small_real_run_then_a_scan(workdir):
    res = _snakemake(workdir, "--cores", "2")
    assert res.returncode == 0, res.stdout + res.stderr
    leak = workdir / "out" / "workflow" / "suspects"
    leak.mkdir(parents=True)
    shutil.copy(workdir / "out" / "workflow" / "marked" / "market-b" / "asset-1.pcd", leak / "found.pcd")
    res = _snakemake(workdir, "--cores", "2", "scan")
    assert res.returncode == 0, res.stdout + res.stderr
    found = ds.dataset(str(workdir / "out" / "workflow" / "scan" / "results"), format="parquet").to_table().to_pylist()
    assert [(r["candidate_asset"], r["recipient"], r["verdict"]) for r in found] == [("asset-1", "market-b", "match")]
    table = ds.dataset(str(workdir / "out" / "workflow" / "manifests" / "copies"), format="parquet").to_table()
    assert table.num_rows == 6 and set(table["status"].to_pylist()) == {"ok"}
    assert len(list((workdir / "out" / "workflow" / "marked").rglob("*.*"))) == 6
    assert (workdir / "out" / "workflow" / "stamps" / "embed-1-of-2.done").exists()
