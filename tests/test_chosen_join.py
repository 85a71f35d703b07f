"""`ego.join = "chosen"`: the merging vehicle decides where it changes into the right lane (a
second action component), and stops at the acceleration lane's end if it has not joined."""

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test
from torchrl.envs.utils import check_env_specs

from marlmerge.config import ScenarioConfig
from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.ramp_flow import ramp_commands
from marlmerge.evaluation.registry import policy_from_spec
from marlmerge.evaluation.rollout import rollout_first_egos
from marlmerge.sim import OUTCOME_COLLISION, TrafficCore
from marlmerge.sim import layout as L
from marlmerge.sim.step import LANE_END_STOP_M
from marlmerge.views.gym_env import RampMergeEnv
from marlmerge.views.pettingzoo_env import EGO_AGENT, parallel_env
from marlmerge.views.ramp_flow_env import ramp_flow_parallel_env
from marlmerge.views.ramp_flow_torchrl import RampFlowTorchEnv
from marlmerge.views.torchrl_env import BatchedMergeEnv

CHOSEN = ScenarioConfig().replace(**{"ego.join": "chosen"})
FLOW_CHOSEN = CHOSEN.replace(**{"ramp.flow_vph": 600.0})


def _ego(core: TrafficCore) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[B] the ego's position (m), speed (m/s) and lane (-1: the ramp)."""
    return core.vf[:, L.VF_X, L.EGO], core.vf[:, L.VF_V, L.EGO], core.vi[:, L.VI_LANE, L.EGO]


def test_the_join_is_a_checked_key():
    with pytest.raises(ValueError, match="ego.join must be one of 'forced', 'chosen'"):
        ScenarioConfig().replace(**{"ego.join": "early"})
    with pytest.raises(ValueError, match="ego.safety_filter"):
        CHOSEN.replace(**{"ego.safety_filter": True})
    assert resolve_config("chosen_join").ego.join == "chosen"


def test_a_vehicle_that_does_not_join_stops_at_the_lanes_end():
    core = TrafficCore(CHOSEN, batch_size=4, seed=0)
    lo = CHOSEN.ego.accel_bounds_mps2[0]
    on_ramp = []
    for _ in range(60):  # 24 s: every ego reaches the lane's end and stands there
        out = core.rollout(np.full(4, 2.5), ego_join=np.full(4, -1.0))
        x, v, lane = _ego(core)
        assert np.all(lane == L.RAMP) and np.all(x < -LANE_END_STOP_M + 0.05)  # inches up to it
        assert np.all(core.vf[:, L.VF_A, L.EGO] >= lo - 0.6)  # braking as its bounds allow
        on_ramp.append(out.ego_obs[:, -1])
    assert np.all(np.array(on_ramp) == 1.0)
    assert np.all(v < 0.5) and np.all(x > -LANE_END_STOP_M - 0.5)


def test_a_join_command_counts_only_inside_the_merge_zone():
    core = TrafficCore(CHOSEN, batch_size=4, seed=1)
    zone = CHOSEN.road.x_zone_start_m
    joined_at = np.full(4, np.nan)
    for _ in range(300):  # simulator steps
        before = _ego(core)[0].copy()
        out = core.rollout(np.zeros(4), k=1, ego_join=np.ones(4))
        x, _, lane = _ego(core)
        new = (lane == L.RIGHT) & np.isnan(joined_at)
        joined_at[new] = x[new]
        assert np.all(before[new] < zone + 5.0)  # the first step inside the zone
        assert np.all(out.ego_obs[lane == L.RIGHT, -1] == 0.0)
        if not np.isnan(joined_at).any():
            break
    assert np.all(joined_at >= zone) and np.all(joined_at < CHOSEN.x_overlap_m)


def test_without_a_join_command_the_vehicle_is_joined_by_force_as_before():
    forced = TrafficCore(ScenarioConfig(), batch_size=4, seed=2)
    chosen = TrafficCore(CHOSEN, batch_size=4, seed=2)
    rng = np.random.default_rng(0)
    for _ in range(80):
        a = rng.uniform(-2.0, 2.0, 4)
        one, two = forced.rollout(a), chosen.rollout(a)  # chosen: the join is NaN
        assert np.array_equal(forced.vf, chosen.vf) and np.array_equal(forced.vi, chosen.vi)
        assert np.array_equal(one.ego_obs, two.ego_obs[:, :-1])


def test_join_commands_change_nothing_with_forced_joins():
    a_core, b_core = (TrafficCore(ScenarioConfig(), batch_size=3, seed=5) for _ in range(2))
    for i in range(50):
        a_core.rollout(np.full(3, 0.5))
        b_core.rollout(np.full(3, 0.5), ego_join=np.full(3, 1.0 if i % 2 else -1.0))
    assert np.array_equal(a_core.vf, b_core.vf)


def test_gap_acceptance_chooses_safe_joins():
    records, _ = rollout_first_egos(policy_from_spec("gap", CHOSEN), CHOSEN, 150, seed=300)
    assert (records["outcome"] == OUTCOME_COLLISION).sum() == 0
    assert (records["outcome"] == 1).mean() >= 0.97


def test_the_views_take_two_action_components():
    env = parallel_env(CHOSEN, control="ego")
    parallel_api_test(env, num_cycles=200)
    assert env.action_space(EGO_AGENT).shape == (2,)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action of 'ramp_0' must have shape \\(2,\\)"):
        env.step({EGO_AGENT: np.zeros(1, np.float32)})
    gym_env = RampMergeEnv(CHOSEN)
    check_env(gym_env, skip_render_check=True)
    assert gym_env.observation_space.shape == (8,)
    torch_env = BatchedMergeEnv(CHOSEN, num_worlds=3, seed=0)
    check_env_specs(torch_env)
    td = torch_env.reset()
    td.set("action", torch.tensor([[0.0, 1.0], [0.0, -1.0], [float("nan"), 0.0]]))
    with pytest.raises(ValueError, match="world 2 must be finite"):
        torch_env.step(td)


def test_ramp_flow_agents_choose_their_joins():
    env = ramp_flow_parallel_env(FLOW_CHOSEN, max_cycles=150)
    parallel_api_test(env, num_cycles=150)
    assert env.action_space("ramp_0").shape == (2,)
    assert env.observation_space("ramp_0").shape == (8,)
    torch_env = RampFlowTorchEnv(FLOW_CHOSEN, num_worlds=2, seed=0, max_agents=4)
    check_env_specs(torch_env)
    # vehicles that never join queue at the lane's end; none is dropped, none passes
    core = TrafficCore(FLOW_CHOSEN, batch_size=2, seed=3)
    gap = policy_from_spec("gap", FLOW_CHOSEN)
    nan = np.full(2, np.nan)
    st = core.state  # the warm-up's ramp vehicles, without a join command, joined by force
    joined, entered = st.ramp_joined.copy(), st.ramp_entered.copy()
    for _ in range(300):
        roster, obs = core.ramp_agents(16)
        cmd = ramp_commands(gap, obs, roster.mask)
        join = np.where(roster.mask, -1.0, np.nan)
        core.rollout(nan, roster=roster, roster_accel=cmd[..., 0], roster_join=join)
    st = core.state
    assert np.array_equal(st.ramp_joined, joined) and st.ramp_collisions.sum() == 0
    assert np.all(st.ramp_entered - entered <= st.n_on_ramp) and st.n_on_ramp.min() >= 2
    x_ramp = np.where(st.active & (st.lane == L.RAMP), st.x_m, -np.inf)
    assert x_ramp.max() < -LANE_END_STOP_M + 0.05


def test_ramp_flow_with_gap_acceptance_choosing_joins():
    core = TrafficCore(FLOW_CHOSEN, batch_size=2, seed=4)
    gap = policy_from_spec("gap", FLOW_CHOSEN)
    nan = np.full(2, np.nan)
    warm = core.state.ramp_collisions.copy()  # the warm-up runs without join commands (forced)
    for _ in range(600):  # 240 s
        roster, obs = core.ramp_agents(16)
        cmd = ramp_commands(gap, obs, roster.mask)
        core.rollout(nan, roster=roster, roster_accel=cmd[..., 0], roster_join=cmd[..., 1])
    st = core.state
    assert st.ramp_passed.min() > 25  # of about 40 due
    assert np.array_equal(st.ramp_collisions, warm)
    core._check_lanes()


@pytest.mark.slow
def test_the_quadratic_learner_trains_a_chosen_join(tmp_path, capsys):
    from marlmerge.cli import main
    from marlmerge.learners.loading import load_policy

    out = tmp_path / "r"
    sets = ["--set", "scenario=chosen_join", "--set", "total_sim_steps=4096"]
    sets += ["--set", "eval_episodes=20", "--set", "update_path=fast", "--no-progress"]
    assert main(["train", "quick", *sets, "--out", str(out)]) == 0
    policy = load_policy(out)
    obs = torch.zeros(3, 8)
    act = policy(obs)
    assert act.shape == (3, 2) and (act[:, 1].abs() < 1.0).all()
    assert main(["evaluate", str(out), "--episodes", "10"]) == 0
    assert '"episodes": 10' in capsys.readouterr().out


def test_what_cannot_train_a_chosen_join_is_refused(tmp_path, capsys):
    from marlmerge.cli import main

    out = tmp_path / "r"
    assert main(["train", "dqn_quick", "--set", "scenario=chosen_join", "--out", str(out)]) == 2
    assert "only the quadratic-Q learner" in capsys.readouterr().err
    assert main(["train", "quick", "--set", "scenario=chosen_join", "--seeds", "0-1",
                 "--out", str(out)]) == 2  # fmt: skip
    assert "--seeds" in capsys.readouterr().err
    assert not out.exists()


def test_a_merge_where_nothing_merged_reports_undefined_values():
    import json

    from marlmerge.evaluation.merge_metrics import MergeTally
    from marlmerge.evaluation.ramp_flow import _COUNTERS, _result

    zeros = {k: np.zeros(2) for k in (*_COUNTERS, "ramp_max_queue")}
    after = {**zeros, "ramp_entered": np.array([30.0, 28.0]), "ramp_max_queue": np.array([9, 7])}
    tally = MergeTally(FLOW_CHOSEN, 2)  # nothing sampled: no lane change, no braking
    r = _result(FLOW_CHOSEN, "x", 2, 3600.0, zeros, after, np.ones(4), tally)
    row = r.to_dict()
    assert row["merged_vph"] == 0.0 and row["ramp_delay_s"] is None
    assert set(row["lane_change_shares"].values()) == {None}
    assert row["braking_over_b_share"] == 0.0 and row["cut_ins"] == 0
    assert row["ramp_collisions_per_1000"] is None and row["ramp_delay_s_ci95"] == (None, None)
    assert row["ramp_collisions_per_1000_ci95"] == (None, None)
    json.loads(json.dumps(row), parse_constant=lambda c: pytest.fail(f"not JSON: {c}"))


def test_the_distance_terms_weigh_the_gap_joined_not_the_one_passed():
    from marlmerge.sim.reward import EGO_TERMS

    gaps = [EGO_TERMS.index("gap_front"), EGO_TERMS.index("gap_back")]
    follower = CHOSEN.replace(**{"reward.w_back_headway": 1.0, "reward.w_back_ttc": 1.0})
    waiting = TrafficCore(follower, batch_size=8, seed=6)
    forced = TrafficCore(ScenarioConfig(), batch_size=8, seed=6)
    seen = 0.0
    for _ in range(40):  # every ego reaches the merge area beside the right lane's traffic
        out = waiting.rollout(np.zeros(8), ego_join=np.full(8, -1.0))
        assert np.all(out.ego_terms[:, gaps + [5, 6]] == 0.0)  # beside its gap: none
        on_ramp = forced.vi[:, L.VI_LANE, L.EGO] == L.RAMP
        seen += np.abs(forced.rollout(np.zeros(8)).ego_terms[on_ramp][:, gaps]).sum()
    assert seen > 0.0  # the paper's forced join weighs the gap it is heading for
    joined = TrafficCore(follower, batch_size=8, seed=6)
    total = 0.0
    for _ in range(40):
        total += np.abs(joined.rollout(np.zeros(8), ego_join=np.ones(8)).ego_terms[:, gaps]).sum()
    assert total > 0.0  # in the lane, its gaps count
