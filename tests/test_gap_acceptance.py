"""The gap-acceptance merger: safe in easy traffic, better than ignoring the merge, sane actions."""

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig
from marlmerge.policies.gap_acceptance import (
    GapAcceptancePolicy,
    GapShield,
    IdmEgoPolicy,
    ShieldTally,
)
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_NONE, OUTCOME_SUCCESS, TrafficCore
from marlmerge.sim.observation import EGO_SCALE, ego_features

COOPERATIVE_LIGHT = {
    "traffic.flow_vph_per_lane": 600.0,
    "driver.mix_cooperative": 1.0,
    "driver.mix_neutral": 0.0,
    "driver.mix_adversarial": 0.0,
}


def first_ego_outcomes(policy, cfg: ScenarioConfig, batch_size: int, seed: int) -> np.ndarray:
    """Outcome of the first ramp vehicle of each world of `TrafficCore(cfg, batch_size, seed)`,
    the policy acting every `action_repeat` simulator steps. [batch_size] OUTCOME_* codes."""
    core = TrafficCore(cfg, batch_size=batch_size, seed=seed)
    out = np.zeros(batch_size, dtype=np.int64)
    max_steps = int(cfg.ego.max_episode_s / cfg.sim.dt_s) + 1
    steps = 0
    while (out == OUTCOME_NONE).any() and steps < max_steps:
        a = np.asarray(policy(core.observe()[0]))[:, 0]
        for _ in range(cfg.sim.action_repeat):
            ev = core.step(a)
            steps += 1
            new = (out == OUTCOME_NONE) & (ev.ego_outcome != OUTCOME_NONE)
            out[new] = ev.ego_outcome[new]
    return out


@pytest.mark.slow
def test_never_collides_in_cooperative_light_traffic_over_30_seeds():
    # "30 seeds": 30 freshly seeded roads, TrafficCore(batch_size=1, seed=s) for s in 0..29, each
    # in steady flow after the warm-up; the episode is the first ramp vehicle of each road.
    cfg = ScenarioConfig().replace(**COOPERATIVE_LIGHT)
    policy = GapAcceptancePolicy(cfg)
    outcomes = np.array([first_ego_outcomes(policy, cfg, 1, seed)[0] for seed in range(30)])
    assert not (outcomes == OUTCOME_COLLISION).any(), outcomes
    assert (outcomes == OUTCOME_SUCCESS).all(), outcomes  # and it neither stalls nor times out


def test_beats_the_merge_ignoring_idm_ego_in_default_traffic():
    cfg = ScenarioConfig()
    gap = first_ego_outcomes(GapAcceptancePolicy(cfg), cfg, batch_size=60, seed=7)
    idm = first_ego_outcomes(IdmEgoPolicy(cfg), cfg, batch_size=60, seed=7)
    assert np.mean(gap == OUTCOME_SUCCESS) >= np.mean(idm == OUTCOME_SUCCESS) + 0.05
    assert np.mean(gap == OUTCOME_COLLISION) < np.mean(idm == OUTCOME_COLLISION)


def test_actions_are_finite_and_inside_the_ego_bounds_for_random_observations():
    cfg = ScenarioConfig()
    policy = GapAcceptancePolicy(cfg)
    lo, hi = cfg.ego.accel_bounds_mps2
    rng = np.random.default_rng(0)
    n = 4000
    raw = np.stack(
        [
            rng.uniform(0.0, 45.0, n),  # ego speed
            rng.uniform(-300.0, 250.0, n),  # ego position
            rng.uniform(0.0, 45.0, n),  # front speed
            rng.uniform(-300.0, 400.0, n),  # front position (also behind the ego)
            rng.uniform(0.0, 45.0, n),  # back speed
            rng.uniform(-450.0, 250.0, n),  # back position (also ahead of the ego)
            rng.uniform(5.0, 40.0, n),  # speed limit
        ],
        axis=1,
    )
    raw[::7, 0] = 0.0  # standing egos
    raw[::11, 1] = cfg.x_overlap_m  # exactly at the join point
    raw[::13, 3] = raw[::13, 1]  # front vehicle level with the ego
    obs = (raw / EGO_SCALE).astype(np.float32)
    a = policy(obs)
    assert a.shape == (n, 1)
    assert np.all(np.isfinite(a))
    assert np.all((a >= lo) & (a <= hi))
    # any leading shape, and junk values are still answered inside the bounds
    assert policy(obs[:20].reshape(4, 5, 7)).shape == (4, 5, 1)
    assert policy(obs[0]).shape == (1,)
    junk = obs[:3].copy()
    junk[0, 2] = np.nan
    junk[1, 3] = np.inf
    junk[2, :] = -np.inf
    out = policy(junk)
    assert np.all(np.isfinite(out)) and np.all((out >= lo) & (out <= hi))


def _obs(cfg, v, x, front=None, back=None):
    """Scaled observation; front/back = (dx from the ego m, speed m/s) or None for none."""
    v_lim = cfg.road.speed_limit_mps
    rng_m = cfg.ego.sensing_range_m
    dxf, vf = front if front is not None else (rng_m, v_lim)
    dxb, vb = back if back is not None else (-rng_m, v_lim)
    raw = np.array([v, x, vf, x + dxf, vb, x + dxb, v_lim])
    return (raw / EGO_SCALE)[None].astype(np.float32)


@pytest.fixture(scope="module")
def cfg():
    return ScenarioConfig()


def test_accelerates_ahead_of_a_close_back_vehicle_when_that_fixes_the_lag_gap(cfg):
    # 150 m before the join point, a back vehicle 15 m behind at the ego's speed
    a = GapAcceptancePolicy(cfg)(_obs(cfg, 25.0, cfg.x_overlap_m - 150.0, back=(-15.0, 25.0)))
    assert a[0, 0] > 0.0


def test_drops_behind_a_vehicle_alongside_in_a_short_gap(cfg):
    obs = _obs(cfg, 25.0, -150.0, front=(10.0, 25.0), back=(-1.0, 25.0))
    assert GapAcceptancePolicy(cfg)(obs)[0, 0] < 0.0


def test_waits_at_the_end_of_the_ramp_until_the_lag_gap_is_long_enough(cfg):
    policy = GapAcceptancePolicy(cfg)
    x = cfg.x_overlap_m - 0.3
    assert policy(_obs(cfg, 0.0, x, back=(-25.0, 25.0)))[0, 0] <= 0.0
    assert policy(_obs(cfg, 0.0, x, back=(-60.0, 25.0)))[0, 0] <= 0.0
    assert policy(_obs(cfg, 0.0, x, back=(-100.0, 25.0)))[0, 0] > 0.0
    assert policy(_obs(cfg, 0.0, x))[0, 0] > 0.0  # nobody around


def test_free_road_speeds_up_to_the_limit_and_follows_by_idm_in_the_lane(cfg):
    policy = GapAcceptancePolicy(cfg)
    assert policy(_obs(cfg, 20.0, -200.0))[0, 0] > 0.0
    assert policy(_obs(cfg, cfg.road.speed_limit_mps, -200.0))[0, 0] == pytest.approx(0.0)
    in_lane = _obs(cfg, 20.0, -10.0, front=(30.0, 18.0), back=(-20.0, 22.0))
    np.testing.assert_allclose(policy(in_lane), IdmEgoPolicy(cfg)(in_lane))


def test_the_shield_lets_commands_through_where_nothing_is_at_stake(cfg):
    shield = GapShield(cfg)
    commands = np.linspace(-4.5, 2.5, 15, dtype=np.float32)[:, None]
    for obs in (
        _obs(cfg, 25.0, -250.0),  # free road
        _obs(cfg, 25.0, -250.0, front=(80.0, 25.0), back=(-80.0, 25.0)),  # a long gap
        _obs(cfg, 25.0, -10.0, front=(30.0, 18.0), back=(-20.0, 22.0)),  # in the lane
    ):
        batch = np.repeat(obs, len(commands), axis=0)
        assert np.array_equal(shield(batch, commands), commands)


def test_the_shield_stops_a_join_alongside_a_vehicle_and_keeps_a_safe_one(cfg):
    shield = GapShield(cfg)
    # 12 m before the join point at 25 m/s, a vehicle 2 m behind, alongside, at 27 m/s
    alongside = _obs(cfg, 25.0, cfg.x_overlap_m - 12.0, back=(-2.0, 27.0))
    out = shield(alongside, np.array([[1.0]], dtype=np.float32))
    assert out[0, 0] != 1.0
    np.testing.assert_allclose(out, GapAcceptancePolicy(cfg)(alongside))
    # at the ramp start, alongside a vehicle in a short gap: it drops behind as gap acceptance
    short = _obs(cfg, 25.0, -250.0, front=(10.0, 25.0), back=(-1.0, 25.0))
    assert shield(short, np.array([[2.0]], dtype=np.float32))[0, 0] < 0.0
    # the same place with the vehicle 60 m behind: joining is safe, the command stands
    clear = _obs(cfg, 25.0, cfg.x_overlap_m - 12.0, back=(-60.0, 25.0))
    assert shield(clear, np.array([[1.0]], dtype=np.float32))[0, 0] == 1.0


def test_the_shield_counts_the_ramp_commands_it_judges_and_changes(cfg):
    shield = GapShield(cfg)
    alongside = _obs(cfg, 25.0, cfg.x_overlap_m - 12.0, back=(-2.0, 27.0))  # overruled
    clear = _obs(cfg, 25.0, cfg.x_overlap_m - 12.0, back=(-60.0, 25.0))  # stands
    in_lane = _obs(cfg, 25.0, -10.0, front=(30.0, 18.0), back=(-20.0, 22.0))  # not judged
    free_column = np.zeros_like(clear)  # an absent agent: all zeros, x = 0 past the join
    obs = np.concatenate([alongside, clear, in_lane, free_column])
    before = ShieldTally(shield.tally.judged, shield.tally.changed)
    shield(obs, np.ones((4, 1), dtype=np.float32))
    assert shield.tally == ShieldTally(judged=2, changed=1)
    shield(obs[:1], np.ones((1, 1), dtype=np.float32))
    assert shield.tally.since(before) == ShieldTally(judged=3, changed=2)


def test_evaluate_counts_the_shields_changes_of_running_episodes_only(cfg):
    """`evaluate` behind a shield: the ego's commands the shield judged on the ramp, per
    episode, counted only while the episode runs (at most one a command), and the share it
    changed."""
    from marlmerge.evaluation.registry import policy_for_evaluation, policy_from_spec
    from marlmerge.evaluation.rollout import run_episodes, summarize

    control_s = cfg.sim.dt_s * cfg.sim.action_repeat
    summaries = {}
    for spec in ("gap@shield", "hold@shield"):
        policy, scen = policy_for_evaluation(spec, cfg)
        rec = run_episodes(policy, scen, episodes=24, seed=3, worlds=8)
        steps = np.round(rec["time_s"] / control_s) + 1  # commands each episode was given
        assert np.all(rec["shield_judged"] > 0) and np.all(rec["shield_judged"] <= steps)
        summaries[spec] = summarize(rec)
    assert summaries["gap@shield"]["shield_changed_share"] < 0.05
    assert summaries["hold@shield"]["shield_changed_share"] > 0.05
    bare = summarize(run_episodes(policy_from_spec("gap", cfg), cfg, episodes=8, seed=3, worlds=8))
    assert "shield_judged" not in bare and "shield_changed_share" not in bare


def test_a_shielded_policy_never_collides_where_the_bare_one_does(cfg):
    """A reckless merger (full throttle on the ramp, IDM in the lane) collides in dense
    traffic; behind the shield the same vehicle does not, over the same roads."""
    dense = cfg.replace(**{"traffic.flow_vph_per_lane": 1800.0})
    hi, idm = dense.ego.accel_bounds_mps2[1], IdmEgoPolicy(dense)

    def reckless(obs: np.ndarray) -> np.ndarray:
        on_ramp = obs[:, 1:2] * EGO_SCALE[1] < dense.x_overlap_m
        return np.where(on_ramp, hi, idm(obs)).astype(np.float32)

    shield = GapShield(dense)
    shielded = lambda obs: shield(obs, reckless(obs))  # noqa: E731
    bare = first_ego_outcomes(reckless, dense, batch_size=128, seed=5)
    safe = first_ego_outcomes(shielded, dense, batch_size=128, seed=5)
    assert (bare == OUTCOME_COLLISION).sum() >= 20  # 55 of the 128
    assert (safe == OUTCOME_COLLISION).sum() == 0 and (safe == OUTCOME_SUCCESS).mean() >= 0.95


def _drive_beside_a_late_mover(watch_left: bool) -> int:
    """The ego holds 22 m/s on the ramp, 4.5 s before the join point, beside a left-lane driver
    at its speed whose lane-change cooldown ends 4 s in (it then moves right, beside the ego,
    with the right lane empty); the ego behind `GapShield(watch_left=...)`. Its outcome."""
    from scenes import scene

    from marlmerge.policies.scripted import constant_speed_action
    from marlmerge.sim.layout import VF_SINCE_LC

    over = {
        "ego.observation": "extended",
        "driver.lane_change_threshold_mps2": 0.2,
        "driver.keep_right_bias_mps2": 0.5,
    }
    probe = scene((0.0, 22.0), overrides=over)
    x0 = probe.cfg.x_overlap_m - 22.0 * 4.5
    core = scene((x0, 22.0), left=[(x0, 22.0)], overrides=over)
    core.vf[0, VF_SINCE_LC, 1] = probe.cfg.driver.lane_change_cooldown_s - 4.0
    shield = GapShield(core.cfg, watch_left=watch_left)
    obs, _ = core.observe()
    for _ in range(60):
        out = core.rollout(shield(obs, constant_speed_action(obs))[:, 0].astype(np.float64))
        obs = out.ego_obs
        if out.ego_outcome[0] != OUTCOME_NONE:
            return int(out.ego_outcome[0])
    return OUTCOME_NONE


def test_the_left_watch_foresees_a_driver_moving_in_beside_the_join():
    # the plain shield sees the mover only once it is beside the ego, too late to drop behind
    assert _drive_beside_a_late_mover(watch_left=False) == OUTCOME_COLLISION
    assert _drive_beside_a_late_mover(watch_left=True) == OUTCOME_SUCCESS


def test_the_left_watch_takes_only_drivers_that_would_move(cfg):
    ext = cfg.replace(**{"ego.observation": "extended"})
    shield = GapShield(ext, watch_left=True)
    names = [f.name for f in ego_features(ext)]
    x, rng_m = ext.x_overlap_m - 60.0, ext.ego.sensing_range_m

    def obs(left_dx: float, left_v: float, front=None) -> np.ndarray:
        raw = np.zeros(len(names))
        raw[:7] = _obs(ext, 25.0, x, front=front)[0] * EGO_SCALE
        raw[names.index("left_front_dx")], raw[names.index("left_front_speed")] = left_dx, left_v
        raw[names.index("left_back_dx")] = -rng_m
        raw[names.index("left_back_speed")] = ext.road.speed_limit_mps
        scale = np.array([f.scale for f in ego_features(ext)])
        return (raw / scale)[None]

    front = names.index("front_position")
    # the right lane empty ahead: the left driver 10 m ahead would move right, into the gap
    seen = shield._left_movers(obs(10.0, 25.0))
    assert seen[0, front] * EGO_SCALE[1] == pytest.approx(x + 10.0)
    # a slow right-lane vehicle 15 m ahead of it: it stays left, the gap is as the sensors say
    held = obs(10.0, 25.0, front=(25.0, 10.0))
    np.testing.assert_array_equal(shield._left_movers(held), held)
    # no left-lane vehicle within the sensing range: nothing changes
    none = obs(rng_m, ext.road.speed_limit_mps)
    np.testing.assert_array_equal(shield._left_movers(none), none)
    with pytest.raises(ValueError, match="ego.observation = 'paper' has none"):
        GapShield(cfg, watch_left=True)


def test_keep_rolling_lifts_an_early_stop_and_leaves_the_wait_point_alone(cfg):
    shield = GapShield(cfg, keep_rolling=True)
    brake = np.array([[-2.0]], dtype=np.float32)
    early = _obs(cfg, 1.0, cfg.x_overlap_m - 150.0)  # 150 m before the join, nearly stopped
    assert GapShield(cfg)(early, brake)[0, 0] == -2.0  # the plain shield lets it stop there
    lifted = shield(early, brake)[0, 0]
    assert lifted > 0.0 and lifted == GapAcceptancePolicy(cfg)(early)[0, 0]
    # at gap acceptance's wait point, or still fast, the command stands
    at_wait = _obs(cfg, 1.0, cfg.x_overlap_m - 2.0, back=(-8.0, 25.0))
    assert shield(at_wait, brake)[0, 0] == GapShield(cfg)(at_wait, brake)[0, 0]
    fast = _obs(cfg, 20.0, cfg.x_overlap_m - 150.0)
    assert shield(fast, brake)[0, 0] == -2.0
