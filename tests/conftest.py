"""Shared fixtures: the real scans of ../shared/data, a secret, small synthetic shapes."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

# One BLAS/OpenMP thread per test process, as every entry point has (pipeline/threads.py), before
# NumPy, OpenBLAS or pykdtree's OpenMP loads.  Two test processes share two cores; a thread per core
# each oversubscribes them.  A variable already set wins; subprocess tests set their own.
from pipeline.threads import PINNED

for _name, _value in PINNED.items():
    os.environ.setdefault(_name, _value)

import numpy as np  # noqa: E402
import pytest

ROOT = Path(__file__).resolve().parents[1]


# The files whose tests take longest, longest first (`--durations`, 2026-12-02).  `make test` hands
# whole files to two processes in collection order (`--dist loadfile --no-loadscope-reorder`): these
# start first, so that neither process is left running one of them alone at the end.
HEAVY_FIRST = ("test_scan.py", "test_features.py", "test_robustness.py", "orchestrate/test_scan_hostile.py",
               "test_robustness_part.py", "orchestrate/test_scan_verdicts.py", "test_bunny.py",
               "orchestrate/test_run.py", "test_cli.py", "orchestrate/test_detect.py")


def pytest_collection_modifyitems(items):
    rank = {f"tests/{name}": i for i, name in enumerate(HEAVY_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(HEAVY_FIRST)))   # stable


def data_dir():
    """The real-scan folder: $POINTMARK_TEST_DATA or ../shared/data."""
    return Path(os.environ.get("POINTMARK_TEST_DATA", ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data():
    path = data_dir()
    if not path.is_dir():
        message = f"real scans not found at {path} (set POINTMARK_TEST_DATA)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + "; CI must have them")
        pytest.skip(message)
    return path


@pytest.fixture(scope="session")
def node_tools():
    """node, glTF Transform's CLI and the Khronos validator (``make setup``); fails under CI=true without them."""
    from pipeline.io import gltf_tools

    if not gltf_tools.tools_available():
        message = (f"node, gltf-transform and gltf-validator not found (node_modules at {gltf_tools.node_modules()}; "
                   "run make setup)")
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + "; CI must have them")
        pytest.skip(message)


@pytest.fixture(scope="session")
def bunny_path(shared_data):
    return shared_data / "models" / "bunny_zipper_faceref_34834.ply"


@pytest.fixture()
def secret_env(monkeypatch):
    monkeypatch.setenv("POINTMARK_SECRET", "test-secret-not-for-production")
    return "test-secret-not-for-production"


def sphere_patch(n=3000, rng=0):
    """(n, 3) points on a bumpy sphere, seeded: a small surface without symmetry."""
    rng = np.random.default_rng(rng)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    r = 1.0 + 0.15 * np.sin(3 * v[:, 0]) * np.cos(2 * v[:, 1]) + 0.1 * v[:, 2] ** 2
    return v * r[:, None] * np.array([1.0, 0.8, 0.6])


# Every key of the watermark section, written out: a shared world's copies never depend on the schema's
# defaults (which may change).  The small bookkeeping worlds of tests/orchestrate use these.
SMALL_WATERMARK = {
    "n_bits": 16, "chip_rate": 10, "beta": 0.002, "valence": 12, "n_clusters": 2, "cluster_size": 1200,
    "seeds": None, "on_touch": "skip", "cover": False, "chip_layout": "consecutive", "first_coefficient": 0,
    "crc_bits": 0, "displacement": "xyz", "amplitude": "model", "max_displacement": None, "tile_points": None,
    "code": "repetition", "band_noise": None,
}

# The registration's effort in those bookkeeping worlds, about a tenth of the default (a sixth of the
# refined poses): their suspects are whole
# copies, or no copy at all, and what is under test is the scan's and the ledger's bookkeeping, not the
# search for a part's pose (tests/test_features.py and tests/test_robustness_part.py test that at the
# default effort).  An innocent candidate's check costs about half as much.
SMALL_DETECTION = {"ransac_iterations": 2000, "search_rotations": 100, "search_poses": 8}


@pytest.fixture(scope="session", autouse=True)
def shared_cluster():
    """One LocalCluster for the session, started as ``start_client`` starts one (spawned workers).

    Its address is Dask's ``scheduler-address`` here and ``DASK_SCHEDULER_ADDRESS`` for the
    subprocesses, so every run, scan and evaluation with no ``dask.address`` uses it instead of
    starting a cluster of its own (a few seconds each).  Its workers work in the folder pytest
    started in, so runs and scans in other folders (the Snakefile's) check that tasks are given
    absolute paths.  Tests of the LocalCluster itself, and of runs killed mid-way (whose tasks must
    die with them), take :func:`own_cluster`.
    """
    import dask

    from pipeline import config
    from pipeline.orchestrate.run import start_client

    # two workers, or one per pytest-xdist process (``make test`` runs two side by side)
    workers = 1 if os.environ.get("PYTEST_XDIST_WORKER") else 2
    before = dict(os.environ)
    client, cluster = start_client(config.load_config(None, [f"dask.n_workers={workers}"]))
    # a nanny sets its workers' pinned environment (PYTHONHASHSEED, thread counts) in the process that
    # starts it: the tests and their subprocesses keep this process's own, or the determinism tests
    # across processes would all run under one hash seed
    os.environ.clear()
    os.environ.update(before, DASK_SCHEDULER_ADDRESS=cluster.scheduler_address)
    try:
        with dask.config.set({"scheduler-address": cluster.scheduler_address}):
            yield cluster
        # the workers of a cluster that outlived every test never held a secret (a respawned one
        # would take the environment of its moment)
        seen = client.run(lambda: sorted(k for k in __import__("os").environ if "SECRET" in k))
        assert all(found == [] for found in seen.values()), seen
    finally:
        client.close()
        os.environ.clear()
        os.environ.update(before)
        cluster.close()


@pytest.fixture()
def own_cluster(monkeypatch):
    """No shared scheduler: runs without ``dask.address`` start their own LocalCluster."""
    import dask

    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    with dask.config.set({"scheduler-address": None}):
        yield


class ScanIndexes:
    """The scan's feature index per catalogue version (``scan.out/state/index-*.npz``, with its ``.ivf``
    part for a large catalogue), kept for the session.

    A scan builds the index of its catalogue into each new ``scan.out``; the small worlds of the
    scan tests are the same catalogue bytes every time, so a later scan into a new ``scan.out`` is
    given the index an earlier scan built (:meth:`seed`, then :meth:`keep` after the scan).  A
    catalogue not seen before, or an index format or name that changed, is simply built by the scan.
    """

    def __init__(self, folder):
        self.folder = Path(folder)

    def seed(self, out):
        out = Path(out)
        for index in self.folder.glob("index-*"):
            target = out / "state" / index.name
            if not target.exists():
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(index, target)

    def keep(self, out):
        for index in (Path(out) / "state").glob("index-*"):
            if not (self.folder / index.name).exists():
                shutil.copyfile(index, self.folder / index.name)


@pytest.fixture(scope="session")
def scan_indexes(tmp_path_factory):
    return ScanIndexes(tmp_path_factory.mktemp("scan-indexes"))


@pytest.fixture(scope="session")
def shared_bases(tmp_path_factory):
    """``evaluate.prepare_bases`` computed once per run for every test process (the handle).

    The store lies where both of pytest-xdist's processes see it, and each entry's handle is
    kept beside it (keyed by the model file's sha256 and the basis parameters), so a model's
    bases at the default configuration, wanted by several files, are computed by the first
    and loaded, verified against the handle's digests, by the rest.
    """
    import json

    from pipeline.io.basis_store import BasisStore, write_file
    from pipeline.io.pointcloud import sha256_file
    from pipeline.orchestrate import evaluate

    root = tmp_path_factory.getbasetemp()
    store = (root.parent if os.environ.get("PYTEST_XDIST_WORKER") else root) / "shared-bases"

    def get(path, params):
        basis_params = evaluate._basis_params(params, params.n_coefficients)
        name = f"{BasisStore(store).key(sha256_file(path), basis_params)}.handle.json"
        if (store / name).is_file():
            return tuple(json.loads((store / name).read_text()))
        handle = evaluate.prepare_bases(path, basis_params, store)
        write_file(store, name, json.dumps(list(handle)).encode())
        return handle

    return get
