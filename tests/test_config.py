"""Strict preset loading and config validation."""

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
