"""`marlmerge simulate`'s rollout: ramp vehicles driven by a rule through scripted traffic."""

import json

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig
from marlmerge.evaluation.simulate import EGO_RULES, ego_rule, simulate


def test_a_drive_writes_its_episodes_and_a_frame(tmp_path):
    seen = []
    result = simulate("default", "idm", 2, 5, tmp_path, on_episode=seen.append)
    assert seen == result.episodes and [r["episode"] for r in seen] == [0, 1]
    assert {r["outcome"] for r in seen} <= {"success", "collision", "truncated"}
    saved = json.loads((tmp_path / "episodes.json").read_text())
    assert saved["summary"]["episodes"] == 2
    rates = sum(saved["summary"][f"{k}_rate"] for k in ("success", "collision", "truncated"))
    assert rates == pytest.approx(1.0)
    for record in seen:  # the episode's reward is the sum of its named terms
        terms = {k: v for k, v in record.items() if k not in ("episode", "outcome", "time_s")}
        assert record["reward"] == pytest.approx(sum(v for k, v in terms.items() if k != "reward"))
    assert result.frame is None or result.frame.exists()


def test_the_same_seed_drives_the_same_episodes(tmp_path):
    a = simulate("dense", "random", 2, 3, tmp_path / "a").episodes
    b = simulate("dense", "random", 2, 3, tmp_path / "b").episodes
    assert a == b


def test_ego_rules_act_within_the_bounds_and_a_bad_name_is_refused():
    cfg = ScenarioConfig()
    lo, hi = cfg.ego.accel_bounds_mps2
    obs = np.zeros(7, dtype=np.float32)
    for rule in EGO_RULES:
        act = np.asarray(ego_rule(rule, cfg, np.random.default_rng(0))(obs))
        assert act.shape == (1,) and lo <= float(act[0]) <= hi
    with pytest.raises(ValueError, match="'fly'"):
        ego_rule("fly", cfg, np.random.default_rng(0))
