"""A plausible driver's envelope for learned highway agents (`highway_envelope = "safe"`): the
safe acceleration against its closed form, constructed scenes, and drivers built to fail the
plausibility checks that no longer fail them within it."""

import numpy as np
import pytest
import torch

from marlmerge.config.cotraining import CoTrainConfig
from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.registry import policy_from_spec
from marlmerge.evaluation.rollout import evaluate_policy
from marlmerge.learners.highway import load_highway_policy, within
from marlmerge.policies.envelope import SafeEnvelope, make_envelope
from marlmerge.sim.observation import HIGHWAY_SCALE

SCEN = resolve_config("default")


def _obs(speed, gap, v_lead):
    """Highway observations [N, 12] of agents at `speed` m/s behind a leader `gap` m ahead."""
    raw = np.zeros((len(speed), 12))
    raw[:, 0], raw[:, 2], raw[:, 3], raw[:, 10], raw[:, 11] = speed, gap, v_lead, 1.0, 29.06
    return raw / HIGHWAY_SCALE


def test_the_safe_acceleration_stops_the_agent_behind_a_braking_leader():
    """After a_safe held for tau and braking at B, the agent stops s0 behind a leader braking
    at B from now: the bound is tight (equality) wherever it is reachable."""
    env = SafeEnvelope(SCEN)
    B, tau, s0 = env.brake_mps2, env.tau_s, env.s0_m
    v, gap, vl = np.array([30.0, 20.0, 25.0]), np.array([15.0, 40.0, 8.0]), np.array([28.0, 10, 25])
    a = env.safe_accel(v, gap, vl)
    v1 = v + a * tau
    travelled = (v + v1) / 2 * tau + v1**2 / (2 * B)
    assert np.allclose(travelled, gap - s0 + vl**2 / (2 * B))
    # no leader in sensing range: a standing one at its edge
    free = env.safe_accel(np.array([20.0, 40.0]), np.array([200.0] * 2), np.array([30.0] * 2))
    edge = env.safe_accel(np.array([20.0, 40.0]), np.array([env.sensing_m] * 2), np.zeros(2))
    assert np.array_equal(free, edge) and free[0] > env.high and free[1] < 0.0


def test_constructed_scenes():
    env = make_envelope("safe", SCEN)
    assert make_envelope("none", SCEN) is None
    with pytest.raises(ValueError, match="unknown highway envelope 'tight'"):
        make_envelope("tight", SCEN)
    obs = _obs([30.0, 30.0, 30.0, 10.0], [150.0, 150.0, 10.0, 1.0], [30.0, 30.0, 30.0, 0.0])
    accel = np.array([[2.0], [-4.5], [2.5], [1.0]], dtype=np.float32)
    out = env(obs, accel)
    b = SCEN.driver.comfort_brake_mps2
    assert out[0, 0] == 2.0  # free road: its own choice
    assert out[1, 0] == -b  # no brake check on a free road
    assert out[2, 0] < 0.0  # 10 m behind a leader at its speed: it must drop back
    assert out[3, 0] == env.low  # about to hit a standing leader: full braking
    fast = env(_obs([34.0], [150.0], [0.0]), np.array([[2.0]]))  # above 1.15 x 29.06 m/s
    assert fast[0, 0] == pytest.approx((1.15 * 29.06 - 34.0) / env.tau_s)
    masked = np.zeros((1, 12))
    assert env(masked, np.array([[0.0]]))[0, 0] == 0.0  # masked-out rows unchanged
    with pytest.raises(ValueError, match="highway_envelope must be one of"):
        CoTrainConfig(highway_envelope="tight")


def test_drivers_built_to_fail_pass_the_checks_within_the_envelope():
    """The test_plausibility drivers (full throttle, full braking throughout), enveloped: no
    collisions of their own, no hard braking."""
    ego = policy_from_spec("gap", SCEN)
    env = SafeEnvelope(SCEN)

    def constant(a, envelope=None):
        def act(obs):
            accel = torch.full((*obs.shape[:-1], 1), a)
            return within(envelope, obs, accel)

        return act

    bare = evaluate_policy(ego, SCEN, 40, 7, 20, constant(2.5))
    racing = evaluate_policy(ego, SCEN, 40, 7, 20, constant(2.5, env))
    braking = evaluate_policy(ego, SCEN, 40, 7, 20, constant(-4.5, env))
    assert bare["highway_own_fault_collision_rate"] > 0.2
    assert racing["highway_own_fault_collision_rate"] == 0.0
    assert braking["highway_hard_brake_share"] < 0.01


def test_a_policy_file_keeps_its_envelope(tmp_path):
    from marlmerge.learners.highway import save_highway_policy
    from marlmerge.learners.quadq import QuadraticQNet
    from marlmerge.sim.observation import HIGHWAY_FEATURES

    net = QuadraticQNet(len(HIGHWAY_FEATURES), 16, action_low=-3.0, action_high=3.0)
    cfg = CoTrainConfig(highway_envelope="safe", hidden=16)
    save_highway_policy(tmp_path / "highway_policy.pt", net.state_dict(), cfg, SCEN)
    policy = load_highway_policy(tmp_path / "highway_policy.pt")
    assert policy.envelope is not None
    obs = torch.as_tensor(_obs([10.0], [1.0], [0.0]), dtype=torch.float32)
    assert policy(obs)[0, 0] == SCEN.sim.highway_agent_accel_bounds_mps2[0]
    plain = CoTrainConfig(hidden=16)
    save_highway_policy(tmp_path / "plain.pt", net.state_dict(), plain, SCEN)
    assert load_highway_policy(tmp_path / "plain.pt").envelope is None


@pytest.mark.slow
@pytest.mark.parametrize("learner", ["quadq", "ppo-speed", "quadq-pace", "ppo-pace"])
def test_an_enveloped_adversary_trains_and_its_policy_file_keeps_the_envelope(tmp_path, learner):
    from test_cotrain import TINY
    from test_ppo import TINY as PPO_TINY

    from marlmerge.training.cotrain import cotrain, load_cotrain_config

    extra = {
        "quadq": TINY,
        "ppo-speed": {"highway_action": "desired_speed", **PPO_TINY},
        "quadq-pace": {"highway_action": "pace_offset", **TINY},
        "ppo-pace": {"highway_action": "pace_offset", **PPO_TINY},
    }[learner]
    cfg = load_cotrain_config(
        "cotrain",
        **{**extra, "rounds": 1, "ego_sim_steps": 0, "select_episodes": 0},
        highway_envelope="safe",
    )
    cotrain(cfg, tmp_path, progress=False)
    driver = load_highway_policy(tmp_path)
    assert driver.envelope is not None
    assert getattr(driver, "pacing", False) == learner.endswith("-pace")
    # whatever the net learned: full braking 1 m behind a standing leader, at most b on a free road
    obs = torch.as_tensor(_obs([10.0, 25.0], [1.0, 150.0], [0.0, 0.0]), dtype=torch.float32)
    accel = driver(obs)
    assert accel[0, 0] == SCEN.sim.highway_agent_accel_bounds_mps2[0]
    assert accel[1, 0] >= -SCEN.driver.comfort_brake_mps2


def test_the_edge_driver_is_the_envelopes_edge_in_evaluate_and_the_grid(capsys):
    """`--highway edge` / `+highway:edge`: IDM + 3 m/s^2 within the envelope, on the scenario it
    drives in; a plausible driver (no collisions of its own) that presses gap acceptance."""
    from marlmerge.cli import main
    from marlmerge.evaluation.grid import parse_condition
    from marlmerge.learners.highway import EDGE_DRIVER, ResidualHighwayPolicy, edge_driver

    cond = parse_condition("grid_moderate_mixed+highway:edge")
    assert cond.highway == (EDGE_DRIVER,) and cond.label.endswith("+ edge drivers")
    with pytest.raises(ValueError, match="'edge' needs the scenario"):
        load_highway_policy(EDGE_DRIVER)
    obs = torch.as_tensor(
        _obs([20.0, 30.0, 10.0], [150.0, 20.0, 1.0], [0.0, 30.0, 0.0]), dtype=torch.float32
    )
    manual = ResidualHighwayPolicy(lambda o: torch.full((*o.shape[:-1], 1), 3.0), SCEN, "safe")
    assert torch.equal(load_highway_policy(EDGE_DRIVER, SCEN)(obs), manual(obs))
    assert edge_driver(SCEN)(obs)[0, 0] == SCEN.sim.highway_agent_accel_bounds_mps2[1]
    assert main(["evaluate", "gap", "--highway", "edge", "--episodes", "40", "--seed", "7"]) == 0
    out = capsys.readouterr().out
    assert "own-fault collisions in 0.0% of episodes" in out
