"""Ramp flow (`ramp.flow_vph > 0`): many merging vehicles at once, each an agent, the merge
measured as a whole; the paper's one-ramp-vehicle mode untouched."""

import json
import math

import numpy as np
import pytest

from marlmerge.cli import main
from marlmerge.config import ScenarioConfig
from marlmerge.evaluation.ramp_flow import (
    merge_line,
    per_1000_interval,
    ramp_commands,
    run_ramp_flow,
)
from marlmerge.evaluation.registry import policy_from_spec
from marlmerge.sim import TrafficCore
from marlmerge.sim import layout as L
from marlmerge.validation.scenarios import drawn_ramp_arrivals

FLOW = ScenarioConfig().replace(**{"ramp.flow_vph": 600.0})


def _drive(core: TrafficCore, n: int, policy: object) -> list[np.ndarray]:
    """n control steps, every ramp agent driven by `policy`; the agents' observations."""
    seen = []
    nan = np.full(core.batch_size, np.nan)
    for _ in range(n):
        roster, obs = core.ramp_agents(8)
        cmd = ramp_commands(policy, obs, roster.mask)
        core.rollout(nan, roster=roster, roster_accel=cmd[..., 0], roster_join=cmd[..., 1])
        seen.append(obs.copy())
    return seen


@pytest.fixture(scope="module")
def gap_core() -> TrafficCore:
    core = TrafficCore(FLOW, batch_size=3, seed=0)
    _drive(core, 600, policy_from_spec("gap", FLOW))  # 240 s
    return core


def test_no_ramp_vehicle_is_dropped(gap_core: TrafficCore):
    st = gap_core.state
    for b in range(3):
        drawn = drawn_ramp_arrivals(FLOW, np.random.SeedSequence(0, spawn_key=(b,)), 300.0)
        due = int((drawn[:, 0] <= st.t_s[b] + 1e-9).sum())
        assert st.ramp_entered[b] + st.ramp_queue[b] == due  # entered or waiting, in order
    # every vehicle that entered is on the ramp, on the road before the merge point, past it,
    # or towed away after a collision (gap acceptance collides now and then: a forced join)
    on_lanes = (st.from_ramp & st.active & (st.lane >= 0)).sum(axis=1)
    assert np.array_equal(st.ramp_entered, st.n_on_ramp + on_lanes + st.ramp_passed + st.ramp_towed)
    assert np.all(st.ramp_towed <= 2 * st.ramp_collisions)
    assert st.ramp_collisions.sum() <= 2 and st.background_collisions.sum() == 0
    assert st.ramp_passed.min() > 30
    gap_core._check_lanes()  # the ramp list holds exactly the ramp's vehicles, in order


def test_ramp_agents_see_the_paper_state(gap_core: TrafficCore):
    roster, obs = gap_core.ramp_agents(8)
    st, cfg = gap_core.state, FLOW
    rng, v_limit = cfg.ego.sensing_range_m, cfg.road.speed_limit_mps
    checked = 0
    for b, j in zip(*np.nonzero(roster.mask), strict=True):
        s = roster.slots[b, j]
        assert st.lane[b, s] == L.RAMP and st.vehicle_id[b, s] == roster.ids[b, j]
        x, v = st.x_m[b, s], st.v_mps[b, s]
        right = st.active[b] & (st.lane[b] == L.RIGHT)
        ahead = right & (st.x_m[b] >= x) & (st.x_m[b] - x <= rng)
        behind = right & (st.x_m[b] < x) & (x - st.x_m[b] <= rng)
        x_f, v_f = x + rng, v_limit
        if ahead.any():
            i = np.flatnonzero(ahead)[np.argmin(st.x_m[b][ahead])]
            x_f, v_f = st.x_m[b, i], st.v_mps[b, i]
        x_b, v_b = x - rng, v_limit
        if behind.any():
            i = np.flatnonzero(behind)[np.argmax(st.x_m[b][behind])]
            x_b, v_b = st.x_m[b, i], st.v_mps[b, i]
        want = np.array([v / 30, x / 100, v_f / 30, x_f / 100, v_b / 30, x_b / 100, v_limit / 30])
        np.testing.assert_allclose(obs[b, j], want, rtol=1e-12)
        checked += 1
    assert checked >= 1
    assert np.all(obs[~roster.mask] == 0.0)


def test_same_seed_same_flow_and_state_resumes_exactly():
    policy = policy_from_spec("gap", FLOW)
    a, b = TrafficCore(FLOW, batch_size=2, seed=3), TrafficCore(FLOW, batch_size=2, seed=3)
    _drive(a, 100, policy)
    _drive(b, 100, policy)
    saved = a.state_dict()
    expected = _drive(a, 150, policy)
    other = TrafficCore(FLOW, batch_size=2, seed=99)
    other.load_state_dict(saved)
    got = _drive(other, 150, policy)
    assert all(np.array_equal(x, y) for x, y in zip(expected, got, strict=True))
    assert np.array_equal(a.vf, other.vf) and np.array_equal(a.lanes, other.lanes)
    assert np.array_equal(_drive(b, 150, policy)[-1], expected[-1])


def test_merging_blind_collides_where_gap_acceptance_does_not(gap_core: TrafficCore):
    core = TrafficCore(FLOW, batch_size=3, seed=0)
    _drive(core, 600, policy_from_spec("idm", FLOW))  # ignores the merge: forced joins
    assert core.state.ramp_collisions.sum() >= 5 * max(gap_core.state.ramp_collisions.sum(), 1)


def test_a_ramp_queue_follows_its_leader_by_idm():
    """A ramp vehicle stopped before the join holds the ones behind it: they stop behind it (IDM
    caps their commands), nobody collides on the ramp, and the arrivals that find no room wait
    at the ramp's entrance."""
    core = TrafficCore(FLOW.replace(**{"traffic.flow_vph_per_lane": 0.0}), batch_size=1, seed=0)
    nan = np.full(1, np.nan)
    for _ in range(400):
        roster, _ = core.ramp_agents(8)
        cmd = np.where(roster.mask, 2.5, np.nan)
        first = roster.slots[0, 0]
        if roster.mask[0, 0] and core.state.x_m[0, first] > -200.0:
            cmd[0, 0] = -4.5  # the first vehicle stops before it joins
        core.rollout(nan, roster=roster, roster_accel=cmd)
    st = core.state
    assert st.ramp_collisions[0] == 0 and st.n_on_ramp[0] >= 2 and st.ramp_queue[0] >= 10
    slots = core.lanes[0, L.RAMP_LIST, : st.n_on_ramp[0]]
    gaps = -np.diff(st.x_m[0, slots]) - FLOW.vehicle.length_m
    assert np.all(gaps >= FLOW.driver.min_gap_m * 0.9) and np.all(st.v_mps[0, slots] < 0.1)


def test_the_paper_mode_keeps_an_empty_ramp_list():
    core = TrafficCore(ScenarioConfig(), batch_size=2, seed=0)
    for _ in range(50):
        out = core.rollout(np.full(2, 1.0))
        core.next_ego(out.ego_outcome != 0)
    assert np.all(core.state.n_on_ramp == 0) and np.all(core.lanes[:, L.RAMP_LIST] == -1)
    assert np.all(core.state.ramp_entered == 0)


def test_ramp_flow_refuses_what_belongs_to_the_one_ego():
    core = TrafficCore(FLOW, batch_size=1, seed=0)
    with pytest.raises(ValueError, match=r"next_ego: ramp\.flow_vph = 600"):
        core.next_ego(np.ones(1, dtype=bool))
    from marlmerge.views.pettingzoo_env import RampMergeParallelEnv
    from marlmerge.views.torchrl_env import BatchedMergeEnv

    for make in (lambda: RampMergeParallelEnv(FLOW), lambda: BatchedMergeEnv(FLOW, 2)):
        with pytest.raises(ValueError, match=r"ramp\.flow_vph = 600.*no ego"):
            make()
    for key, value in (("sensing.latency_s", 0.2), ("ego.safety_filter", True)):
        with pytest.raises(ValueError, match=key.split(".")[0]):
            FLOW.replace(**{key: value})
    with pytest.raises(ValueError, match=r"ramp\.flow_vph must be in \[0, 3600\]"):
        ScenarioConfig().replace(**{"ramp.flow_vph": -5.0})


def test_rampflow_command_prints_the_merge(capsys):
    assert main(["rampflow", "gap", "--ramp-flow", "400,800", "--hours", "0.05",
                 "--skip", "60", "--worlds", "2"]) == 0  # fmt: skip
    rows = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [r["ramp_demand_vph"] for r in rows] == [400.0, 800.0]
    assert all(r["merged_vph"] > 0 and r["ramp_collisions"] == 0 for r in rows)
    for bad in ("0", "abc", "600,5000"):
        assert main(["rampflow", "gap", "--ramp-flow", bad]) != 0
        err = capsys.readouterr().err
        assert "--ramp-flow" in err and repr(bad) in err
    assert main(["rampflow", "gap"]) != 0  # the default scenario has no ramp flow
    assert "give the demand(s)" in capsys.readouterr().err


def test_run_ramp_flow_result_is_reproducible():
    a = run_ramp_flow(FLOW, "gap", hours=0.05, worlds=2, seed=1, skip_s=60)
    b = run_ramp_flow(FLOW, "gap", hours=0.05, worlds=2, seed=1, skip_s=60)
    assert {**a.to_dict(), "wall_s": 0} == {**b.to_dict(), "wall_s": 0}
    lo, hi = a.merged_vph_ci95
    assert lo <= a.merged_vph <= hi and a.ramp_delay_s > 0
    merged = round(a.merged_vph * a.worlds * a.measured_s / 3600.0)
    lo, hi = a.ramp_collisions_per_1000_ci95  # none collided: 0 to about 3.84 in merged + 3.84
    assert a.ramp_collisions == 0 and lo == 0.0
    assert hi == pytest.approx(1000.0 * 3.8415 / (merged + 3.8415), rel=1e-3)
    assert f"0 collisions (0.00 [0.00, {hi:.2f}] per 1,000 merged)" in merge_line(a.to_dict())


def test_one_world_has_no_interval_over_worlds():
    row = run_ramp_flow(FLOW, "gap", hours=0.05, worlds=1, seed=1, skip_s=60).to_dict()
    assert row["merged_vph"] > 0 and row["ramp_delay_s"] > 0
    assert row["merged_vph_ci95"] == (None, None) == row["ramp_delay_s_ci95"]  # not [x, x]
    lo, hi = row["ramp_collisions_per_1000_ci95"]  # counts of vehicles still have one
    line = merge_line(row)
    assert f"merged {row['merged_vph']:.0f} veh/h, ramp delay {row['ramp_delay_s']:.1f} s" in line
    assert f"[{lo:.2f}, {hi:.2f}] per 1,000 merged" in line


def test_collisions_per_1000_merged_carry_a_wilson_interval():
    lo, hi = per_1000_interval(2, 2400)  # 0.83 per 1,000
    assert lo == pytest.approx(0.2286, abs=1e-3) and hi == pytest.approx(3.0335, abs=1e-3)
    # 5 collided, 3 merged: 5 trials
    assert per_1000_interval(5, 3) == (pytest.approx(565.5, abs=0.1), 1000.0)
    assert all(math.isnan(b) for b in per_1000_interval(0, 0))  # nothing merged: undefined


def test_joining_when_safe_never_collides_and_stops_at_the_lanes_end():
    """`ramp.join = "when_safe"`: vehicles that ignore the merge (IDM) join only into safe gaps,
    so nobody collides where forced joins do; a vehicle that finds no gap stops before the
    acceleration lane's end (x = 0) and waits there."""
    dense = FLOW.replace(**{"traffic.flow_vph_per_lane": 1200.0})
    idm = policy_from_spec("idm", dense)
    forced = TrafficCore(dense, batch_size=2, seed=2)
    _drive(forced, 500, idm)
    safe = TrafficCore(dense.replace(**{"ramp.join": "when_safe"}), batch_size=2, seed=2)
    stopped_at_end = 0
    nan = np.full(2, np.nan)
    for _ in range(500):
        roster, obs = safe.ramp_agents(8)
        cmd = ramp_commands(idm, obs, roster.mask)[..., 0]
        safe.rollout(nan, roster=roster, roster_accel=cmd)
        st = safe.state
        on_ramp = st.active & (st.lane == L.RAMP)
        assert np.all(st.x_m[on_ramp] < 0.0)  # nobody drives past the lane's end
        stopped_at_end += int((on_ramp & (st.x_m > -10.0) & (st.v_mps < 0.1)).sum())
    assert forced.state.ramp_collisions.sum() >= 5
    assert safe.state.ramp_collisions.sum() == 0 and safe.state.ramp_joined.min() > 10
    assert stopped_at_end > 0
    st = safe.state  # no collisions: every joined vehicle is past x = 0 or on its way there
    on_lanes = (st.from_ramp & st.active & (st.lane >= 0)).sum(axis=1)
    assert np.array_equal(st.ramp_joined, st.ramp_passed + on_lanes)


def test_a_join_mode_without_ramp_flow_is_refused():
    with pytest.raises(ValueError, match=r"ramp\.join = 'when_safe' needs ramp flow"):
        ScenarioConfig().replace(**{"ramp.join": "when_safe"})
    with pytest.raises(ValueError, match=r"ramp\.join must be one of 'forced', 'when_safe'"):
        FLOW.replace(**{"ramp.join": "chosen"})


@pytest.mark.parametrize("entrance", ["drawn", "best"])
def test_the_sumo_merge_reference_covers_the_grid(entrance):
    from marlmerge.validation.merge import MERGE_GRID, REFERENCES

    saved = json.loads(REFERENCES[entrance].read_text())
    assert set(saved["cells"]) == {f"{r:g}/{m:g}" for r, m in MERGE_GRID}
    for cell in saved["cells"].values():
        assert cell["merged_vph"] > 0 and cell["ramp_delay_s"] > 0
        assert cell["lane_changes_per_hour"] > 0  # SUMO's mainline measured as ours
        assert 0.0 <= cell["entrance_lane_change_share"] <= 1.0
        assert 0.0 <= cell["braking_over_b_share"] <= 1.0


@pytest.mark.slow
def test_validate_merge_against_the_reference_writes_its_report(tmp_path, capsys):
    code = main(["validate", "--merge", "--reference", "--out", str(tmp_path)])
    result = json.loads((tmp_path / "results.json").read_text())
    assert code == (0 if result["all_targets_met"] else 1)
    assert result["sumo_ran"] is False
    for name in ("gap_forced", "idm_when_safe"):
        cells = result[name]["cells"]
        assert len(cells) == 12
        # below saturation both simulators pass what arrives: merged flow agrees at low demand
        assert cells["200/600"]["merged_vph_ok"] and cells["600/600"]["merged_vph_ok"]
    assert "Merge capacity" in (tmp_path / "README.md").read_text()
    for name in ("gap_forced", "idm_when_safe"):
        share = result[name]["cells"]["600/1200"]["entrance_share_ratio"]
        assert share is not None and share > 0
    assert "idm_when_safe: merged flow within 10 %" in capsys.readouterr().out


def test_validate_merge_picks_the_reference_of_the_entrance_rule(tmp_path, monkeypatch):
    from marlmerge.validation import merge

    best = ScenarioConfig().replace(**{"traffic.entrance_lane": "best"})
    with pytest.raises(ValueError, match="--update-reference needs SUMO"):
        merge.validate_merge(best.replace(**{"ramp.flow_vph": 10.0}), tmp_path, True, True)
    # the entrance rule picks the committed SUMO side (the grid itself is the slow test above)
    seen = []
    monkeypatch.setattr(
        merge, "run_grid", lambda cfg, which, seed=0: seen.append(cfg.traffic.entrance_lane) or {}
    )
    result = merge.validate_merge(best, tmp_path)
    assert seen == ["best", "best"] and result["entrance_lane"] == "best"
    assert 'departLane="best"' in (tmp_path / "README.md").read_text()


def test_ramp_flow_pettingzoo_agents_appear_and_leave():
    from pettingzoo.test import api_test, parallel_api_test

    from marlmerge import ramp_flow_env, ramp_flow_parallel_env

    over = {"ramp.flow_vph": 900.0}
    parallel_api_test(ramp_flow_parallel_env(overrides=over, max_cycles=250), num_cycles=250)
    api_test(ramp_flow_env(overrides=over, max_cycles=150), num_cycles=150)
    env = ramp_flow_parallel_env(overrides=over, max_cycles=400)
    obs, _ = env.reset(seed=3)
    gap = policy_from_spec("gap", env.cfg)
    seen, finished, peak, outcomes = set(), set(), 0, []
    penalty = env.cfg.reward.collision_penalty
    while env.agents:
        peak = max(peak, len(env.agents))
        x = np.stack([obs[a] for a in env.agents])[None]  # [1, n, 7]
        cmd = ramp_commands(gap, x, np.ones(x.shape[:2], dtype=bool))[0, :, :1]
        obs, rewards, term, trunc, infos = env.step(dict(zip(env.agents, cmd, strict=True)))
        for a in rewards:
            assert a not in finished  # no name comes back
            seen.add(a)
            assert infos[a]["reward_collision"] == (-penalty if infos[a]["outcome"] == 2 else 0.0)
            assert rewards[a] <= 0.0 and rewards[a] == pytest.approx(
                sum(v for k, v in infos[a].items() if k.startswith("reward_"))
            )
            if term[a] or trunc[a]:
                finished.add(a)
                outcomes.append(infos[a]["outcome"])
    assert len(seen) >= 20 and peak >= 2  # many merging vehicles, several at once
    assert outcomes.count(1) >= 0.8 * len(outcomes)  # gap acceptance mostly merges
    assert [a for a in env.possible_agents if a in seen] == env.possible_agents[: len(seen)]
    extended = {**over, "ego.observation": "extended_accel"}  # the agents see the ego's layout
    parallel_api_test(ramp_flow_parallel_env(overrides=extended, max_cycles=100), num_cycles=100)
    assert ramp_flow_parallel_env(overrides=extended).observation_space("ramp_0").shape == (17,)
    with pytest.raises(ValueError, match=r"needs ramp flow: ramp\.flow_vph = 0"):
        ramp_flow_parallel_env()
    env.reset(seed=1)
    with pytest.raises(ValueError, match=r"action of 'ramp_0' must be finite"):
        env.step({a: np.array([np.nan]) for a in env.agents})


def test_a_version_2_state_still_loads():
    """A state saved before ramp flow (version 2: no ramp rows, two lane lists) continues bit for
    bit."""
    core = TrafficCore(ScenarioConfig(), batch_size=2, seed=1)
    for _ in range(20):
        out = core.rollout(np.full(2, 0.5))
        core.next_ego(out.ego_outcome != 0)
    saved = core.state_dict()
    v2 = {**saved, "version": 2, "arrays": dict(saved["arrays"])}
    for name, rows in (("vi", L.VI_ROWS_V2), ("wf", L.WF_ROWS_V2), ("wi", L.WI_ROWS_V2)):
        v2["arrays"][name] = saved["arrays"][name][:, :rows]
    v2["arrays"]["lanes"] = saved["arrays"]["lanes"][:, :2]
    v2["arrays"]["vf"] = saved["arrays"]["vf"][:, : L.VF_ROWS_V3]  # no attention lapses then
    other = TrafficCore(ScenarioConfig(), batch_size=2, seed=9)
    other.load_state_dict(v2)
    for _ in range(30):
        a, b = core.rollout(np.full(2, 1.0)), other.rollout(np.full(2, 1.0))
        assert np.array_equal(a.ego_obs, b.ego_obs)
        core.next_ego(a.ego_outcome != 0)
        other.next_ego(b.ego_outcome != 0)
    v2["arrays"]["wi"] = v2["arrays"]["wi"][:, :-1]
    with pytest.raises(ValueError, match="array 'wi' has shape"):
        other.load_state_dict(v2)


@pytest.mark.slow
def test_a_mix_of_scripted_and_learned_merging_vehicles():
    """`SPEC=SHARE,...`: each ramp vehicle draws its driver once; a mix lies between its parts."""
    runs = {
        d: run_ramp_flow(FLOW, d, hours=0.1, worlds=2, seed=3, skip_s=60)
        for d in ("gap", "idm", "gap=0.5,idm=0.5")
    }
    coll = {d: r.ramp_collisions for d, r in runs.items()}
    assert coll["gap"] < coll["gap=0.5,idm=0.5"] < coll["idm"]
    again = run_ramp_flow(FLOW, "gap=0.5,idm=0.5", hours=0.1, worlds=2, seed=3, skip_s=60)
    assert again.ramp_collisions == coll["gap=0.5,idm=0.5"]
    for bad, match in (("gap=0.5,idm=0.4", "sum to 0.9"), ("gap=2", "not SPEC=SHARE")):
        with pytest.raises(ValueError, match=match):
            run_ramp_flow(FLOW, bad, hours=0.1)


def _check_extended(core: TrafficCore, cfg: ScenarioConfig) -> int:
    """Each ramp agent's left-lane, time and command columns against the state; how many."""
    roster, obs = core.ramp_agents(8)
    st, rng, lim = core.state, cfg.ego.sensing_range_m, cfg.road.speed_limit_mps
    checked = 0
    for b, j in zip(*np.nonzero(roster.mask), strict=True):
        s = roster.slots[b, j]
        x, v = st.x_m[b, s], st.v_mps[b, s]
        left = st.active[b] & (st.lane[b] == L.LEFT)
        ahead = left & (st.x_m[b] >= x) & (st.x_m[b] - x <= rng)
        behind = left & (st.x_m[b] < x) & (x - st.x_m[b] <= rng)
        want_f = (rng, lim)
        if ahead.any():
            i = np.flatnonzero(ahead)[np.argmin(st.x_m[b][ahead])]
            want_f = (st.x_m[b, i] - x, st.v_mps[b, i])
        want_b = (-rng, lim)
        if behind.any():
            i = np.flatnonzero(behind)[np.argmax(st.x_m[b][behind])]
            want_b = (st.x_m[b, i] - x, st.v_mps[b, i])
        np.testing.assert_allclose(obs[b, j, 10:14], [want_f[0] / 100, want_f[1] / 30,
                                   want_b[0] / 100, want_b[1] / 30], rtol=1e-12)  # fmt: skip
        to_join = min((cfg.x_overlap_m - x) / max(v, 1e-9), 10.0) if x < cfg.x_overlap_m else 0.0
        assert obs[b, j, 14] == pytest.approx(to_join / 10.0, rel=1e-9)
        assert obs[b, j, 16] == core.vf[b, L.VF_ACC, s] / 5.0  # its last command
        checked += 1
    assert np.all(obs[~roster.mask] == 0.0)
    return checked


def test_ramp_agents_see_the_extended_layout_from_where_they_are():
    """With `ego.observation = "extended_accel"` each ramp agent sees the paper's seven features
    as before, then the left lane, the times to the join and merge points and its last command,
    all measured from itself."""
    from marlmerge.sim.observation import ramp_agent_features

    cfg = FLOW.replace(**{"ego.observation": "extended_accel"})
    core = TrafficCore(cfg, batch_size=3, seed=0)
    paper = TrafficCore(FLOW, batch_size=3, seed=0)
    policy = policy_from_spec("gap", FLOW)
    nan, checked = np.full(3, np.nan), 0
    for step in range(300):
        (roster, obs), (_, obs7) = core.ramp_agents(8), paper.ramp_agents(8)
        assert obs.shape[2] == len(ramp_agent_features(cfg)) == 17
        np.testing.assert_array_equal(obs[..., :7], obs7)  # the same traffic, seen the same way
        cmd = ramp_commands(policy, obs, roster.mask)
        core.rollout(nan, roster=roster, roster_accel=cmd[..., 0])
        paper.rollout(nan, roster=roster, roster_accel=cmd[..., 0])
        if step % 25 == 24:
            checked += _check_extended(core, cfg)
    assert checked >= 10


def test_ramp_agents_see_their_gaps_at_the_join():
    """With `ego.observation = "extended_join"` each ramp agent's last two columns extrapolate
    its own gap vehicles to its own arrival at the join point."""
    from test_observation_layouts import check_gaps_at_join

    cfg = FLOW.replace(**{"ego.observation": "extended_join"})
    core = TrafficCore(cfg, batch_size=3, seed=0)
    policy = policy_from_spec("gap", FLOW)
    nan, checked = np.full(3, np.nan), 0
    for _ in range(200):
        roster, obs = core.ramp_agents(8)
        assert obs.shape[2] == 19
        checked += check_gaps_at_join(obs[roster.mask.astype(bool)], cfg)
        cmd = ramp_commands(policy, obs, roster.mask)
        core.rollout(nan, roster=roster, roster_accel=cmd[..., 0])
    assert checked >= 50


def test_a_shield_that_watches_the_left_lane_drives_ramp_agents():
    """`gap@shield-left` needs the extended layout: the ramp's agents are simulated with it, and
    a rule beside it in a mix drives in the same layout."""
    from marlmerge.evaluation.ramp_flow import agents_scenario

    policies, cfg = agents_scenario(FLOW, ["gap@shield-left", "gap"])
    assert cfg.ego.observation == "extended" and len(policies) == 2
    r = run_ramp_flow(FLOW, "gap@shield-left=0.5,gap=0.5", hours=0.05, worlds=2, seed=1, skip_s=60)
    again = run_ramp_flow(FLOW, "gap@shield-left=0.5,gap=0.5", hours=0.05, worlds=2, seed=1,
                          skip_s=60)  # fmt: skip
    assert r.merged_vph > 0 and r.to_dict() | {"wall_s": 0} == again.to_dict() | {"wall_s": 0}


def test_the_report_says_how_often_the_shield_changed_the_commands():
    """Behind a shield the result counts the ramp commands it judged in the measurement window
    and the share it changed: few of gap acceptance's own, many of a vehicle that holds its
    speed into the merge; without a shield both are None."""
    gap = run_ramp_flow(FLOW, "gap@shield", hours=0.05, worlds=2, seed=1, skip_s=60)
    hold = run_ramp_flow(FLOW, "hold@shield", hours=0.05, worlds=2, seed=1, skip_s=60)
    bare = run_ramp_flow(FLOW, "gap", hours=0.05, worlds=2, seed=1, skip_s=60)
    # 2 worlds x 180 s at 600 veh/h: ~60 vehicles, each judged for ~10 s at 2 commands a second
    assert gap.shield_judged > 500 and hold.shield_judged > 500
    assert gap.shield_changed_share < 0.1 < hold.shield_changed_share
    assert bare.shield_judged is None and bare.shield_changed_share is None
    assert "the shield changed" in merge_line(hold.to_dict())
    assert "the shield" not in merge_line(bare.to_dict())
