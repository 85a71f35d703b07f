"""The PettingZoo view: API conformance, determinism, bad input and episode structure."""

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

import marlmerge
from marlmerge.sim import OUTCOME_NAMES
from marlmerge.sim.observation import EGO_FEATURES, HIGHWAY_FEATURES
from marlmerge.sim.reward import EGO_TERMS, LEARNED_HIGHWAY_TERMS
from marlmerge.views.pettingzoo_env import EGO_AGENT, reward_terms


def test_parallel_api_test():
    parallel_api_test(marlmerge.parallel_env(), num_cycles=400)


def test_parallel_api_test_ego_only():
    parallel_api_test(marlmerge.parallel_env(control="ego"), num_cycles=200)


def test_parallel_seed_test():
    parallel_seed_test(lambda: marlmerge.parallel_env(), num_cycles=300)


def _rollout(seed, n_steps=300):
    env = marlmerge.parallel_env()
    rng = np.random.default_rng(123)
    obs, _ = env.reset(seed=seed)
    trace = []
    for _ in range(n_steps):
        actions = {a: rng.uniform(-3.0, 2.0, size=1).astype(np.float32) for a in env.agents}
        obs, rew, term, trunc, info = env.step(actions)
        trace.append((sorted(obs.items(), key=lambda kv: kv[0]), sorted(rew.items())))
        if not env.agents:
            obs, _ = env.reset()
    return trace, env.core.state.x_m.copy()


def test_same_seed_same_actions_same_trajectory_bit_for_bit():
    t1, x1 = _rollout(7)
    t2, x2 = _rollout(7)
    assert np.array_equal(x1, x2)
    for (o1, r1), (o2, r2) in zip(t1, t2, strict=False):
        assert [k for k, _ in o1] == [k for k, _ in o2]
        assert all(np.array_equal(a, b) for (_, a), (_, b) in zip(o1, o2, strict=False))
        assert r1 == r2
    t3, x3 = _rollout(8)
    assert not np.array_equal(x1, x3)


def test_agents_spaces_and_metadata():
    env = marlmerge.parallel_env()
    assert env.metadata["name"] == "marlmerge_ramp_v2"
    assert env.possible_agents[0] == EGO_AGENT
    assert env.possible_agents[1:] == [f"highway_{i}" for i in range(4)]
    assert env.observation_space(EGO_AGENT).shape == (len(EGO_FEATURES),)
    assert env.observation_space("highway_0").shape == (len(HIGHWAY_FEATURES),)
    assert env.action_space(EGO_AGENT) is env.action_space(EGO_AGENT)
    assert tuple(env.action_space(EGO_AGENT).low) == (-4.5,)
    obs, _ = env.reset(seed=0)
    assert set(obs) == set(env.agents)
    assert env.agents[0] == EGO_AGENT and len(env.agents) == 5


def test_ego_only_control_has_one_agent():
    env = marlmerge.parallel_env(control="ego")
    obs, _ = env.reset(seed=0)
    assert env.agents == [EGO_AGENT] == env.possible_agents


@pytest.mark.parametrize(
    ("action", "match"),
    [
        (np.array([np.nan]), "'ramp_0'.*nan"),
        (np.array([np.inf]), "'ramp_0'.*inf"),
        (np.array([0.1, 0.2]), r"'ramp_0'.*shape \(2,\)"),
        (np.zeros((1, 1)), r"'ramp_0'.*shape \(1, 1\)"),
    ],
)
def test_bad_actions_raise_naming_agent_and_value(action, match):
    env = marlmerge.parallel_env(control="ego")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.step({EGO_AGENT: action})


@pytest.mark.parametrize("make", ["parallel_env", "ramp_flow_parallel_env"])
def test_a_step_before_reset_says_so(make):
    env = getattr(marlmerge, make)(*(("ramp_flow",) if make.startswith("ramp") else ()))
    with pytest.raises(RuntimeError, match=r"step\(\) called before reset\(\): call reset"):
        env.step({})


def test_unknown_and_missing_agents_raise():
    env = marlmerge.parallel_env()
    env.reset(seed=0)
    acts = {a: np.zeros(1) for a in env.agents}
    with pytest.raises(ValueError, match="'car_9'"):
        env.step({**acts, "car_9": np.zeros(1)})
    del acts["highway_0"]
    with pytest.raises(ValueError, match="'highway_0'"):
        env.step(acts)
    with pytest.raises(ValueError, match="'ramp_1'"):
        env.step({**acts, "highway_0": np.zeros(1), "ramp_1": np.zeros(1)})
    with pytest.raises(ValueError, match="'nobody'"):
        env.action_space("nobody")


def test_out_of_range_actions_are_clipped():
    e1, e2 = marlmerge.parallel_env(control="ego"), marlmerge.parallel_env(control="ego")
    e1.reset(seed=4)
    e2.reset(seed=4)
    for _ in range(5):
        o1, r1, *_ = e1.step({EGO_AGENT: np.array([100.0])})
        o2, r2, *_ = e2.step({EGO_AGENT: np.array([2.5])})
        assert np.array_equal(o1[EGO_AGENT], o2[EGO_AGENT]) and r1 == r2


def test_reward_terms_are_reported_and_sum_to_the_reward():
    env = marlmerge.parallel_env()
    env.reset(seed=1)
    seen = set()
    for _ in range(200):
        obs, rew, term, trunc, info = env.step({a: np.array([-0.5]) for a in env.agents})
        terms = reward_terms(info[EGO_AGENT])
        assert tuple(terms) == EGO_TERMS
        assert sum(terms.values()) == pytest.approx(rew[EGO_AGENT])
        assert all(v <= 0.0 for v in terms.values())
        for a in rew:
            if a != EGO_AGENT:
                assert tuple(reward_terms(info[a])) == LEARNED_HIGHWAY_TERMS
        seen |= {k for k, v in terms.items() if v < 0}
        if not env.agents:
            assert OUTCOME_NAMES[info[EGO_AGENT]["outcome"]] in (
                "success",
                "collision",
                "truncated",
            )
            env.reset()
    assert {"acceleration", "gap_front", "speed"} <= seen


def test_episode_end_and_next_ego():
    env = marlmerge.parallel_env()
    env.reset(seed=2)
    ego_ids = []
    for _ in range(3):
        while env.agents:
            _, _, term, trunc, info = env.step({a: np.array([0.0]) for a in env.agents})
        ego_done = term[EGO_AGENT] or trunc[EGO_AGENT]
        assert ego_done
        ego_ids.append(int(env.core.state.vehicle_id[0, 0]))
        with pytest.raises(RuntimeError, match="on a finished episode: call reset"):
            env.step({EGO_AGENT: np.zeros(1)})
        env.reset()  # the next ramp vehicle departs into the same traffic
        assert env.core.state.x_m[0, 0] == env.cfg.road.x_ramp_start_m
    assert len(set(ego_ids)) == 3


def test_highway_agent_that_leaves_the_road_terminates():
    env = marlmerge.parallel_env(overrides={"ego.max_episode_s": 60.0})
    env.reset(seed=0)
    gone = None
    for _ in range(150):
        acts = {a: np.array([2.5 if a != EGO_AGENT else -4.5]) for a in env.agents}
        _, _, term, trunc, _ = env.step(acts)
        left = [a for a in term if a != EGO_AGENT and term[a]]
        if left:
            gone = left[0]
            break
        if not env.agents:
            break
    assert gone is not None, "a highway agent flooring it should reach the exit within 60 s"
    assert gone not in env.agents and EGO_AGENT in env.agents
    # an action for an agent that is done is checked, then ignored
    with pytest.raises(ValueError, match=f"action of '{gone}' \\(not live this step\\)"):
        env.step({**{a: np.zeros(1) for a in env.agents}, gone: np.array([np.nan])})
    env.step({**{a: np.zeros(1) for a in env.agents}, gone: np.array([1.0])})
