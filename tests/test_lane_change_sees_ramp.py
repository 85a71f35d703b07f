"""`driver.lane_change_sees_ramp`: mainline drivers moving right keep clear of the ramp vehicle
in the merge zone (off by default: the paper's drivers move in beside it)."""

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig
from marlmerge.evaluation.registry import policy_for_evaluation
from marlmerge.evaluation.rollout import rollout_first_egos
from marlmerge.sim import EGO, OUTCOME_COLLISION
from marlmerge.sim.layout import VI_LANE
from tests.scenes import scene

KEEN = {"driver.lane_change_threshold_mps2": 0.0}  # the keep-right bias alone moves a driver right


def _lane_after(ego_x_m: float, left_x_m: float, sees: bool, seconds: float = 1.0) -> int:
    """The lane of a left-lane driver at `left_x_m` (25 m/s, as the ego) after `seconds` of
    the ego holding its speed at `ego_x_m` on the ramp."""
    core = scene((ego_x_m, 25.0), left=[(left_x_m, 25.0)], overrides=KEEN | {
        "driver.lane_change_sees_ramp": sees})  # fmt: skip
    slot = int(np.flatnonzero(core.vi[0, VI_LANE, 1:] == 1)[0]) + 1
    assert slot != EGO
    for _ in range(int(round(seconds / core.cfg.sim.dt_s))):
        core.step(np.zeros(1))
    return int(core.vi[0, VI_LANE, slot])


@pytest.mark.parametrize("offset_m", [-3.0, 0.0, 4.0])
def test_a_driver_does_not_move_in_beside_a_ramp_vehicle_in_the_merge_zone(offset_m):
    x_e = ScenarioConfig().road.x_zone_start_m + 20.0
    assert _lane_after(x_e, x_e + offset_m, sees=False) == 0  # the paper's drivers move right
    assert _lane_after(x_e, x_e + offset_m, sees=True) == 1


def test_a_driver_well_clear_of_the_ramp_vehicle_or_before_the_zone_still_moves_right():
    cfg = ScenarioConfig()
    x_e = cfg.road.x_zone_start_m + 20.0
    assert _lane_after(x_e, x_e + 60.0, sees=True) == 0  # far ahead of it
    assert _lane_after(x_e, x_e - 60.0, sees=True) == 0  # far behind it
    x_ramp = cfg.road.x_zone_start_m - 60.0  # the ego still on its ramp, before the zone
    assert _lane_after(x_ramp, x_ramp, sees=True, seconds=0.4) == 0


def test_the_option_removes_most_collisions_with_drivers_moving_in():
    """Roads where gap acceptance's ego was hit at the join by a driver moving in beside it (a
    search of 100,000 moderate neutral roads; `docs/stress.md`): with the option on, those
    drivers stay in their lane."""
    keys = (5863, 7199, 55843, 70593, 71686)
    base = ScenarioConfig().replace(**{
        "traffic.flow_vph_per_lane": 1200.0, "driver.mix_cooperative": 0.0,
        "driver.mix_neutral": 1.0, "driver.mix_adversarial": 0.0, "name": "grid_moderate_neutral",
    })  # fmt: skip
    seeds = [np.random.SeedSequence(0, spawn_key=(3, 0, k)) for k in keys]
    hit = {}
    for sees in (False, True):
        policy, cfg = policy_for_evaluation(
            "gap", base.replace(**{"driver.lane_change_sees_ramp": sees})
        )
        rec, _ = rollout_first_egos(policy, cfg, len(keys), 0, len(keys), road_seeds=seeds)
        hit[sees] = int(np.count_nonzero(rec["outcome"] == OUTCOME_COLLISION))
    assert hit == {False: len(keys), True: 0}
