"""Scripted policies act through the agent interface and behave as their profiles promise."""

import numpy as np

import marlmerge
from marlmerge.policies.scripted import IdmEgoPolicy, ScriptedHighwayPolicy
from marlmerge.sim import OUTCOME_NONE
from marlmerge.sim.observation import HIGHWAY_FEATURES, HIGHWAY_SCALE
from marlmerge.views.pettingzoo_env import EGO_AGENT


def _highway_obs(**raw):
    values = {
        "speed": 25.0,
        "lane": 0.0,
        "leader_gap": 60.0,
        "leader_speed": 25.0,
        "follower_gap": 40.0,
        "follower_speed": 25.0,
        "ego_dx": 15.0,
        "ego_speed": 25.0,
        "ego_to_merge": 80.0,
        "ego_in_lane": 0.0,
        "ego_present": 1.0,
        "speed_limit": 29.06,
    }
    values.update(raw)
    return np.array([values[f.name] for f in HIGHWAY_FEATURES]) / HIGHWAY_SCALE


def test_profiles_differ_when_a_ramp_vehicle_will_merge_ahead():
    obs = _highway_obs()
    a = {
        p: float(ScriptedHighwayPolicy(p)(obs)[0])
        for p in ("cooperative", "neutral", "adversarial")
    }
    assert a["cooperative"] < a["neutral"] < a["adversarial"]
    assert a["cooperative"] >= -2.0  # yields gently (yield_max_brake_mps2)


def test_profiles_agree_when_no_ramp_vehicle_is_near():
    obs = _highway_obs(ego_present=0.0)
    acts = [
        float(ScriptedHighwayPolicy(p)(obs)[0]) for p in ("cooperative", "neutral", "adversarial")
    ]
    assert acts[0] == acts[1] == acts[2]


def test_unknown_profile_is_named():
    try:
        ScriptedHighwayPolicy("aggressive")
    except ValueError as err:
        assert "'aggressive'" in str(err)
    else:
        raise AssertionError("expected ValueError")


def test_scripted_policies_drive_highway_agents_without_mainline_collisions():
    env = marlmerge.parallel_env()
    obs, infos = env.reset(seed=9)
    ego = IdmEgoPolicy(env.cfg)
    outcomes = []
    for _ in range(6):
        pols = {
            a: ScriptedHighwayPolicy(int(i["profile"]), env.cfg)
            for a, i in infos.items()
            if a != EGO_AGENT
        }
        while env.agents:
            acts = {a: pols[a](obs[a]) if a != EGO_AGENT else ego(obs[a]) for a in env.agents}
            obs, _, _, _, info = env.step(acts)
        outcomes.append(info[EGO_AGENT]["outcome"])
        obs, infos = env.reset()
    assert env.core.state.background_collisions.sum() == 0
    assert all(o != OUTCOME_NONE for o in outcomes)  # every episode reached its end
