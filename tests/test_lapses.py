"""Attention lapses of mainline drivers: the draw, the behaviour, determinism, the proposal's
exact weights, and states saved before lapses existed."""

import math
from dataclasses import replace

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig
from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.estimate import (
    LAPSE_Q_MIN,
    LAPSE_START_P,
    EstimateSettings,
    fit_proposal,
    initial_proposal,
    lapse_grid,
)
from marlmerge.sim import layout as L
from marlmerge.sim.core import TrafficCore
from marlmerge.sim.lapses import MIN_CLOSING_MPS, lapse_class, lapse_uniform
from marlmerge.sim.proposal import N_STATS, ST_LAPSE_N, ST_LAPSE_STEPS, Proposal

LAPSING = ScenarioConfig().replace(**{"driver.lapse_rate_per_h": 600.0, "driver.lapse_s": 1.0})


def _drive(core: TrafficCore, calls: int) -> list[np.ndarray]:
    out = []
    for _ in range(calls):
        step = core.rollout(np.full(core.batch_size, 0.3))
        core.next_ego(step.ego_outcome != 0)
        out.append(core.vf[:, L.VF_X].copy())
    return out


def test_the_lapse_draw_is_uniform_and_the_same_compiled_or_not():
    u = np.array(
        [lapse_uniform(7, step, vid) for step in range(400) for vid in range(50)], dtype=float
    )
    counts, _ = np.histogram(u, bins=20, range=(0.0, 1.0))
    expected = u.size / 20
    chi2 = float(np.sum((counts - expected) ** 2 / expected))
    assert chi2 < 45.0  # 19 degrees of freedom: p < 1e-3 beyond this
    assert 0.0 < u.min() and u.max() < 1.0
    assert abs(np.corrcoef(u[:-1], u[1:])[0, 1]) < 0.03
    for args in ((0, 0, 0), (2**31 - 1, 123456, 98765), (42, 7, 3)):
        assert lapse_uniform(*args) == lapse_uniform.py_func(*args)
    assert lapse_uniform(1, 5, 9) != lapse_uniform(2, 5, 9)


def test_a_lapsing_driver_holds_its_speed_for_the_lapse():
    """Every vehicle in a lapse after a step moved at constant speed in it; lapses last
    `lapse_s` (10 steps here); about the drawn share of driver-steps lapse."""
    core = TrafficCore(LAPSING, batch_size=4, seed=3)
    core.reset(seed=3)
    seen, held = 0, 0
    for _ in range(60):
        v_before = core.vf[:, L.VF_V].copy()
        core.step(np.full(4, 0.3))
        lapse = (core.vf[:, L.VF_LAPSE] > 0) & (core.vi[:, L.VI_ACTIVE] == 1)
        lapse[:, 0] = False
        seen += int(lapse.sum())
        held += int(np.sum(lapse & (core.vf[:, L.VF_V] == v_before)))
        assert core.vf[:, L.VF_LAPSE].max() <= 9.0
    assert seen > 50 and held == seen


def test_lapses_are_seeded_per_world_and_off_by_default():
    batch = TrafficCore(LAPSING, batch_size=3, seed=[5, 6, 7])
    batch.reset(seed=[5, 6, 7])
    alone = TrafficCore(LAPSING, batch_size=1, seed=[6])
    alone.reset(seed=[6])
    for a, b in zip(_drive(batch, 25), _drive(alone, 25), strict=True):
        assert np.array_equal(a[1], b[0])
    plain = TrafficCore(ScenarioConfig(), batch_size=2, seed=1)
    assert plain.params[0, L.P_LAPSE_P] == 0.0 and plain.streams.n_streams == 4
    _drive(plain, 10)
    assert np.all(plain.vf[:, L.VF_LAPSE] == 0.0) and np.all(plain.wf[:, L.WF_LAPSE_STEPS] == 0)


def test_the_tilted_lapses_weigh_exactly():
    """log w = sum over classes c of steps_c log((1-p)/(1-q_c)) + lapses_c (log(p/q_c) -
    log((1-p)/(1-q_c))), world by world; the weights average 1; the natural probability gives
    weight 1 exactly."""
    cfg = resolve_config("lapses")
    p = L.lapse_step_probability(cfg)
    q = (0.05, 0.03, 0.02, 0.01)
    core = TrafficCore(
        cfg, batch_size=300, seed=4, proposal=replace(Proposal.natural(cfg), lapse_p=q)
    )
    core.reset(seed=4)
    for _ in range(60):
        core.rollout(np.full(300, 0.5))
    want = np.zeros(300)
    for c, q_c in enumerate(q):
        steps, lapses = core.wf[:, L.WF_LAPSE_STEPS + c], core.wf[:, L.WF_LAPSE_N + c]
        no = math.log1p(-p) - math.log1p(-q_c)
        want += steps * no + lapses * (math.log(p / q_c) - no)
        assert steps.sum() > 0
    assert np.allclose(core.wf[:, L.WF_LAPSE_LOGW], want, rtol=1e-12, atol=1e-9)
    begun = core.wf[:, L.WF_LAPSE_N : L.WF_LAPSE_N + L.N_LAPSE_CLASSES].sum(axis=1)  # [B]
    assert begun.sum() > 5 and begun.max() == 1.0  # the first tilted lapse only
    w = np.exp(core.wf[:, L.WF_LAPSE_LOGW])
    assert abs(w.mean() - 1.0) < 4 * w.std(ddof=1) / math.sqrt(w.size)
    natural = TrafficCore(cfg, batch_size=20, seed=4, proposal=Proposal.natural(cfg))
    natural.reset(seed=4)
    for _ in range(60):
        natural.rollout(np.full(20, 0.5))
    assert natural.wf[:, L.WF_LAPSE_STEPS].sum() > 0
    assert np.all(natural.wf[:, L.WF_LAPSE_LOGW] == 0.0)


def test_lapse_proposals_refuse_and_fit():
    with pytest.raises(ValueError, match="lapse_p must be 4 probabilities in"):
        Proposal((5.0, 30.0), ((0.4, 0.3, 0.3),) * 2, lapse_p=(0.1, 0.9, 0.1, 0.1))
    with pytest.raises(ValueError, match="never lapse"):
        TrafficCore(
            ScenarioConfig(), 1, seed=0, proposal=Proposal((5.0, 30.0), ((0.4, 0.3, 0.3),) * 2,
                                                           lapse_p=(0.1,) * 4)
        )  # fmt: skip
    cfg = resolve_config("lapses")
    start = initial_proposal(cfg)
    p = L.lapse_step_probability(cfg)
    assert start.lapse_p == tuple(max(p, q) for q in LAPSE_START_P) and min(start.lapse_p) > p
    assert initial_proposal(ScenarioConfig()).lapse_p is None
    assert Proposal.from_dict(start.to_dict()) == start
    assert "lapse_p" not in Proposal.natural(ScenarioConfig()).to_dict()
    n = 100
    stats = np.zeros((n, N_STATS))
    stats[:, ST_LAPSE_STEPS] = 10.0
    stats[:10, ST_LAPSE_N] = 1.0  # each event lapsed once, in its tenth step of class 0
    batch = {
        "event": np.arange(n) < 10,
        "log_weight": np.zeros(n),
        "draw_stats": stats,
        "min_gap_m": np.full(n, 10.0),
    }
    fitted, _ = fit_proposal(cfg, start, batch, EstimateSettings(smoothing=1.0))
    # alike events: the second moment is least where their likelihood is largest (q = 1/10);
    # classes 1-3: no step of them in the events, so the grid's first (the floor)
    floor = lapse_grid(p)[0]
    assert floor == max(p, LAPSE_Q_MIN)
    assert fitted.lapse_p == pytest.approx((0.1, floor, floor, floor), rel=0.06)
    few = {**batch, "event": np.arange(n) < 4}
    assert fit_proposal(cfg, start, few, EstimateSettings())[0].lapse_p == start.lapse_p


def test_the_lapse_fit_minimises_the_estimates_second_moment():
    """Events whose class-0 windows were 3 and 30 steps long, one lapse each, drawn under q =
    0.02: the fit is the grid point where sum_i w_i w_q,i is least (closed form below), and that
    is well below the cross-entropy fit (2 lapses in 33 steps), whose long windows would weigh
    ((1 - p)/(1 - q))^29 each."""
    cfg = resolve_config("lapses")
    p, q_own = L.lapse_step_probability(cfg), 0.02
    start = replace(initial_proposal(cfg), lapse_p=(q_own,) * L.N_LAPSE_CLASSES)
    steps = np.array([3.0, 30.0] * 10)
    stats = np.zeros((steps.size, N_STATS))
    stats[:, ST_LAPSE_STEPS], stats[:, ST_LAPSE_N] = steps, 1.0

    def log_ratio(q: float | np.ndarray) -> np.ndarray:  # [E, ...] the lapse part of log w
        q = np.asarray(q)[None]
        return np.log(p / q) + (steps[:, None] - 1.0) * (np.log1p(-p) - np.log1p(-q))

    batch = {
        "event": np.ones(steps.size, dtype=bool),
        "log_weight": log_ratio(q_own)[:, 0],
        "draw_stats": stats,
        "min_gap_m": np.zeros(steps.size),
    }
    fitted, _ = fit_proposal(cfg, start, batch, EstimateSettings(smoothing=1.0))
    grid = lapse_grid(p)
    second = np.exp(log_ratio(q_own) + log_ratio(grid)).sum(axis=0)  # [G]
    assert fitted.lapse_p[0] == pytest.approx(grid[np.argmin(second)], rel=1e-12)
    cross_entropy = 2.0 / 33.0
    at = np.exp(log_ratio(q_own) + log_ratio(np.array([fitted.lapse_p[0], cross_entropy])))
    assert at.sum(axis=0)[0] < 0.9 * at.sum(axis=0)[1]


def test_a_version_3_state_still_loads():
    """A state saved before lapses (version 3: no lapse rows) continues bit for bit."""
    core = TrafficCore(ScenarioConfig(), batch_size=2, seed=1)
    _drive(core, 15)
    saved = core.state_dict()
    v3 = {**saved, "version": 3, "arrays": dict(saved["arrays"])}
    for name, rows in (("vf", L.VF_ROWS_V3), ("wf", L.WF_ROWS_V3), ("wi", L.WI_ROWS_V3)):
        v3["arrays"][name] = saved["arrays"][name][:, :rows]
    other = TrafficCore(ScenarioConfig(), batch_size=2, seed=9)
    other.load_state_dict(v3)
    for a, b in zip(_drive(core, 20), _drive(other, 20), strict=True):
        assert np.array_equal(a, b)
    v3["arrays"]["vf"] = v3["arrays"]["vf"][:, :-1]
    with pytest.raises(ValueError, match="array 'vf' has shape"):
        other.load_state_dict(v3)


def test_a_version_4_state_still_loads():
    """A state saved with two lapse classes (version 4) continues bit for bit, its per-class
    counts kept as those of classes 0 and 1."""
    core = TrafficCore(LAPSING, batch_size=3, seed=2)
    _drive(core, 15)
    saved = core.state_dict()
    wf = saved["arrays"]["wf"]
    wf[:, L.WF_LAPSE_STEPS : L.WF_LAPSE_STEPS + 2] = [[3.0, 4.0]]  # as if drawn by a proposal
    wf[:, L.WF_LAPSE_N] = 1.0
    steps, begun = L.WF_LAPSE_STEPS, L.WF_LAPSE_N
    v4_wf = np.concatenate([wf[:, :steps], wf[:, steps : steps + 2], wf[:, begun : begun + 2]], 1)
    assert v4_wf.shape[1] == L.WF_ROWS_V4
    v4 = {**saved, "version": 4, "arrays": {**saved["arrays"], "wf": v4_wf}}
    other = TrafficCore(LAPSING, batch_size=3, seed=9)
    other.load_state_dict(v4)
    assert np.array_equal(other.wf, wf)
    core.load_state_dict(saved)
    for a, b in zip(_drive(core, 20), _drive(other, 20), strict=True):
        assert np.array_equal(a, b)
    v4["arrays"]["wf"] = v4_wf[:, :-1]
    with pytest.raises(ValueError, match="array 'wf' has shape"):
        other.load_state_dict(v4)


def test_lapse_classes_bin_the_reach_ratio():
    """gap / (closing speed, at least 1.5 m/s, x the lapse's length): [0.5, 1) is class 0,
    [1, 1.5) class 1, [1.5, 2.5) class 2, below 0.5 or [2.5, 5) class 3; farther out, or not
    closing in, no class."""
    cfg = resolve_config("lapses")  # 3 s lapses
    core = TrafficCore(cfg, batch_size=1, seed=0)
    p = L.pack_params(cfg)
    vf = np.zeros_like(core.vf)
    S = (vf, core.vi, core.wf, core.wi, core.lanes, core.sched)
    s = 1
    vf[0, L.VF_V, L.EGO] = 20.0
    for closing, ratio, want in [
        (4.0, 0.3, 3), (4.0, 0.7, 0), (4.0, 1.2, 1), (4.0, 2.0, 2), (4.0, 3.0, 3), (4.0, 6.0, -1),
        (0.5, 0.7, 0), (0.5, 1.2, 1), (-0.1, 0.7, -1),
    ]:  # fmt: skip
        vf[0, L.VF_V, s] = 20.0 + closing
        gap_m = ratio * max(closing, MIN_CLOSING_MPS) * 3.0
        vf[0, L.VF_X, s] = vf[0, L.VF_X, L.EGO] - cfg.vehicle.length_m - gap_m
        assert lapse_class(S, 0, p, s) == want, (closing, ratio)
