"""The merge's lane-change and braking tallies, and ramp flow in `evaluate` and the grid."""

import json

import numpy as np
import pytest

from marlmerge.cli import main
from marlmerge.config import ScenarioConfig
from marlmerge.evaluation.grid import run_grid
from marlmerge.evaluation.merge_metrics import SECTIONS, MergeTally, ratio_interval
from marlmerge.evaluation.ramp_flow import ramp_commands, run_ramp_flow
from marlmerge.evaluation.registry import parse_policy, policy_from_spec
from marlmerge.sim import TrafficCore

FLOW = ScenarioConfig().replace(**{"ramp.flow_vph": 600.0})


def _tally(cfg: ScenarioConfig, steps: int) -> tuple[MergeTally, list[tuple[int, int, int]]]:
    """A tally of `steps` control steps with gap acceptance on the ramp, and the lane changes
    seen by following every vehicle id by hand: (world, id, new lane)."""
    core = TrafficCore(cfg, batch_size=2, seed=4)
    tally = MergeTally(cfg, 2)
    policy = policy_from_spec("gap", cfg)
    nan = np.full(2, np.nan)
    lanes: list[dict[int, int]] = [{}, {}]
    seen = []
    for _ in range(steps):
        roster, obs = core.ramp_agents(8)
        cmd = ramp_commands(policy, obs, roster.mask)
        core.rollout(nan, roster=roster, roster_accel=cmd[..., 0], roster_join=cmd[..., 1])
        tally.add(core)
        st = core.state
        for b in range(2):
            for s in np.flatnonzero(st.active[b] & (st.lane[b] >= 0) & ~st.from_ramp[b]):
                vid, lane = int(st.vehicle_id[b, s]), int(st.lane[b, s])
                if lanes[b].get(vid, lane) != lane:
                    seen.append((b, vid, lane))
                lanes[b][vid] = lane
    return tally, seen


def test_lane_changes_are_the_mainline_vehicles_changing_lanes():
    tally, seen = _tally(FLOW, 400)
    assert len(seen) > 20
    assert tally.lane_changes.sum() == len(seen)
    assert tally.lane_changes.sum(axis=1).tolist() == [
        sum(1 for b, _, _ in seen if b == w) for w in range(2)
    ]
    shares = tally.shares()
    assert list(shares) == list(SECTIONS)
    assert sum(shares.values()) == pytest.approx(1.0)


def test_a_ramp_vehicle_joining_is_not_a_lane_change():
    empty = FLOW.replace(**{"traffic.flow_vph_per_lane": 0.0})
    tally, seen = _tally(empty, 400)
    core_joins = tally.lane_changes[:, : SECTIONS.index("downstream")].sum()
    assert core_joins == 0  # ramp vehicles joined all along; none of it counted
    assert tally.lane_changes.sum() == len(seen)
    assert tally.shares()["entrance"] in (None, 0.0)


def test_braking_shares_are_shares_of_the_samples():
    tally, _ = _tally(FLOW, 300)
    braking = tally.braking()
    assert tally.brake_samples.sum() > 1000
    assert 0.0 <= braking["braking_over_4_share"] <= braking["braking_over_b_share"] <= 1.0
    assert (tally.over_hard <= tally.over_comfort).all()
    assert 0.0 < braking["hardest_braking_mps2"] <= FLOW.vehicle.max_brake_mps2 + 1e-9


def test_a_shares_interval_treats_each_world_as_one_cluster():
    assert all(np.isnan(ratio_interval(np.array([3.0]), np.array([10.0]))))
    assert all(np.isnan(ratio_interval(np.zeros(4), np.zeros(4))))
    # the same share in every world: no spread between worlds, a point
    assert ratio_interval(np.array([1.0, 2.0, 4.0]), np.array([10.0, 20.0, 40.0])) == (0.1, 0.1)
    # by hand: shares 0.1 and 0.3 of 100 samples each; residuals -10 and +10 around 0.2
    lo, hi = ratio_interval(np.array([10.0, 30.0]), np.array([100.0, 100.0]))
    half = 1.96 * np.sqrt(2 / 1 * 200.0) / 200.0
    assert (lo, hi) == pytest.approx((0.2 - half, 0.2 + half))
    # many samples in few worlds are not many trials: wider than a binomial interval
    binomial_half = 1.96 * np.sqrt(0.2 * 0.8 / 200.0)
    assert hi - lo > 2 * binomial_half
    assert ratio_interval(np.array([0.0, 9.0]), np.array([10.0, 10.0]))[0] == 0.0  # clipped


def test_ramp_flow_reports_the_new_measures_as_strict_json():
    r = run_ramp_flow(FLOW, "gap", hours=0.05, worlds=2, seed=1, skip_s=60).to_dict()
    again = run_ramp_flow(FLOW, "gap", hours=0.05, worlds=2, seed=1, skip_s=60).to_dict()
    r.pop("wall_s"), again.pop("wall_s")
    assert r == again
    assert set(r["lane_change_shares"]) == set(SECTIONS) == set(r["lane_change_shares_ci95"])
    lo, hi = r["braking_over_b_share_ci95"]
    assert lo <= r["braking_over_b_share"] <= hi
    lo, hi = r["lane_change_shares_ci95"]["entrance"]
    assert lo <= r["lane_change_shares"]["entrance"] <= hi
    assert r["lane_changes_per_hour"] > 0
    json.dumps(r, allow_nan=False)


def test_evaluate_runs_ramp_flow_on_a_ramp_flow_scenario(capsys):
    assert (
        main(["evaluate", "gap", "--scenario", "ramp_flow", "--episodes", "40", "--worlds", "2"])
        == 0
    )
    out = capsys.readouterr().out.strip().splitlines()
    assert "under ramp flow" in out[-2] and "lane changes/h" in out[-2]
    ev = json.loads(out[-1])
    assert ev["ramp_demand_vph"] == 600.0 and ev["worlds"] == 2
    assert {"merged_vph", "braking_over_b_share", "lane_change_shares"} <= set(ev)
    assert main(["evaluate", "gap", "--scenario", "ramp_flow", "--highway", "nowhere"]) != 0
    assert "--highway / --fairness: scenario 'ramp_flow' runs ramp flow" in capsys.readouterr().err


@pytest.mark.slow
def test_the_grid_measures_ramp_flow_conditions_as_a_whole_merge(tmp_path):
    pols = [parse_policy("gap"), parse_policy("idm")]
    kw = dict(
        episodes=10, worlds=10, out_dir=tmp_path, progress=False, ramp_hours=0.03, ramp_worlds=2
    )
    run_grid(pols, ["grid_light_neutral", "ramp_flow"], **kw)
    summary = (tmp_path / "summary.md").read_text()
    assert "## Success % / collision %" in summary and "## Merge under ramp flow" in summary
    rows = [line for line in summary.splitlines() if line.startswith("| gap | - | ramp flow")]
    assert len(rows) == 1
    cells = sorted(tmp_path.glob("cells/*.flow.json"))
    assert len(cells) == 2
    first = [c.read_text() for c in cells]
    again = run_grid(pols, ["grid_light_neutral", "ramp_flow"], **kw)
    assert again.cells_run == 0 and [c.read_text() for c in cells] == first
    alone = tmp_path / "alone"
    run_grid(pols, ["ramp_flow"], **{**kw, "out_dir": alone})
    assert (alone / "summary.md").read_text().count("| ramp flow |") == 2
    assert sorted(p.read_text() for p in alone.glob("cells/*.flow.json")) == sorted(first)
    with pytest.raises(ValueError, match="@shield"):
        run_grid([parse_policy("gap@shield")], ["ramp_flow"], **kw)


@pytest.mark.slow
def test_braking_after_cut_ins_follows_mobils_safe_braking():
    """Cut-ins are what MOBIL's safe braking bounds: a gentler bound, gentler braking after them
    (joins, which it does not bound, are counted apart)."""
    out = {}
    for safe in (1.0, 4.0):
        cfg = FLOW.replace(**{"driver.safe_brake_mps2": safe})
        out[safe] = run_ramp_flow(cfg, "gap", hours=0.1, worlds=2, seed=2, skip_s=60)
    gentle, default = out[1.0], out[4.0]
    assert gentle.cut_ins > 20 and default.cut_ins > 20 and default.joins > 20
    assert gentle.hardest_braking_after_cut_in_mps2 < default.hardest_braking_after_cut_in_mps2
    assert (gentle.cut_ins_braking_over_b / gentle.cut_ins) < (
        default.cut_ins_braking_over_b / default.cut_ins
    )
    assert default.joins_braking_over_b <= default.joins


def test_ramp_vehicles_beyond_the_agents_are_counted_as_driven_by_idm(monkeypatch):
    """Vehicles behind the first `MAX_RAMP_AGENTS` of a ramp drive by IDM: their steps are
    counted, exactly (here with the agents cut to 2, so that the ramp holds more), and gap
    acceptance on the default ramp flow has none (the entrance keeps a queue off the ramp)."""
    from marlmerge.evaluation import ramp_flow
    from marlmerge.sim import layout as L

    monkeypatch.setattr(ramp_flow, "MAX_RAMP_AGENTS", 2)
    core = TrafficCore(FLOW, batch_size=2, seed=0)
    drivers = ramp_flow.RampDrivers([policy_from_spec("gap", FLOW)], [1.0], 2, 0)
    counted, by_hand = np.zeros(2), 0
    for _ in range(300):
        by_hand += int(np.maximum(core.wi[:, L.WI_N_RAMP] - 2, 0).sum())
        ramp_flow._drive(core, drivers, 1, None, None, counted)
    assert counted[1] == by_hand > 0 and counted[0] > counted[1]
    monkeypatch.undo()
    r = run_ramp_flow(FLOW, "gap", hours=0.05, worlds=2, seed=1, skip_s=60)
    assert r.ramp_steps_by_idm_share == 0.0
