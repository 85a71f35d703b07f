"""The stress-test space: points become the scenarios `[sample]` would draw, presets reproduce
them, and the third and fourth held-out sets are their seeds' draws, not choices."""

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig, load_scenario
from marlmerge.config.presets import preset_dir
from marlmerge.evaluation.space import (
    HELDOUT3_SEED,
    SPACE,
    from_unit,
    heldout_points,
    latin_hypercube,
    point_preset,
    scenario_at,
    unit,
    write_heldout3,
    write_heldout_set,
    write_preset,
)


def test_the_heldout3_files_are_the_seeds_draw(tmp_path):
    drawn = write_heldout3(tmp_path)
    assert len(drawn) == 12
    for path in drawn:
        committed = preset_dir("envs") / path.name
        assert load_scenario(committed) == load_scenario(path), path.name


@pytest.mark.parametrize("prefix", [f"heldout{k}" for k in range(4, 18)])
def test_the_later_heldout_files_are_their_seeds_draw_and_differ_from_heldout3(tmp_path, prefix):
    drawn = write_heldout_set(tmp_path, prefix)
    assert len(drawn) == 12
    for path in drawn:
        committed = preset_dir("envs") / path.name
        assert load_scenario(committed) == load_scenario(path), path.name
        other = load_scenario(preset_dir("envs") / path.name.replace(prefix, "heldout3"))
        assert load_scenario(path).road != other.road


def test_a_point_is_what_sample_draws_there():
    rng = np.random.default_rng(4)
    for _ in range(5):
        point = from_unit(rng.uniform(size=len(SPACE)))
        cfg = scenario_at(ScenarioConfig(), point)
        assert not cfg.sample.active
        assert cfg.traffic.flow_vph_per_lane == pytest.approx(point["flow_vph_per_lane"])
        assert cfg.road.merge_zone_m == pytest.approx(point["merge_zone_m"])
        assert np.mean(cfg.driver.desired_speed_factor) == pytest.approx(
            point["desired_speed_factor"]
        )
        assert np.allclose(unit(point), unit(from_unit(unit(point))))


def test_a_point_preset_reproduces_its_condition(tmp_path):
    point = heldout_points(1, seed=HELDOUT3_SEED + 1)[0]
    fixed = write_preset(tmp_path / "p.toml", point_preset(ScenarioConfig(), point, "p"))
    assert load_scenario(fixed) == scenario_at(ScenarioConfig(), point).replace(name="p")


def test_the_latin_hypercube_fills_every_stratum():
    u = latin_hypercube(50, len(SPACE), np.random.default_rng(0))
    assert u.shape == (50, len(SPACE)) and (0 <= u).all() and (u < 1).all()
    for d in range(len(SPACE)):
        assert sorted(np.floor(u[:, d] * 50).astype(int)) == list(range(50))


def test_every_corner_of_the_space_is_a_valid_scenario():
    for corner in (np.zeros(len(SPACE)), np.ones(len(SPACE))):
        scenario_at(ScenarioConfig(), from_unit(corner))  # raises if a corner were invalid
