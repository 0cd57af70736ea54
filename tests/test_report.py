"""The evaluation report's rate-distortion section, from synthetic trial rows."""

import numpy as np

from pipeline import report


def _rows():
    rows = []
    for method, displacement, code, gain in [("paper", "xyz", "repetition", 1.0),
                                              ("robust-xyz", "xyz", "repetition", 1.5),
                                              ("robust", "normal", "convolutional", 3.0)]:
        for beta in (0.00115, 0.002, 0.0035):
            surface = 0.135 * beta * (np.sqrt(3) if displacement == "normal" else 1.0)
            for seed in range(4):
                wrong = seed < round(4 * max(0.0, 1 - gain * surface / 0.0004))
                rows.append({"experiment": "rate-distortion", "model": "m", "attack": "noise:1%",
                             "method": method, "displacement": displacement, "code": code, "beta": beta,
                             "seed": seed, "ber": 0.1 * wrong, "message_error": wrong, "bit_errors": 3 * wrong,
                             "mrms_rel_diag": surface, "rmse_rel_diag": 0.23 * beta,
                             "hausdorff_rel_diag": 0.001, "surface_rmse_rel_diag": surface,
                             "n_clusters": 5, "chip_rate": 10})
    return rows


def test_values_at_the_papers_distance_are_read_off_each_curve():
    curves = report.rate_distortion_curves(_rows())
    by = curves[("m", "noise:1%")]
    px, _, pmer, _, _ = by["paper embedding, paper detector"]
    x0 = float(np.median(px))
    assert x0 == np.float64(0.135 * 0.002)
    x, _, mer, n, _ = by["normal, convolutional, robust detector"]
    assert list(n) == [4, 4, 4]
    assert report._at((x, mer), x0) == 0 < report._at((px, pmer), x0) == 0.25
    assert np.isnan(report._at((x, mer), 10 * x0))          # outside the curve: no extrapolation


def test_the_report_writes_one_plot_per_model_and_flags_a_worse_curve(tmp_path):
    rows = _rows()
    summary = report.write_report(tmp_path, rows, [], 1e-6, 1.0).read_text()
    assert "## Rate-distortion" in summary and "paper's: nowhere." in summary
    assert (tmp_path / "rate_distortion_m.png").stat().st_size > 5000
    for r in rows:   # make the robust detector lose at every distortion
        if r["method"] == "robust-xyz":
            r["message_error"] = True
    summary = report.write_report(tmp_path, rows, [], 1e-6, 1.0).read_text()
    assert "m, noise:1%, paper embedding, robust detector: 1.00 against" in summary
