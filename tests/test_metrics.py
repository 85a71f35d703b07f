"""Evaluation metrics on hand-built trajectories with known answers, and the 95 % intervals."""

import math

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig
from marlmerge.evaluation.metrics import (
    METRICS,
    EpisodeTrajectory,
    TrajectoryRecorder,
    aggregate,
    episode_metrics,
    summarize,
    ttc_series,
    wilson_interval,
)
from marlmerge.sim import (
    OUTCOME_COLLISION,
    OUTCOME_NONE,
    OUTCOME_SUCCESS,
    OUTCOME_TRUNCATED,
    TrafficCore,
)

DT = 0.1


def make_traj(
    x,
    v,
    a=None,
    d_front=None,
    v_front=None,
    d_back=None,
    v_back=None,
    a_back=None,
    outcome=OUTCOME_SUCCESS,
    zone_start=-100.0,
):
    """A trajectory with no gap vehicles unless given (inf gaps, nan speeds)."""
    x = np.asarray(x, dtype=float)
    n = x.size

    def arr(val, fill):
        return np.full(n, fill) if val is None else np.broadcast_to(np.asarray(val, float), n)

    return EpisodeTrajectory(
        dt_s=DT,
        x_m=x,
        v_mps=arr(v, 0.0),
        a_mps2=arr(a, 0.0),
        d_front_m=arr(d_front, np.inf),
        v_front_mps=arr(v_front, np.nan),
        d_back_m=arr(d_back, np.inf),
        v_back_mps=arr(v_back, np.nan),
        a_back_mps2=arr(a_back, np.nan),
        outcome=outcome,
        zone_start_m=zone_start,
    )


def constant_run(x0=-150.0, v=20.0, n=200, **kw):
    return make_traj(x0 + v * DT * np.arange(n), v, **kw)


def test_every_metric_is_reported_in_table_order():
    m = episode_metrics(constant_run())
    assert list(m) == [row.name for row in METRICS]
    assert all(row.kind in ("rate", "mean", "min", "max") for row in METRICS)
    assert all(isinstance(v, float) for v in m.values())


def test_constant_speed_pass_has_no_acceleration_jerk_or_conflict():
    m = episode_metrics(constant_run())
    assert m["mean_abs_accel_mps2"] == 0.0
    assert m["max_abs_accel_mps2"] == 0.0
    assert m["max_abs_jerk_mps3"] == 0.0
    assert m["mean_speed_mps"] == pytest.approx(20.0)
    # no gap vehicles: never closing (inf, not nan), no follower (nan)
    assert m["min_ttc_front_s"] == math.inf
    assert m["min_ttc_back_s"] == math.inf
    assert m["time_ttc_below_s"] == 0.0
    assert m["min_gap_after_merge_m"] == math.inf
    assert m["min_headway_after_merge_s"] == math.inf
    assert math.isnan(m["follower_min_accel_mps2"])


def test_outcome_flags():
    for outcome, key in [
        (OUTCOME_SUCCESS, "success"),
        (OUTCOME_COLLISION, "collision"),
        (OUTCOME_TRUNCATED, "truncation"),
    ]:
        m = episode_metrics(constant_run(outcome=outcome))
        flags = {k: m[k] for k in ("success", "collision", "truncation")}
        assert flags == {k: float(k == key) for k in flags}
    m = episode_metrics(constant_run(outcome=OUTCOME_NONE))
    assert m["success"] == m["collision"] == m["truncation"] == 0.0


def test_time_to_merge_from_the_zone_start_at_20_mps_is_5_s():
    m = episode_metrics(constant_run(x0=-100.0, v=20.0, n=80))
    assert m["time_to_merge_s"] == pytest.approx(5.0, abs=DT)
    # between samples it is interpolated: from -99 m the merge point is 4.95 s away
    m = episode_metrics(constant_run(x0=-99.0, v=20.0, n=80))
    assert m["time_to_merge_s"] == pytest.approx(4.95, abs=1e-9)
    # sample times start at t0_s (the recorder samples after each step: t0 = dt)
    traj = constant_run(x0=-98.0, v=20.0, n=80)
    traj.t0_s = DT
    assert episode_metrics(traj)["time_to_merge_s"] == pytest.approx(5.0, abs=1e-9)


def test_jerk_is_the_largest_acceleration_step_over_dt():
    a = np.zeros(50)
    a[20:] = 1.0
    a[30:] = -0.5
    m = episode_metrics(constant_run(n=50, a=a))
    assert m["max_abs_jerk_mps3"] == pytest.approx(1.5 / DT)
    assert m["max_abs_accel_mps2"] == pytest.approx(1.0)
    assert m["mean_abs_accel_mps2"] == pytest.approx((10 * 1.0 + 20 * 0.5) / 50)


def approach(zone_start=-100.0):
    """Ego at 20 m/s closes on a front vehicle at 10 m/s from 100 m to 50 m (steps 0..50), then
    the front vehicle speeds up to 20 m/s and the gap stays at 50 m."""
    n = 100
    k = np.arange(n)
    d_front = np.where(k <= 50, 100.0 - 10.0 * DT * k, 50.0)
    v_front = np.where(k <= 50, 10.0, 20.0)
    return constant_run(
        x0=-80.0, v=20.0, n=n, d_front=d_front, v_front=v_front, zone_start=zone_start
    )


def test_known_approach_has_min_ttc_5_s_at_the_50_m_step():
    traj = approach()
    ttc_f, ttc_b = ttc_series(traj)
    assert np.argmin(ttc_f) == 50
    assert ttc_f[50] == pytest.approx(5.0)
    assert ttc_f[0] == pytest.approx(10.0)
    assert np.all(np.isinf(ttc_f[51:]))  # no longer closing
    assert np.all(np.isinf(ttc_b))  # no back vehicle
    m = episode_metrics(traj)
    assert m["min_ttc_front_s"] == pytest.approx(5.0)
    assert m["min_ttc_back_s"] == math.inf


def test_time_with_ttc_below_threshold():
    traj = approach()
    # TTC = 10 - 0.1 k s on steps 0..50: below 6 s on steps 41..50 (10 steps = 1 s)
    assert episode_metrics(traj, ttc_threshold_s=6.0)["time_ttc_below_s"] == pytest.approx(1.0)
    assert episode_metrics(traj, ttc_threshold_s=4.0)["time_ttc_below_s"] == 0.0
    assert episode_metrics(traj, ttc_threshold_s=5.0)["time_ttc_below_s"] == 0.0  # strictly below
    assert episode_metrics(traj, ttc_threshold_s=1.5)["time_ttc_below_s"] == 0.0


def test_ttc_counts_only_from_the_zone_start():
    # the whole approach happens upstream of a zone that starts at -20 m (x reaches it at k = 30)
    m = episode_metrics(approach(zone_start=-20.0), ttc_threshold_s=6.0)
    assert m["min_ttc_front_s"] == pytest.approx(5.0)  # step 50 is inside
    m = episode_metrics(approach(zone_start=50.0), ttc_threshold_s=6.0)
    assert m["min_ttc_front_s"] == math.inf
    assert m["time_ttc_below_s"] == 0.0


def test_back_vehicle_ttc():
    # inside the zone, a back vehicle at 25 m/s 30 m behind the ego at 20 m/s: TTC 6 s; a slower
    # one never closes
    m = episode_metrics(constant_run(x0=-50.0, n=20, d_back=30.0, v_back=25.0))
    assert m["min_ttc_back_s"] == pytest.approx(6.0)
    m = episode_metrics(constant_run(x0=-50.0, n=20, d_back=30.0, v_back=15.0))
    assert m["min_ttc_back_s"] == math.inf
    # an overlap (collision) counts as TTC 0
    m = episode_metrics(constant_run(x0=-50.0, n=20, d_back=-1.0, v_back=25.0))
    assert m["min_ttc_back_s"] == 0.0


def test_min_gap_and_headway_after_the_merge_point():
    # ego at 20 m/s from -50 m: merged (x >= 0) from step 25 on; the front gap shrinks 60 -> 20 m
    n = 60
    d_front = np.linspace(60.0, 20.0, n)
    d_front[:10] = 5.0  # a short gap before the merge point does not count
    m = episode_metrics(constant_run(x0=-50.0, n=n, d_front=d_front, v_front=20.0))
    assert m["min_gap_after_merge_m"] == pytest.approx(20.0)
    assert m["min_headway_after_merge_s"] == pytest.approx(1.0)


def test_follower_min_accel_after_the_merge():
    n = 60
    a_back = np.full(n, -1.0)
    a_back[5] = -6.0  # before the merge point (x < 0): ignored
    a_back[30] = -3.0
    a_back[40:] = np.nan  # no follower any more
    m = episode_metrics(constant_run(x0=-50.0, n=n, a_back=a_back))
    assert m["follower_min_accel_mps2"] == pytest.approx(-3.0)


def test_never_merged_gives_nan_for_merge_metrics():
    m = episode_metrics(
        constant_run(
            x0=-200.0, n=50, d_front=30.0, v_front=20.0, a_back=-1.0, outcome=OUTCOME_COLLISION
        )
    )
    for key in (
        "time_to_merge_s",
        "min_gap_after_merge_m",
        "min_headway_after_merge_s",
        "follower_min_accel_mps2",
    ):
        assert math.isnan(m[key]), key
    assert m["collision"] == 1.0


def test_wilson_interval_known_values():
    lo, hi = wilson_interval(0, 30)
    assert lo == 0.0 and hi == pytest.approx(0.1135, abs=5e-4)
    lo, hi = wilson_interval(15, 30)
    assert lo == pytest.approx(0.3315, abs=5e-4) and hi == pytest.approx(0.6685, abs=5e-4)
    lo, hi = wilson_interval(1, 10)
    assert lo == pytest.approx(0.0179, abs=5e-4) and hi == pytest.approx(0.4042, abs=5e-4)
    lo, hi = wilson_interval(30, 30)
    assert lo == pytest.approx(1 - 0.1135, abs=5e-4) and hi == 1.0
    assert all(math.isnan(v) for v in wilson_interval(0, 0))


def test_aggregate_rates_and_means():
    mean, lo, hi = aggregate(np.r_[np.ones(15), np.zeros(15)], "rate")
    assert (mean, lo, hi) == pytest.approx((0.5, 0.3315, 0.6685), abs=5e-4)
    assert aggregate(np.zeros(30), "rate") == pytest.approx((0.0, 0.0, 0.1135), abs=5e-4)
    assert aggregate(np.array([1.0, 0.0, np.nan]), "rate")[0] == 0.5  # nan ignored
    mean, lo, hi = aggregate(np.array([1.0, 2.0, 3.0]), "mean")
    half = 1.959964 * 1.0 / math.sqrt(3)
    assert (mean, lo, hi) == pytest.approx((2.0, 2.0 - half, 2.0 + half))


def test_aggregate_ignores_nan_and_inf_in_means():
    mean, lo, hi = aggregate(np.array([1.0, 2.0, 3.0, np.nan, np.inf]), "min")
    assert mean == pytest.approx(2.0) and lo < 2.0 < hi
    assert aggregate(np.array([np.inf, np.inf, np.nan]), "min") == (math.inf,) * 3
    assert aggregate(np.array([-np.inf]), "max") == (-math.inf,) * 3
    assert all(math.isnan(v) for v in aggregate(np.array([np.nan, np.nan]), "mean"))
    assert all(math.isnan(v) for v in aggregate(np.array([]), "mean"))
    assert all(math.isnan(v) for v in aggregate(np.array([np.inf, -np.inf]), "mean"))
    mean, lo, hi = aggregate(np.array([4.0, np.nan]), "mean")
    assert mean == 4.0 and math.isnan(lo) and math.isnan(hi)
    with pytest.raises(ValueError, match="kind"):
        aggregate(np.ones(3), "median")


def test_recorder_collects_whole_episodes_from_the_core():
    cfg = ScenarioConfig()
    core = TrafficCore(cfg, batch_size=4, seed=3)
    rec = TrajectoryRecorder(cfg, 4)
    done: dict[int, EpisodeTrajectory] = {}
    steps = 0
    while len(done) < 4 and steps < 300:
        out = core.rollout(np.zeros(4))  # hold speed
        steps += 1
        for b, traj in rec.record(out):
            done.setdefault(b, traj)
        core.next_ego(out.ego_outcome != OUTCOME_NONE)
    assert len(done) == 4
    for traj in done.values():
        assert traj.outcome != OUTCOME_NONE
        assert np.all(np.diff(traj.x_m) >= 0.0)
        assert traj.x_m[0] == pytest.approx(cfg.road.x_ramp_start_m + traj.v_mps[0] * DT)
        assert np.all(traj.a_mps2 == 0.0)  # held speed
        m = episode_metrics(traj)
        if traj.outcome == OUTCOME_SUCCESS:
            assert traj.x_m[-1] >= cfg.ego.success_distance_m
            assert m["time_to_merge_s"] == pytest.approx(-cfg.road.x_ramp_start_m / traj.v_mps[0])
    s = summarize([episode_metrics(t) for t in done.values()])
    assert set(s) == {row.name for row in METRICS}
