import numpy as np
import pytest

from pipeline.kernels import distortion


@pytest.fixture(scope="module")
def sheet():
    """A gently curved 60 x 60 sheet of points (unit spacing) with scanner-like roughness."""
    u, v = np.meshgrid(np.arange(60.0), np.arange(60.0))
    rough = np.random.default_rng(5).normal(0, 0.005, u.size)
    return np.column_stack([u.ravel(), v.ravel(), 0.002 * (u.ravel() - 30) ** 2 + rough])


def test_an_unchanged_copy_in_any_order_is_not_distorted(sheet):
    shuffled = sheet[np.random.default_rng(0).permutation(len(sheet))]
    d = distortion.surface_distortion(sheet, shuffled)
    assert d["mrms"] == pytest.approx(0, abs=1e-12) and d["surface_hausdorff"] == pytest.approx(0, abs=1e-12)
    assert d["normal_deviation_deg"] < 1e-6 and d["msdm"] < 1e-9


def test_motion_along_the_surface_is_not_distance_to_it():
    u, v = np.meshgrid(np.arange(40.0), np.arange(40.0))
    plane = np.column_stack([u.ravel(), v.ravel(), np.zeros(u.size)])
    slid = plane + np.array([0.3, -0.2, 0.0])
    across = plane + np.array([0.0, 0.0, 0.01])
    assert distortion.surface_distortion(plane, slid)["mrms"] < 1e-12
    assert distortion.surface_distortion(plane, across)["mrms"] == pytest.approx(0.01, rel=1e-6)


def test_the_perceptual_measures_see_roughness_that_mrms_cannot(sheet):
    rng = np.random.default_rng(1)
    h = 0.02
    rough = sheet.copy()
    rough[:, 2] += rng.choice([-h, h], len(sheet))                     # point-to-point bumps
    smooth = sheet.copy()
    smooth[:, 2] += h * np.sin(sheet[:, 0] / 9.0) * np.sqrt(2)         # one slow wave, same RMS
    d_rough, d_smooth = (distortion.surface_distortion(sheet, x) for x in (rough, smooth))
    assert d_rough["mrms"] == pytest.approx(d_smooth["mrms"], rel=0.25)
    assert d_rough["msdm"] > 10 * d_smooth["msdm"]
    assert d_rough["normal_deviation_deg"] > 2 * d_smooth["normal_deviation_deg"]
    assert 0 <= d_smooth["msdm"] < d_rough["msdm"] <= 1


def test_local_planes_in_blocks_equal_one_pass(monkeypatch):
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(3000, 3)) * [1, 1, 0.05]
    whole = distortion.local_planes(pts, pts[:1000])
    monkeypatch.setattr(distortion, "_BLOCK", 77)
    blocks = distortion.local_planes(pts, pts[:1000])
    for a, b in zip(whole, blocks):
        assert np.array_equal(a, b)


def test_pooled_measures_of_one_cell_are_the_whole_and_of_four_cells_are_close():
    rng = np.random.default_rng(6)
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 80), np.linspace(0, 1, 80)), -1).reshape(-1, 2)
    sheet = np.column_stack([grid, 0.05 * np.sin(6 * grid[:, 0])])
    marked = sheet + rng.normal(0, 2e-3, sheet.shape)
    whole = distortion.surface_distortion(sheet, marked)
    one = distortion.pooled_distortion(sheet, marked, [np.arange(len(sheet))])
    assert one == pytest.approx(whole, rel=1e-12)
    quarters = [np.flatnonzero(((grid[:, 0] < 0.5) == a) & ((grid[:, 1] < 0.5) == b))
                for a in (True, False) for b in (True, False)]
    pooled = distortion.pooled_distortion(sheet, marked, quarters)
    for name in ("mrms", "surface_rms_forward", "normal_deviation_deg", "msdm"):
        assert pooled[name] == pytest.approx(whole[name], rel=0.1), name
    assert pooled["hausdorff"] == pytest.approx(whole["hausdorff"], rel=0.1)
