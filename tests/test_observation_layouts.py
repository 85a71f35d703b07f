"""The extended ego observation: the table, the kernel's values in hand-computed scenes, and every
view sized from the layout."""

import gymnasium
import numpy as np
import pytest
import torch
from pettingzoo.test import parallel_api_test
from scenes import scene
from torchrl.envs.utils import check_env_specs

import marlmerge
from marlmerge.config import ScenarioConfig
from marlmerge.sim.observation import (
    EGO_EXTENDED_ACCEL_FEATURES,
    EGO_EXTENDED_FEATURES,
    EGO_EXTENDED_JOIN_FEATURES,
    EGO_FEATURES,
    EGO_LAYOUTS,
    ego_features,
    ego_obs_size,
    feature_index,
)
from marlmerge.views.pettingzoo_env import EGO_AGENT
from marlmerge.views.torchrl_env import BatchedMergeEnv
from marlmerge.views.torchrl_groups import MultiAgentMergeEnv

EXTENDED = {"ego.observation": "extended"}
CFG = ScenarioConfig()
L_M, RANGE_M, V_LIMIT = CFG.vehicle.length_m, CFG.ego.sensing_range_m, CFG.road.speed_limit_mps


def _raw(obs: np.ndarray) -> dict[str, float]:
    """The observation in SI units, by feature name."""
    return {f.name: float(obs[i]) * f.scale for i, f in enumerate(EGO_EXTENDED_FEATURES)}


def test_every_layout_begins_with_the_papers_state():
    assert tuple(EGO_LAYOUTS) == ("paper", "extended", "extended_accel", "extended_join")
    assert EGO_EXTENDED_JOIN_FEATURES[:17] == EGO_EXTENDED_ACCEL_FEATURES
    assert [f.name for f in EGO_EXTENDED_JOIN_FEATURES[17:]] == [
        "lead_gap_at_join",
        "lag_gap_at_join",
    ]
    assert EGO_EXTENDED_FEATURES[: len(EGO_FEATURES)] == EGO_FEATURES
    assert EGO_EXTENDED_ACCEL_FEATURES[:16] == EGO_EXTENDED_FEATURES
    assert EGO_EXTENDED_ACCEL_FEATURES[16].name == "ego_accel"
    assert ego_obs_size(CFG.replace(**{"ego.observation": "extended_accel"})) == 17
    assert len({f.name for f in EGO_EXTENDED_FEATURES}) == len(EGO_EXTENDED_FEATURES) == 16
    assert ego_features(CFG) == EGO_FEATURES and ego_obs_size(CFG) == 7
    assert ego_obs_size(CFG.replace(**EXTENDED)) == 16
    assert all(f.noise in ("", "position", "speed") for f in EGO_EXTENDED_FEATURES)
    with pytest.raises(ValueError, match=r"ego\.observation.*'wide'"):
        CFG.replace(**{"ego.observation": "wide"})


def test_extended_features_match_a_hand_computed_scene():
    # ego on the ramp at -60 m; a right-lane car 3 m ahead of it (alongside), one behind; two
    # left-lane cars
    core = scene(
        ego=(-60.0, 20.0),
        right=[(-57.0, 25.0), (-80.0, 22.0)],
        left=[(-30.0, 28.0), (-100.0, 27.0)],
        overrides=EXTENDED,
    )
    obs, _ = core.observe()
    assert obs.shape == (1, 16) and obs.dtype == np.float32
    got = _raw(obs[0])
    x_join = core.cfg.x_overlap_m
    expected = {
        "ego_speed": 20.0,
        "ego_position": -60.0,
        "front_speed": 25.0,
        "front_position": -57.0,
        "back_speed": 22.0,
        "back_position": -80.0,
        "speed_limit": V_LIMIT,
        "side_dx": 3.0,
        "side_speed": 25.0,
        "side_overlap": 1.0 - 3.0 / L_M,
        "left_front_dx": 30.0,
        "left_front_speed": 28.0,
        "left_back_dx": -40.0,
        "left_back_speed": 27.0,
        "time_to_join": (x_join + 60.0) / 20.0,
        "time_to_merge": 60.0 / 20.0,
    }
    assert list(got) == list(expected)
    for name, value in expected.items():
        assert got[name] == pytest.approx(value, rel=1e-6, abs=1e-5), name


def test_missing_vehicles_are_virtual_at_the_sensing_edge():
    core = scene(ego=(-60.0, 0.0), right=[(-90.0, 25.0)], overrides=EXTENDED)
    got = _raw(core.observe()[0][0])
    assert got["side_dx"] == pytest.approx(RANGE_M) and got["side_overlap"] == 0.0
    assert got["side_speed"] == pytest.approx(V_LIMIT)
    assert got["left_front_dx"] == pytest.approx(RANGE_M)
    assert got["left_back_dx"] == pytest.approx(-RANGE_M)
    assert got["left_front_speed"] == pytest.approx(V_LIMIT)
    cap = CFG.ego.time_to_merge_cap_s
    assert got["time_to_join"] == pytest.approx(cap) and got["time_to_merge"] == pytest.approx(cap)
    # the car behind is 25 m back: not alongside
    assert got["back_position"] == pytest.approx(-90.0)


def test_the_alongside_vehicle_can_be_the_gap_back_one_and_times_end_at_zero():
    core = scene(ego=(10.0, 20.0), right=[(40.0, 20.0), (8.0, 20.0)], overrides=EXTENDED)
    got = _raw(core.observe()[0][0])  # in the lane, overlapping the car behind: a crash scene
    assert got["side_dx"] == pytest.approx(-2.0) and got["side_overlap"] == pytest.approx(0.6)
    assert got["time_to_join"] == 0.0 and got["time_to_merge"] == 0.0
    assert feature_index(EGO_EXTENDED_FEATURES, "time_to_merge") == 15


def test_the_paper_layout_is_the_first_seven_extended_features():
    kwargs = {"ego": (-60.0, 20.0), "right": [(-57.0, 25.0)], "left": [(-30.0, 28.0)]}
    paper = scene(**kwargs).observe()[0]
    extended = scene(**kwargs, overrides=EXTENDED).observe()[0]
    assert paper.shape == (1, 7) and np.array_equal(paper, extended[:, :7])


FULL = {
    "ego.observation": "extended_accel",
    "reward.w_jerk": 0.1,
    "ego.safety_filter": True,
    "sensing.position_noise_std_m": 0.5,
    "sensing.latency_s": 0.2,
    "sensing.occlusion": True,
    "reward.w_back_ttc": 1.0,
}


def test_torchrl_views_are_sized_from_the_layout():
    env = BatchedMergeEnv(num_worlds=3, seed=0, overrides=FULL)
    assert env.observation_spec["observation"].shape == (3, 17)
    check_env_specs(env, seed=0)
    td = env.rollout(5, break_when_any_done=False)
    assert td["next", "observation"].shape == (3, 5, 17)
    assert td["next", "filter_interventions"].dtype.is_floating_point is False
    assert "filter_interventions" not in BatchedMergeEnv(num_worlds=2).observation_spec.keys()
    marl = MultiAgentMergeEnv(num_worlds=2, seed=1, overrides=FULL)
    check_env_specs(marl, seed=1)
    assert marl.observation_spec["observation"].shape == (2, 17)


def test_pettingzoo_view_is_sized_from_the_layout():
    env = marlmerge.parallel_env(overrides=FULL)
    assert env.observation_space(EGO_AGENT).shape == (17,)
    parallel_api_test(env, num_cycles=60)
    obs, infos = env.reset(seed=0)
    assert obs[EGO_AGENT].shape == (17,) and infos[EGO_AGENT]["filter_interventions"] == 0
    assert "filter_interventions" not in marlmerge.parallel_env().reset(seed=0)[1][EGO_AGENT]


def test_gymnasium_views_are_sized_from_the_layout():
    env = gymnasium.make("marlmerge/RampMerge-v2", overrides=FULL)
    obs, info = env.reset(seed=0)
    assert env.observation_space.shape == (17,) and obs.shape == (17,)
    assert env.observation_space.contains(obs) and "filter_interventions" in info
    obs, *_, info = env.step(np.array([0.5], dtype=np.float32))
    assert obs.shape == (17,)
    vec = gymnasium.make_vec(
        "marlmerge/RampMerge-v2", num_envs=3, vectorization_mode="vector_entry_point",
        overrides=FULL,
    )  # fmt: skip
    obs, _ = vec.reset(seed=0)
    assert vec.single_observation_space.shape == (17,) and obs.shape == (3, 17)
    obs, *_ = vec.step(np.zeros((3, 1), dtype=np.float32))
    assert obs.shape == (3, 17)


def test_rule_policies_read_the_papers_features_of_any_layout():
    from marlmerge.policies.gap_acceptance import GapAcceptancePolicy, IdmEgoPolicy

    core = scene(ego=(-60.0, 20.0), right=[(-57.0, 25.0)], overrides=EXTENDED)
    extended = core.observe()[0]
    for policy in (GapAcceptancePolicy(core.cfg), IdmEgoPolicy(core.cfg)):
        assert np.array_equal(policy(extended), policy(extended[:, :7]))


def test_the_documented_table_is_the_spec_table():
    from pathlib import Path

    page = (Path(__file__).resolve().parent.parent / "docs" / "sensing.md").read_text()
    rows = [line.split("|")[1:5] for line in page.splitlines() if line.startswith("| `")]
    table = {c[0].strip().strip("`"): tuple(x.strip() for x in c[1:]) for c in rows}
    for f in EGO_EXTENDED_JOIN_FEATURES:
        assert table.get(f.name) == (f.unit, f"{f.scale:g}", f.noise or "-"), f.name


def test_the_ego_sees_the_acceleration_it_applied():
    core = scene(ego=(-120.0, 20.0), overrides={"ego.observation": "extended_accel"})
    assert core.observe()[0][0, 16] == 0.0  # before its first step
    for cmd in (1.5, -2.0, 0.0):
        out = core.rollout(np.array([cmd]))
        assert out.ego_obs[0, 16] == np.float32(cmd / 5.0)
        assert np.array_equal(out.ego_obs[:, :16], core.observe()[0][:, :16])


JOIN = {"ego.observation": "extended_join"}


JOIN_SCALE = np.array([f.scale for f in EGO_EXTENDED_JOIN_FEATURES])
_J = {f.name: i for i, f in enumerate(EGO_EXTENDED_JOIN_FEATURES)}


def _join_gaps(core) -> tuple[float, float]:
    """The two `"extended_join"` columns in metres."""
    obs = core.observe()[0][0]
    assert obs.shape == (19,)
    raw = obs * JOIN_SCALE
    return float(raw[_J["lead_gap_at_join"]]), float(raw[_J["lag_gap_at_join"]])


def test_gaps_at_join_extrapolate_the_gap_vehicles_to_the_join_point():
    # ego at -60 m, 20 m/s; the gap-front 3 m ahead at 25 m/s, the gap-back 20 m behind at 22 m/s
    core = scene(ego=(-60.0, 20.0), right=[(-57.0, 25.0), (-80.0, 22.0)], overrides=JOIN)
    t = (core.cfg.x_overlap_m + 60.0) / 20.0
    lead, lag = _join_gaps(core)
    assert lead == pytest.approx(3.0 + 5.0 * t - L_M, abs=1e-4)
    assert lag == pytest.approx(20.0 - 2.0 * t - L_M, abs=1e-4)
    # the first 17 columns are those of "extended_accel"
    accel = scene(
        ego=(-60.0, 20.0),
        right=[(-57.0, 25.0), (-80.0, 22.0)],
        overrides={"ego.observation": "extended_accel"},
    )
    assert np.array_equal(core.observe()[0][:, :17], accel.observe()[0])


def test_gaps_at_join_flag_an_overlap_and_missing_vehicles():
    # a car 30 m behind closing at 10 m/s, 3 s from the join: it would be 0 m behind... overlap
    core = scene(ego=(-110.0, 20.0), right=[(-140.0, 30.0)], overrides=JOIN)
    t = (core.cfg.x_overlap_m + 110.0) / 20.0
    lead, lag = _join_gaps(core)
    assert lead == pytest.approx(RANGE_M)  # no gap-front vehicle
    assert lag == pytest.approx(max(30.0 - 10.0 * t - L_M, -RANGE_M), abs=1e-4) and lag < 0.0
    # past the join point the time is 0: the current bumper gaps
    core = scene(ego=(10.0, 20.0), right=[(40.0, 20.0), (-10.0, 25.0)], overrides=JOIN)
    assert _join_gaps(core) == pytest.approx((30.0 - L_M, 20.0 - L_M), abs=1e-4)


def check_gaps_at_join(obs: np.ndarray, cfg: ScenarioConfig) -> int:
    """The `"extended_join"` gaps of observations [..., 19] against the same rows' gap vehicles
    (the paper's features) and time to the join; returns the rows with both gap vehicles
    present (a missing one reads +sensing range)."""
    raw = obs.reshape(-1, obs.shape[-1]).astype(np.float64) * JOIN_SCALE  # SI units
    f = {name: raw[:, i] for name, i in _J.items()}
    x, v, t = f["ego_position"], f["ego_speed"], f["time_to_join"]
    rng, length = cfg.ego.sensing_range_m, cfg.vehicle.length_m
    lead = np.clip(f["front_position"] - x + (f["front_speed"] - v) * t - length, -rng, rng)
    lag = np.clip(x - f["back_position"] + (v - f["back_speed"]) * t - length, -rng, rng)
    got_lead, got_lag = f["lead_gap_at_join"], f["lag_gap_at_join"]
    ok_lead = np.isclose(got_lead, lead, atol=2e-3) | np.isclose(got_lead, rng, atol=2e-3)
    ok_lag = np.isclose(got_lag, lag, atol=2e-3) | np.isclose(got_lag, rng, atol=2e-3)
    assert ok_lead.all() and ok_lag.all()
    both = np.isclose(got_lead, lead, atol=2e-3) & np.isclose(got_lag, lag, atol=2e-3)
    return int((both & (np.abs(lead) < rng - 1.0) & (np.abs(lag) < rng - 1.0)).sum())


def test_gaps_at_join_follow_the_reported_gap_in_traffic():
    env = BatchedMergeEnv(
        num_worlds=8, seed=3, overrides={**JOIN, "traffic.flow_vph_per_lane": 1500}
    )
    check_env_specs(env, seed=3)
    hold = torch.zeros(8, 1)  # a fixed command: the same traffic on every run
    td = env.rollout(60, policy=lambda td: td.set("action", hold), break_when_any_done=False)
    obs = td["next", "observation"].numpy()
    assert obs.shape == (8, 60, 19)
    assert check_gaps_at_join(obs, env.core.cfg) >= 100
