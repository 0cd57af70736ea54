"""GLB copies issued by a catalogue run, leaked through glTF Transform and trimesh, attributed by `pointmark scan`.

Small settings (the helmet, two recipients, two clusters, three leaks: a GLB
re-packed, a GLB re-encoded lossily, a conversion to another format; the copies
embedded in this process, the scan run through the command line's ``main``
here); the full table of every tool on the helmet and the owl scan is
``bench/gltf.py``.
"""

import importlib.util

import pytest

from tests.conftest import ROOT

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("node_tools")]   # fails under CI=true without them


def _bench():
    spec = importlib.util.spec_from_file_location("bench_gltf", ROOT / "bench" / "gltf.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_leaks_through_the_tools_are_attributed(shared_data, tmp_path):
    """Optimize, Draco at 14 bits and conversion to OBJ (bench/gltf.py leaks through every tool)."""
    bench = _bench()
    bench.RECIPIENTS[:] = ["alice", "bob"]
    assets = {"helmet": shared_data / "gltf" / "DamagedHelmet.glb"}
    attacks = {k: bench.ATTACKS[k] for k in ("optimize", "draco14", "obj")}
    cfg = bench.build(tmp_path, assets, {"n_clusters": 2, "cluster_size": 2500}, serial=True)
    rows = bench.scan(tmp_path, cfg, bench.leak(tmp_path, assets, attacks), in_process=True)
    assert len(rows) == len(attacks)
    assert {r["recipient"] for r in rows} == {"alice", "bob"}
    for r in rows:
        assert r["right"] and r["score"] >= r["threshold"], r
