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


def _fingerprint_rows():
    rows = []
    for beta in (0.0004, 0.0008, 0.0016):
        for seed in range(8):
            score = 20000 * beta - 2.0 + 0.1 * seed          # 6.0 to 30.7: a miss at the lowest beta
            rows.append({"experiment": "fp", "model": "m", "case": "single", "colluders": 1, "attack": "noise:1%",
                         "seed": seed, "beta": beta, "mrms_rel_diag": 0.3 * beta, "n_recipients": 1000,
                         "epsilon": 1e-6, "threshold": 6.44, "n_poses": 1, "min_colluder_score": score,
                         "accused_colluders": int(score >= 6.44), "accused_innocents": 0,
                         "max_innocent_score": 4.0, "innocent_checks": 999, "innocents_over_2": 20,
                         "innocents_over_3": 1, "innocents_over_4": 0})
    return rows


def test_fingerprint_curves_read_the_named_share_and_margin_at_the_papers_distance_and_chos(tmp_path):
    fp = _fingerprint_rows()
    paper = [{**r, "experiment": report.PAPER_DISTANCE, "model": "m", "mrms_rel_diag": 0.3 * 0.0008}
             for r in _rows()[:2]]
    x, named, margin, n, beta = report.fingerprint_curves(fp)["m"]["single, noise:1%"]
    assert list(n) == [8, 8, 8] and list(beta) == [0.0004, 0.0008, 0.0016]
    assert named[0] == 3 / 8 and named[1] == named[2] == 1.0        # scores 6.0-6.7 at the lowest beta
    assert np.isclose(margin[1], 20000 * 0.0008 - 2.0 + 0.35 - 6.44)
    summary = report.write_report(tmp_path, paper, [], 1e-6, 1.0, fp).read_text()
    assert "## Fingerprints against distance" in summary
    assert f"| m | single, noise:1% | 8 | 1.00, {margin[1]:+.2f} | 0.38, {margin[0]:+.2f} |" in summary
    assert (tmp_path / "fingerprint_rate_distortion_m.png").stat().st_size > 5000
    assert "| m | single | noise:1% | 0.000400 | 8 | 1000 | 6.44 | 3/8 |" in summary
