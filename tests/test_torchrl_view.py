"""The PettingZoo env works under torchrl's PettingZoo wrapper (agent groups, masks, infos)."""

import pytest
import torch
from torchrl.envs.libs.pettingzoo import PettingZooWrapper
from torchrl.envs.utils import check_env_specs

import marlmerge


def _wrap(control):
    return PettingZooWrapper(
        env=marlmerge.parallel_env(control=control), use_mask=True, done_on_any=False, seed=0
    )


@pytest.mark.parametrize("control", ["ego", "all"])
def test_check_env_specs(control):
    check_env_specs(_wrap(control), seed=0)


def test_groups_masks_and_reward_terms_in_a_rollout():
    env = _wrap("all")
    assert env.group_map == {"ramp": ["ramp_0"], "highway": [f"highway_{i}" for i in range(4)]}

    def policy(td):  # the ego holds its speed, highway agents floor it and soon leave the road
        td.set(("ramp", "action"), torch.zeros(1, 1))
        td.set(("highway", "action"), torch.full((4, 1), 2.5))
        return td

    td = env.rollout(200, policy, break_when_any_done=False)
    assert td["highway", "observation"].shape[-2:] == (4, 12)
    assert td["ramp", "info", "reward_gap_front"].shape[-1] == 1
    assert (td["next", "ramp", "info", "reward_gap_front"] <= 0).all()
    # a highway agent that is done is masked out at the next step, until the next episode
    mask = td["highway", "mask"]
    hw_done = td["next", "highway", "done"].squeeze(-1)
    episode_over = td["next", "done"].squeeze(-1)
    left_early = hw_done[:-1] & ~episode_over[:-1, None]
    assert left_early.any(), "some highway agent should leave the road mid-episode in 200 steps"
    assert not mask[1:][left_early].any()
