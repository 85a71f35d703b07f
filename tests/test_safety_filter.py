"""The safety filter: it stops a join into an occupied gap that collides without it, leaves a
free join alone, and counts what it did."""

import numpy as np
import pytest
from scenes import scene

from marlmerge.config import ScenarioConfig
from marlmerge.sim import EGO, OUTCOME_COLLISION, OUTCOME_SUCCESS, RAMP
from marlmerge.sim.safety import HOLD_MARGIN_M, arrival_s

FILTER = {"ego.safety_filter": True}
X_JOIN = ScenarioConfig().x_overlap_m


def _episode(core, accel: float, max_steps: int = 200) -> tuple[int, list[float]]:
    """Run the ego's episode with a constant command; (outcome, its positions)."""
    xs = []
    for _ in range(max_steps):
        out = core.rollout(np.array([accel]))
        xs += out.trace[0, : out.ego_steps[0], 0].tolist()
        if out.ego_outcome[0] != 0:
            return int(out.ego_outcome[0]), xs
    return 0, xs


# a car in the right lane alongside the ego (2 m ahead of it) at the ego's speed
ALONGSIDE = {"ego": (-75.0, 25.0), "right": [(-73.0, 25.0)]}


@pytest.mark.parametrize("accel", [0.0, 0.5, np.nan])  # nan: the plain-IDM ego
def test_the_filter_prevents_a_join_into_an_occupied_gap(accel):
    outcome, _ = _episode(scene(**ALONGSIDE), accel)
    assert outcome == OUTCOME_COLLISION  # without it the ego joins onto the car
    core = scene(**ALONGSIDE, overrides=FILTER)
    outcome, _ = _episode(core, accel)
    assert core.state.filter_interventions[0] > 0
    assert outcome == OUTCOME_SUCCESS  # it drops back, then merges behind the car


def test_the_filter_waits_at_the_hold_line_while_the_lane_is_jammed():
    # a slow queue in the right lane: no gap the ego may take
    right = [(-40.0 - 9.0 * i, 5.0) for i in range(8)]
    core = scene((-120.0, 15.0), right=right, overrides=FILTER)
    for _ in range(15):
        out = core.rollout(np.array([1.0]))
        assert out.ego_outcome[0] != OUTCOME_COLLISION
    st = core.state
    assert st.lane[0, EGO] == RAMP and st.x_m[0, EGO] <= X_JOIN - HOLD_MARGIN_M + 1e-9
    assert st.filter_interventions[0] > 10


def test_the_filter_leaves_a_free_join_alone():
    core = scene((-75.0, 25.0), right=[(-20.0, 25.0), (-160.0, 25.0)], overrides=FILTER)
    outcome, _ = _episode(core, 0.0)
    assert outcome == OUTCOME_SUCCESS and core.state.filter_interventions[0] == 0
    free = scene((-75.0, 25.0), right=[(-20.0, 25.0), (-160.0, 25.0)])
    assert (
        _episode(free, 0.0)[1]
        == _episode(
            scene((-75.0, 25.0), right=[(-20.0, 25.0), (-160.0, 25.0)], overrides=FILTER), 0.0
        )[1]
    )


def test_interventions_are_counted_per_episode_and_reported():
    core = scene(**ALONGSIDE, overrides=FILTER)
    out = core.rollout(np.array([0.5]))
    assert out.filter_interventions[0] == core.state.filter_interventions[0] > 0
    core.next_ego(np.ones(1, dtype=bool))
    assert core.state.filter_interventions[0] == 0


def test_arrival_time_closed_forms():
    assert arrival_s(100.0, 20.0, 0.0, 60.0) == pytest.approx(5.0)
    assert arrival_s(30.0, 0.0, 2.0, 60.0) == pytest.approx(np.sqrt(30.0))
    assert arrival_s(100.0, 10.0, -2.0, 60.0) == 60.0  # stops after 25 m: never arrives
    assert arrival_s(-1.0, 10.0, 0.0, 60.0) == 0.0


def test_bad_filter_values_are_named():
    with pytest.raises(ValueError, match=r"ego\.safety_min_headway_s must be in \[0, 10\], got -1"):
        ScenarioConfig().replace(**{"ego.safety_min_headway_s": -1.0})
    with pytest.raises(ValueError, match=r"ego\.safety_filter' must be true or false"):
        ScenarioConfig().replace(**{"ego.safety_filter": "yes"})
