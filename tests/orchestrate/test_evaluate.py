"""pointmark evaluate on the small config: Parquet rows, plots, summary."""

import pyarrow.parquet as pq
import pytest

from pipeline import config
from pipeline.orchestrate.evaluate import run_evaluation
from tests.conftest import ROOT

pytestmark = pytest.mark.slow


def test_small_evaluation_writes_results_plots_and_summary(shared_data, tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    cfg = config.load_config(ROOT / "configs" / "evaluate-small.yaml", [f"evaluate.out={tmp_path}"])
    for exp in cfg["evaluate"]["experiments"]:
        exp["models"] = [str(shared_data / "models" / "bunny_res3_1889.ply")]
    assert run_evaluation(cfg, b"evaluation-test-secret") == 0
    rows = pq.read_table(tmp_path / "results.parquet").to_pylist()
    assert len(rows) == 2 * (4 + 2 * 2)
    assert {"model", "attack", "method", "seed", "ber", "detected", "p_value", "rmse_rel_diag",
            "seconds_detect"} <= set(rows[0])
    clean = [r for r in rows if r["attack"] == "none"]
    assert all(r["bit_errors"] == 0 and r["detected"] for r in clean)
    fp = pq.read_table(tmp_path / "false_positives.parquet").to_pylist()
    wrong = [r["p_value"] for r in fp if r["key"] >= 0]
    assert len(wrong) == 400 and sum(p < 1e-6 for p in wrong) == 0
    assert 0.02 < sum(p < 0.1 for p in wrong) / len(wrong) < 0.2       # calibrated, roughly
    for name in ("attacks.png", "noise_curves.png", "false_positives.png", "summary.md"):
        assert (tmp_path / name).stat().st_size > 1000
    text = (tmp_path / "summary.md").read_text()
    assert "## False positives" in text and "| BER, paper | BER, robust |" in text
    assert "surface RMS" in text
    # the paper's method embeds in xyz, the robust one along the normals
    assert {(r["method"], r["displacement"]) for r in rows} == {("paper", "xyz"), ("robust", "normal")}
