from __future__ import annotations

import copy
import pickle
from pathlib import Path

import pytest

from pothole_detector.errors import ConfigError
from pothole_detector.params import PARAMETERS, Config, default_yaml, load_yaml

ROOT = Path(__file__).resolve().parents[1]


def test_config_yaml_matches_the_table():
    assert (ROOT / "config" / "pothole_detector.yaml").read_text() == default_yaml()


def test_yaml_round_trip_gives_the_defaults():
    values = load_yaml(ROOT / "config" / "pothole_detector.yaml")
    assert Config(values) == Config()
    assert set(values) == {p.name for p in PARAMETERS}


@pytest.mark.parametrize("name, value, message", [
    ("sgm_block_size", 0, ">= 1"),
    ("sgm_block_size", 2.5, "integer"),
    ("delta_pd_px", "3", "number"),
    ("delta_pd_px", float("nan"), "NaN"),
    ("median_filter", 1, "true or false"),
    ("road_model", "cubic", "one of"),
    ("no_such_parameter", 1, "unknown parameter"),
])
def test_invalid_values_are_refused_with_a_reason(name, value, message):
    with pytest.raises(ConfigError, match=message):
        Config({name: value})


def test_penalties_must_be_ordered():
    with pytest.raises(ConfigError, match="sgm_p2 must be larger"):
        Config({"sgm_p1": 40, "sgm_p2": 20})


def test_replace_validates_and_keeps_the_original():
    config = Config()
    changed = config.replace(delta_pd_px=3)
    assert changed.delta_pd_px == 3.0 and config.delta_pd_px == 2.36
    with pytest.raises(ConfigError):
        config.replace(slic_iterations=0)


def test_a_config_pickles_and_copies_as_itself():
    for config in (Config({"delta_pd_px": 3, "read_processes": 2}), Config(group="node")):
        for copied in (pickle.loads(pickle.dumps(config)), copy.deepcopy(config)):
            assert copied == config and copied.as_dict() == config.as_dict()
    assert pickle.loads(pickle.dumps(Config({"delta_pd_px": 3}))).delta_pd_px == 3.0


def test_flat_yaml_and_missing_file(tmp_path):
    path = tmp_path / "flat.yaml"
    path.write_text("delta_pd_px: 3.0\n")
    assert load_yaml(path) == {"delta_pd_px": 3.0}
    with pytest.raises(ConfigError, match="does not exist"):
        load_yaml(tmp_path / "missing.yaml")
