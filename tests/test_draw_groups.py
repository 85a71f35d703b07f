"""Draw groups (`marlmerge.sim.core.draw_groups`): the worlds of a group run bit for bit as a
core of those worlds alone, whatever the other groups' worlds do (resets, their warm-up calls,
their traffic's need for vehicle slots)."""

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig
from marlmerge.sim import TrafficCore
from marlmerge.sim.layout import OUTCOME_NONE

BASE = ScenarioConfig().replace(  # few slots to start; measurement errors drawn in chunks
    **{"traffic.flow_vph_per_lane": 300.0, "sensing.position_noise_std_m": 1.0}
)
DENSE = BASE.replace(
    **{"traffic.flow_vph_per_lane": 2400.0, "driver.desired_speed_factor": [0.3, 0.4]}
)
LIGHT = BASE.replace(**{"traffic.flow_vph_per_lane": 600.0})


def _drive(core: TrafficCore, steps: int, reset_every: dict[int, int]) -> list[np.ndarray]:
    """The ego observations [B, F] of `steps` calls; every ego that ends is replaced, and
    world w gets a new road every `reset_every[w]` calls."""
    out = []
    for step in range(1, steps + 1):
        r = core.rollout(np.full(core.batch_size, 0.3 * np.sin(0.1 * step)))
        out.append(r.ego_obs.copy())
        core.next_ego(r.ego_outcome != OUTCOME_NONE)
        for world, every in reset_every.items():
            if step % every == 0:
                mask = np.zeros(core.batch_size, dtype=bool)
                mask[world] = True
                core.reset(mask=mask)
    return out


@pytest.mark.parametrize("groups", [[0, 0, 1, 1], [5, 5, 2, 2]])
def test_a_groups_worlds_run_as_a_core_of_their_own(groups):
    together = TrafficCore(
        BASE, 4, seed=[10, 11, 12, 13], scenarios=[DENSE, DENSE, LIGHT, LIGHT], world_groups=groups
    )
    alone = TrafficCore(BASE, 2, seed=[12, 13], scenarios=[LIGHT, LIGHT])
    # the dense worlds get new roads often (warm-up calls that the light ones sit out) and
    # need more slots; the light ones reset on their own clock, the same in both cores
    obs_together = _drive(together, 400, {0: 23, 1: 37, 3: 61})
    obs_alone = _drive(alone, 400, {1: 61})
    assert together.n_slots > alone.n_slots  # the dense group made the arrays grow
    for step, (t, a) in enumerate(zip(obs_together, obs_alone, strict=True)):
        assert np.array_equal(t[2:], a), f"the light worlds differ at call {step}"
    state = together.state_dict()  # a checkpoint keeps each group's slot count
    again = TrafficCore(
        BASE, 4, seed=[0, 0, 0, 0], scenarios=[DENSE, DENSE, LIGHT, LIGHT], world_groups=groups
    )
    again.load_state_dict(state)
    assert again.state_dict()["group_slots"] == state["group_slots"]
    for t, a in zip(_drive(together, 50, {0: 7}), _drive(again, 50, {0: 7}), strict=True):
        assert np.array_equal(t, a)


@pytest.mark.parametrize("groups", [[0, 1], [0, 1, 2, -1], [0.0, 1.0, 0.0, 1.0], "ab"])
def test_bad_world_groups_are_named(groups):
    with pytest.raises(ValueError, match="world_groups"):
        TrafficCore(BASE, 4, seed=0, world_groups=groups)
