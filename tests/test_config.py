"""Strict preset loading and config validation."""

import re
from pathlib import Path

import pytest

from marlmerge.config import ScenarioConfig, from_dict, load_scenario, to_dict

ENVS = sorted((Path(__file__).parent.parent / "envs").glob("*.toml"))


def test_defaults_follow_the_paper():
    cfg = ScenarioConfig()
    assert cfg.road.lane_width_m == 3.75 and cfg.road.ramp_width_m == 3.5
    assert cfg.road.speed_limit_mps == pytest.approx(29.06, abs=0.01)
    assert cfg.sim.dt_s == 0.1 and cfg.sim.action_repeat == 4
    assert cfg.ego.accel_bounds_mps2 == (-4.5, 2.5)
    assert cfg.ego.sensing_range_m == 150.0


@pytest.mark.parametrize("path", ENVS, ids=[p.stem for p in ENVS])
def test_every_preset_loads(path):
    cfg = load_scenario(path)
    assert cfg.name == path.stem


TRAINERS = sorted((Path(__file__).parent.parent / "trainers").glob("*.toml"))


@pytest.mark.parametrize("path", TRAINERS, ids=[p.stem for p in TRAINERS])
def test_every_training_preset_loads_with_its_kind(path):
    from marlmerge.config.presets import load_cotrain_config, load_train_config

    kind = re.search(r'^kind = "(\w+)"', path.read_text(), re.M).group(1)
    cfg = (load_train_config if kind == "train" else load_cotrain_config)(path)
    assert cfg.name == path.stem


def test_unknown_top_level_key_is_named(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('name = "bad"\nflow = 3\n')
    with pytest.raises(ValueError, match="'flow'"):
        load_scenario(p)


def test_unknown_nested_key_is_named_with_its_path(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text("[traffic]\nflow_vph = 900\n")
    with pytest.raises(ValueError, match=r"traffic\.flow_vph"):
        load_scenario(p)


def test_wrong_type_is_named(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('[sim]\naction_repeat = "four"\n')
    with pytest.raises(ValueError, match=r"sim\.action_repeat"):
        load_scenario(p)


def test_cross_field_validation():
    with pytest.raises(ValueError, match="mix"):
        ScenarioConfig().replace(**{"driver.mix_cooperative": 0.9})
    with pytest.raises(ValueError, match="unknown config key 'traffic.nope'"):
        ScenarioConfig().replace(**{"traffic.nope": 1})


def test_round_trip_through_dicts():
    cfg = ScenarioConfig().replace(**{"traffic.flow_vph_per_lane": 700})
    assert from_dict(ScenarioConfig, to_dict(cfg)) == cfg


NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("road.speed_limit_mph", 0.0, "must be in [10, 100]"),
        ("road.speed_limit_mph", NAN, "must be finite"),
        ("sim.dt_s", INF, "must be finite"),
        ("ego.sensing_range_m", -1.0, "must be in (0, 1000]"),
        ("traffic.entry_speed_mps", (-3.0, 1.0), "must be in [0, 60]"),
        ("traffic.entry_speed_mps", (3.0, 2.0), "slowest entry speed"),
        ("road.lane_width_m", 0.0, "must be in [2.5, 5]"),
        ("vehicle.length_m", -5.0, "must be in [2, 20]"),
        ("driver.accel_mps2", 0.0, "must be in [0.1, 8]"),
        ("driver.comfort_brake_mps2", 0.0, "must be in [0.1, 12]"),
        ("driver.min_gap_m", 0.0, "must be in (0, 20]"),
        ("driver.delta", 0.0, "must be in [1, 10]"),
        ("driver.time_headway_s", (1.8, 1.0), "low <= high"),
        ("traffic.warmup_s", 1e5, "must be in [0, 600]"),
        ("reward.w_front", -1.0, "must be in [0, 10000]"),
        ("ego.start_speed_mps", (-1.0, 5.0), "must be in [0, 60]"),
        ("traffic.entrance_lane", "fastest", "must be one of 'drawn', 'best'"),
    ],
)
def test_bad_scenario_numbers_are_refused_naming_key_and_value(key, value, message):
    with pytest.raises(ValueError, match=re.escape(key) + ".*" + re.escape(message)) as err:
        ScenarioConfig().replace(**{key: value})
    shown = str(value[0] if isinstance(value, tuple) else value)
    assert shown in str(err.value)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("lr", -1.0),
        ("sigma_start", -1.0),
        ("batch_size", 0),
        ("hidden", 0),
        ("checkpoint_every_sim_steps", 0),
        ("replay_capacity", 0),
        ("eval_worlds", 0),
        ("gamma", NAN),
    ],
)
def test_bad_training_numbers_are_refused_before_any_work(key, value, capsys):
    from marlmerge.cli import main

    assert main(["train", "quick", "--set", f"{key}={value}", "--out", "/nonexistent/x"]) == 2
    err = capsys.readouterr().err
    assert f"--set {key}={value} (on quick.toml): {key} must be" in err and str(value) in err


def test_a_toml_syntax_error_names_the_file(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("[traffic]\nflow_vph_per_lane = \n")
    with pytest.raises(ValueError, match=r"broken\.toml: not valid TOML.*line 2"):
        load_scenario(p)


@pytest.mark.parametrize("argv", [["evaluate", "x", "--episodes", "0"], ["grid", "--worlds", "0"]])
def test_bad_cli_numbers_are_refused_naming_the_option(argv, capsys):
    from marlmerge.cli import main

    with pytest.raises(SystemExit):
        main(argv)
    assert f"argument {argv[-2]}: must be >= 1, got 0" in capsys.readouterr().err
