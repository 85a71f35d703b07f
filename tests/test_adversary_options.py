"""Options of the adversary phase: learned drivers that choose a desired speed (plausible by
construction), and shaping of their reward with the ego's own value estimate."""

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from test_ppo import TINY as PPO_TINY

from marlmerge.config import ScenarioConfig
from marlmerge.io import files
from marlmerge.learners.highway import (
    DesiredSpeedHighwayPolicy,
    ResidualHighwayPolicy,
    load_highway_policy,
)
from marlmerge.learners.quadq import QuadraticQNet
from marlmerge.policies.scripted import ScriptedHighwayPolicy
from marlmerge.sim.observation import HIGHWAY_FEATURES, HIGHWAY_SCALE
from marlmerge.training.cotrain import cotrain, load_cotrain_config, shape_with_ego_value
from marlmerge.views.torchrl_groups import GROUP

_I = {f.name: i for i, f in enumerate(HIGHWAY_FEATURES)}


def _free_road_obs(v_mps: float, n: int = 3) -> torch.Tensor:
    """[1, n, 12] scaled observations of agents at `v_mps` with no leader in sight."""
    raw = np.zeros((1, n, len(HIGHWAY_FEATURES)))
    raw[..., _I["speed"]] = v_mps
    raw[..., _I["leader_gap"]] = 1_000.0
    raw[..., _I["leader_speed"]] = v_mps
    return torch.as_tensor(raw / HIGHWAY_SCALE, dtype=torch.float32)


def test_a_speed_choosing_driver_is_idm_at_the_chosen_speed():
    scen = ScenarioConfig()
    limit = scen.road.speed_limit_mps
    obs = _free_road_obs(limit)
    for factor, sign in ((0.5, -1.0), (1.0, 0.0), (1.1, 1.0)):
        policy = DesiredSpeedHighwayPolicy(
            lambda o, f=factor: torch.full((*o.shape[:-1], 1), f), scen
        )
        accel = policy(obs)
        idm = ScriptedHighwayPolicy("neutral", scen)(obs.numpy(), np.full((1, 3), factor * limit))
        assert accel.shape == (1, 3, 1)
        assert torch.allclose(accel, torch.as_tensor(idm, dtype=accel.dtype).clamp(-4.5, 2.5))
        assert np.sign(round(float(accel[0, 0, 0]), 6)) == sign
    # a learner's act (a dict) keeps what else it acted with and gets the acceleration
    out = DesiredSpeedHighwayPolicy(
        lambda o: {"action": torch.full((*o.shape[:-1], 1), 0.5), "z": torch.ones(1)}, scen
    )(obs)
    assert set(out) == {"action", "z"} and bool((out["action"] < 0).all())


def test_desired_speed_needs_ppo_and_sane_bounds():
    with pytest.raises(ValueError, match="highway_action"):
        load_cotrain_config("adversary", highway_action="desired_speed")
    with pytest.raises(ValueError, match="highway_action"):
        load_cotrain_config("adversary_ppo", highway_action="fly")
    with pytest.raises(ValueError, match="highway_speed_factor_bounds"):
        load_cotrain_config(
            "adversary_ppo", highway_action="desired_speed", highway_speed_factor_bounds=[1.2, 0.5]
        )


def test_ego_value_shaping_is_the_potential_difference_for_every_agent():
    gen = torch.Generator().manual_seed(0)
    net = QuadraticQNet(7, 8, generator=torch.Generator().manual_seed(1))
    b, t, k = 3, 5, 4
    terminated = torch.zeros(b, t, 1, dtype=torch.bool)
    terminated[1, 2] = True
    batch = TensorDict(
        {
            "observation": torch.randn(b, t, 7, generator=gen),
            "next": {
                "observation": torch.randn(b, t, 7, generator=gen),
                "terminated": terminated,
                GROUP: {"reward": torch.ones(b, t, k, 1)},
            },
        },
        [b, t],
    )
    shaping = shape_with_ego_value(batch, net, 0.9, 2.0, 1.0)
    v = net.max_value(batch["observation"]).detach()
    v_next = net.max_value(batch["next", "observation"]).detach()
    expected = 2.0 * (v - 0.9 * (~terminated).float() * v_next)
    assert torch.allclose(shaping, expected)
    assert torch.allclose(shaping[1, 2], 2.0 * v[1, 2])  # the ego's episode ended: V(end) = 0
    reward = batch["next", GROUP, "reward"]
    assert torch.allclose(reward, 1.0 + expected.unsqueeze(-2).expand(b, t, k, 1))


@pytest.mark.slow
def test_a_speed_choosing_adversary_trains_saves_and_reloads(tmp_path):
    cfg = load_cotrain_config(
        "cotrain",
        **{**PPO_TINY, "ego_sim_steps": 0, "select_episodes": 0},
        highway_action="desired_speed",
        ego_value_shaping=1.0,
    )
    cotrain(cfg, tmp_path, progress=False)
    saved = files.load(tmp_path / "highway_policy.pt")
    assert saved["algorithm"] == "ppo-speed"
    assert list(saved["action_bounds_mps2"]) == [0.5, 1.1]
    driver = load_highway_policy(tmp_path)
    accel = driver(_free_road_obs(ScenarioConfig().road.speed_limit_mps))
    assert accel.shape == (1, 3, 1) and bool(((accel >= -4.5) & (accel <= 2.5)).all())
    assert not isinstance(driver, ResidualHighwayPolicy)
