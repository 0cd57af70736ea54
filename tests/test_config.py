import json

import pytest

from pipeline import config
from tests.conftest import ROOT


def test_defaults_are_the_papers():
    p = config.watermark_params(config.load_config())
    assert (p.n_bits, p.chip_rate, p.beta, p.valence, p.n_clusters, p.cluster_size) == (32, 10, 0.002, 12, 5, 4000)


def test_schema_matches_the_parameter_dataclasses():
    wm, det = config.dataclass_keys()
    assert set(config.SCHEMA["properties"]["watermark"]["properties"]) == wm
    assert set(config.SCHEMA["properties"]["detection"]["properties"]) == det


def test_committed_schema_is_current():
    assert json.loads((ROOT / "configs" / "schema.json").read_text()) == json.loads(config.schema_json())


@pytest.mark.parametrize("name", sorted(p.name for p in (ROOT / "configs").glob("*.yaml")))
def test_shipped_configs_validate(name):
    config.load_config(ROOT / "configs" / name)


def test_unknown_key_is_rejected_with_its_path(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("watermark:\n  betta: 0.1\n")
    with pytest.raises(config.ConfigError, match=r"watermark: unknown key\(s\) betta"):
        config.load_config(f)


def test_bad_value_names_key_and_problem(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("watermark:\n  beta: -1\n")
    with pytest.raises(config.ConfigError, match=r"watermark\.beta: -1 is less than or equal to the minimum of 0"):
        config.load_config(f)


def test_set_uses_the_keys_own_names():
    cfg = config.load_config(overrides=["beta=0.004", "chip_rate=16", "detection.registration=paper"])
    assert cfg["watermark"]["beta"] == 0.004 and cfg["watermark"]["chip_rate"] == 16
    assert cfg["detection"]["registration"] == "paper"
    with pytest.raises(config.ConfigError, match="no such config key"):
        config.load_config(overrides=["nonsense=1"])


def test_a_secret_in_the_config_is_refused(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("key:\n  secret: hunter2\n")
    with pytest.raises(config.ConfigError, match="unknown key"):
        config.load_config(f)


def test_a_code_longer_than_the_chips_is_refused_before_any_work(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("watermark:\n  code: convolutional\n  chip_rate: 2\n")
    with pytest.raises(config.ConfigError, match="watermark.code: .*chip_rate to at least 3"):
        config.load_config(path)
    path.write_text("watermark:\n  code: convolutional\n  chip_rate: 3\n")
    assert config.load_config(path)["watermark"]["code"] == "convolutional"
