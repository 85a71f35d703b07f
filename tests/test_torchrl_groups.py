"""The highway agent group of the multi-agent torchrl view, and the interaction reward."""

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from marlmerge.views.torchrl_env import BatchedMergeEnv
from marlmerge.views.torchrl_groups import GROUP, MultiAgentMergeEnv


def _const_policy(ego_a, hw_a):
    def policy(td):
        b = td.batch_size[0]
        td.set("action", torch.full((b, 1), ego_a))
        td.set((GROUP, "action"), torch.full((b, 4, 1), hw_a))
        return td

    return policy


def test_group_spec_has_the_agent_dimension_and_passes_check_env_specs():
    env = MultiAgentMergeEnv(num_worlds=3, seed=0)
    assert env.observation_spec[GROUP, "observation"].shape == (3, 4, 12)
    assert env.observation_spec[GROUP, "mask"].shape == (3, 4)
    assert env.full_action_spec[GROUP, "action"].shape == (3, 4, 1)
    assert env.full_reward_spec[GROUP, "reward"].shape == (3, 4, 1)
    check_env_specs(env, seed=0)


def test_masks_drop_agents_that_leave_the_road_and_zero_their_observations():
    env = MultiAgentMergeEnv(num_worlds=4, seed=1)
    env.set_opponent_mix(1, 0.0)
    # the ego waits on the ramp (it stalls: long episodes); highway agents floor it and exit
    td = env.rollout(150, _const_policy(-4.5, 3.0), break_when_any_done=False)
    mask = td[GROUP, "mask"]  # [B, T, K]
    left = td["next", GROUP, "left_road"]
    next_mask = td["next", GROUP, "mask"]
    assert left.any(), "agents flooring it should leave the road within 150 env steps"
    # left_road marks exactly the acting agents that are gone after the step; those that drove
    # off the road's end (not towed away after a collision) are also marked exited
    assert torch.equal(left, mask & ~next_mask)
    exited = td["next", GROUP, "exited"]
    assert exited.any() and not (exited & ~left).any()
    # once gone, an agent stays masked until its world's next ego departs
    episode_over = td["next", "done"].squeeze(-1)  # [B, T]
    for w, s in zip(*np.nonzero(left.any(-1).numpy()), strict=True):
        if s + 1 < td.shape[1] and not episode_over[w, s]:
            assert not (mask[w, s + 1] & left[w, s]).any()
    assert (td["next", GROUP, "observation"][~next_mask] == 0).all()
    assert (td["next", GROUP, "reward"][~mask] == 0).all()


def test_scripted_worlds_ignore_highway_actions_and_match_the_single_agent_view():
    a = MultiAgentMergeEnv(num_worlds=3, seed=5)
    a.set_opponent_mix(0, 1.0)  # every world scripted
    b = BatchedMergeEnv(num_worlds=3, seed=5)
    ta = a.rollout(60, _const_policy(0.5, -9.0), break_when_any_done=False)

    def ego_only(td):
        td.set("action", torch.full((3, 1), 0.5))
        return td

    tb = b.rollout(60, ego_only, break_when_any_done=False)
    assert torch.equal(ta["next", "observation"], tb["next", "observation"])
    assert torch.equal(ta["next", "reward"], tb["next", "reward"])
    assert (ta["opponent"] == -1).all()


def test_bad_highway_actions_raise_naming_the_agent():
    env = MultiAgentMergeEnv(num_worlds=2, seed=0)
    env.set_opponent_mix(1, 0.0)
    td = env.reset()
    td.set("action", torch.zeros(2, 1))
    act = torch.zeros(2, 4, 1)
    w, k = np.argwhere(env.mask)[0]
    act[w, k] = float("nan")
    td.set((GROUP, "action"), act)
    with pytest.raises(ValueError, match=f"highway agent {k} in world {w}"):
        env.step(td)
    with pytest.raises(ValueError, match="opponent"):
        env.set_opponent_mix(0, 0.5)


def test_an_env_of_several_seeds_runs_each_seed_as_its_own_env():
    many = MultiAgentMergeEnv(num_worlds=3, group_seeds=[4, 9])
    one = MultiAgentMergeEnv(num_worlds=3, seed=9)
    for env in (many, one):
        env.set_opponent_mix(3, 0.4)  # opponents drawn anew for every ego
    tm = many.rollout(150, _const_policy(1.0, 0.5), break_when_any_done=False)
    to = one.rollout(150, _const_policy(1.0, 0.5), break_when_any_done=False)
    assert tm.batch_size[0] == 6 and to["next", "done"].sum() >= 6
    part = tm[3:]  # seed 9's worlds
    for key in ("opponent", ("next", "observation"), ("next", "reward"), ("next", GROUP, "reward")):
        assert torch.equal(part[key], to[key]), key
    assert len(torch.unique(to["opponent"])) >= 3  # drawn anew: scripted and learned ones
    assert not torch.equal(tm[:3]["opponent"], to["opponent"])  # seed 4 draws its own
    with pytest.raises(ValueError, match="seeded when it is made"):
        many.set_seed(1)
