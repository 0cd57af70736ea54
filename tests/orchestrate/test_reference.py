"""One function builds a reference and one loads it; both verify digests."""

import numpy as np
import pytest

from pipeline.config import WatermarkParams
from pipeline.io.basis_store import BasisStore
from pipeline.orchestrate.reference import build_reference, load_reference
from pipeline.watermark import ReferenceMismatch, compute_reference
from tests.conftest import sphere_patch

PARAMS = WatermarkParams(n_bits=8, chip_rate=4, n_clusters=2, cluster_size=600)


@pytest.fixture(scope="module")
def points():
    return sphere_patch(2500, rng=11)


def test_a_built_reference_is_kept_and_loads_back_verified(tmp_path, points):
    store = BasisStore(tmp_path / "bases")
    built = build_reference(points, PARAMS, store, "k", detection=True)
    assert built.digests() == compute_reference(points, PARAMS).digests()
    loaded = load_reference(points, PARAMS, store, "k", built.digests(), detection=True)
    assert loaded.digests() == built.digests()
    assert all(np.array_equal(a, b) for a, b in zip(loaded.grams, built.grams))
    assert np.array_equal(loaded.spacing, built.spacing)
    # building again over the kept entry checks it against what is rebuilt
    assert build_reference(points, PARAMS, store, "k").digests() == built.digests()


def test_loading_refuses_a_reference_other_than_the_recorded_one(tmp_path, points):
    store = BasisStore(tmp_path / "bases")
    recorded = build_reference(points, PARAMS, store, "k").digests()
    radius, basis, normals = store.load_cluster("k", 1)
    store.save_cluster("k", 1, radius, -basis, normals)          # another basis under cluster 1
    with pytest.raises(ReferenceMismatch, match="cluster 1 spectral basis digest"):
        load_reference(points, PARAMS, store, "k", recorded)
    with pytest.raises(ReferenceMismatch, match="rebuilt from the original"):
        build_reference(points, PARAMS, store, "k")


def test_a_revised_original_is_refused_against_the_old_record(tmp_path, points):
    store = BasisStore(tmp_path / "bases")
    recorded = build_reference(points, PARAMS, store, "k").digests()
    moved = points.copy()
    moved[build_reference(points, PARAMS).specs[0].members[7]] += 0.2     # out of its neighbourhood
    assert build_reference(moved, PARAMS).digests() != recorded
    with pytest.raises(ReferenceMismatch):
        load_reference(moved, PARAMS, BasisStore(tmp_path / "empty"), "k", recorded)
