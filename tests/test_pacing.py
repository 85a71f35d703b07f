"""The scripted pacing driver (`--highway pace`) and learned adjustments to it
(`highway_action = "pace_offset"`): its rule in constructed scenes, its place in evaluate, the
grid and the policy files, and what it does to a ramp vehicle that does not look for a gap."""

import numpy as np
import pytest
import torch

from marlmerge.config.cotraining import CoTrainConfig
from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.registry import policy_from_spec
from marlmerge.evaluation.rollout import evaluate_policy
from marlmerge.learners.highway import (
    COURTESY_SPEED_FACTOR,
    OFFSET_BOUNDS_MPS2,
    PACE_DRIVER,
    PACE_GAINS,
    PACE_RANGE_M,
    ResidualHighwayPolicy,
    load_highway_policy,
    pace_driver,
    pacing_accel,
)
from marlmerge.sim.observation import HIGHWAY_FEATURES, HIGHWAY_SCALE, feature_index

SCEN = resolve_config("default")
LIMIT = SCEN.road.speed_limit_mps
COL = {f.name: feature_index(HIGHWAY_FEATURES, f.name) for f in HIGHWAY_FEATURES}


def _raw(**values: list[float]) -> np.ndarray:
    """Unscaled highway observations [N, 12]: a right-lane agent at 25 m/s on a free road with
    a ramp vehicle on the ramp, the given columns replaced."""
    n = len(next(iter(values.values())))
    raw = np.zeros((n, len(HIGHWAY_FEATURES)))
    base = {"speed": 25.0, "leader_gap": 150.0, "leader_speed": 25.0, "follower_gap": 150.0,
            "follower_speed": 25.0, "ego_speed": 25.0, "ego_to_merge": 150.0,
            "ego_present": 1.0, "speed_limit": LIMIT}  # fmt: skip
    for name, value in {**base, **values}.items():
        raw[:, COL[name]] = value
    return raw


def test_the_pacing_rule_in_constructed_scenes():
    raw = _raw(
        ego_dx=[4.0, -10.0, 30.0, 4.0, 4.0, 4.0],
        ego_speed=[27.0, 22.0, 27.0, 0.5 * LIMIT, 27.0, 27.0],
        ego_in_lane=[0.0, 0.0, 0.0, 0.0, 1.0, 0.0],
        ego_present=[1.0, 1.0, 1.0, 1.0, 1.0, 0.0],
    )
    idm = np.array([0.3, -0.2, 0.1, 0.5, 0.4, 0.6])
    out = pacing_accel(raw, idm)
    top = OFFSET_BOUNDS_MPS2[1]
    # beside the ramp vehicle: towards its position and speed
    assert out[0] == pytest.approx(PACE_GAINS[0] * 4.0 + PACE_GAINS[1] * (27.0 - 25.0))
    assert out[1] == pytest.approx(PACE_GAINS[0] * -10.0 + PACE_GAINS[1] * (22.0 - 25.0))
    assert out[2] == idm[2] + top  # beyond PACE_RANGE_M: closing gaps as the edge driver
    assert 30.0 > PACE_RANGE_M
    assert out[3] == idm[3]  # a ramp vehicle waiting for a gap is let in
    assert 0.5 < COURTESY_SPEED_FACTOR
    assert out[4] == idm[4] + top  # it has joined: nothing to pace
    assert out[5] == idm[5] + top  # no ramp vehicle on the road


def test_the_pacing_driver_in_evaluate_and_the_grid(capsys):
    """`--highway pace` / `+highway:pace`: the pacing base with no adjustment, within the
    envelope; no collision of its own against gap acceptance."""
    from marlmerge.cli import main
    from marlmerge.evaluation.grid import parse_condition
    from marlmerge.learners.highway import SCRIPTED_DRIVERS, SCRIPTED_LABELS

    assert SCRIPTED_LABELS.keys() == SCRIPTED_DRIVERS.keys()  # every scripted driver named
    cond = parse_condition("grid_moderate_mixed+highway:pace")
    assert cond.highway == (PACE_DRIVER,) and cond.label.endswith("+ pacing drivers")
    with pytest.raises(ValueError, match="'pace' needs the scenario"):
        load_highway_policy(PACE_DRIVER)
    raw = _raw(ego_dx=[4.0, 0.0, 2.0], leader_gap=[150.0, 2.0, 150.0], speed=[25.0, 25.0, 36.0])
    obs = torch.as_tensor(raw / HIGHWAY_SCALE, dtype=torch.float32)
    driver = load_highway_policy(PACE_DRIVER, SCEN)
    manual = ResidualHighwayPolicy(lambda o: torch.zeros((*o.shape[:-1], 1)), SCEN, "safe", "pace")
    assert torch.equal(driver(obs), manual(obs)) and driver.envelope is not None
    accel = driver(obs)[:, 0]
    assert accel[0] > 0.0  # the ramp vehicle 4 m ahead and 2 m/s faster: it keeps up
    assert accel[1] == SCEN.sim.highway_agent_accel_bounds_mps2[0]  # 2 m behind its leader
    assert accel[2] < 0.0  # above the fastest driver's speed: the envelope slows it
    masked = torch.zeros((1, len(HIGHWAY_FEATURES)))
    idm = ResidualHighwayPolicy(lambda o: o, SCEN, "safe")
    assert torch.equal(pace_driver(SCEN).base(masked), idm.base(masked))  # masked: no pacing
    with pytest.raises(ValueError, match="unknown highway base 'fast'"):
        ResidualHighwayPolicy(lambda o: o, SCEN, "safe", "fast")
    assert main(["evaluate", "gap", "--highway", "pace", "--episodes", "40", "--seed", "7"]) == 0
    assert "own-fault collisions in 0.0% of episodes" in capsys.readouterr().out


def test_pacing_drivers_take_the_place_a_careless_ramp_vehicle_merges_into():
    """A ramp vehicle that ignores the merge (IDM) merges into whatever is beside it: against
    pacing drivers it collides far more often than against edge drivers, which only close gaps;
    gap acceptance, which waits for a gap, is let in."""
    careless, careful = policy_from_spec("idm", SCEN), policy_from_spec("gap", SCEN)
    pace, edge = load_highway_policy("pace", SCEN), load_highway_policy("edge", SCEN)
    paced = evaluate_policy(careless, SCEN, 100, 7, 20, pace)
    edged = evaluate_policy(careless, SCEN, 100, 7, 20, edge)
    assert paced["collision_rate"] > edged["collision_rate"] + 0.3
    assert evaluate_policy(careful, SCEN, 100, 7, 20, pace)["success_rate"] >= 0.95


def test_a_learned_adjustment_to_pacing_keeps_its_base_in_the_policy_file(tmp_path):
    from marlmerge.io.policy_file import read_policy
    from marlmerge.learners.highway import frozen_net, save_highway_policy
    from marlmerge.learners.quadq import QuadraticQNet

    torch.manual_seed(0)
    net = QuadraticQNet(len(HIGHWAY_FEATURES), 16, action_low=-3.0, action_high=3.0)
    cfg = CoTrainConfig(highway_envelope="safe", highway_action="pace_offset", hidden=16)
    save_highway_policy(tmp_path / "highway_policy.pt", net.state_dict(), cfg, SCEN)
    assert read_policy(tmp_path / "highway_policy.pt", "highway")["algorithm"] == "quadq-pace"
    loaded = load_highway_policy(tmp_path / "highway_policy.pt")
    assert loaded.pacing and loaded.envelope is not None
    greedy = frozen_net(net.state_dict(), len(HIGHWAY_FEATURES), 16, (-3.0, 3.0)).greedy
    manual = ResidualHighwayPolicy(greedy, SCEN, "safe", "pace")
    obs = torch.as_tensor(_raw(ego_dx=[4.0, -20.0]) / HIGHWAY_SCALE, dtype=torch.float32)
    assert torch.equal(loaded(obs), manual(obs))
    idm_cfg = CoTrainConfig(highway_envelope="safe", hidden=16)
    save_highway_policy(tmp_path / "idm.pt", net.state_dict(), idm_cfg, SCEN)
    assert not load_highway_policy(tmp_path / "idm.pt").pacing
    with pytest.raises(ValueError, match="highway_action must be one of"):
        CoTrainConfig(highway_action="pace")
