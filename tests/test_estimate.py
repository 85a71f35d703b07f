"""Rare-event estimation: exact likelihood ratios of each proposal family, unbiased weighted
estimates, the natural proposal's unit weights, default runs untouched, resume and refusal."""

import json
import math

import numpy as np
import pytest

from marlmerge.cli import main
from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.estimate import (
    EVENT_SCORE,
    EstimateSettings,
    Estimator,
    _stalled,
    fit_proposal,
    weighted_estimate,
)
from marlmerge.evaluation.registry import policy_from_spec
from marlmerge.io.files import load
from marlmerge.sim.core import TrafficCore
from marlmerge.sim.proposal import (
    N_STATS,
    ST_BETA,
    ST_GAP_N,
    ST_GAP_SUM,
    ST_PROFILE,
    Proposal,
    TiltedDraws,
)

CFG = resolve_config("default")
TILT = Proposal(
    window_s=(5.0, 30.0),
    profile_p=((0.2, 0.2, 0.6), (0.3, 0.3, 0.4)),
    gap_scale=(0.8, 1.2),
    beta=((2.0, 1.0), (1.0, 2.0), (1.5, 1.5), (3.0, 1.0)),
)


def _draws(proposal: Proposal = TILT) -> tuple[TiltedDraws, np.random.Generator]:
    return TiltedDraws(proposal, 1), np.random.default_rng(3)


def test_gap_weights_are_the_exponential_density_ratio():
    """A gap u of natural mean m drawn with mean m s inside the window has
    p/q = (e^{-u/m} / m) / (e^{-u/(m s)} / (m s)); gaps starting outside are natural."""
    tw, g = _draws()
    m = 3.0
    times = tw.gaps(0, 0, g, m, t_last=4.0, n=12)
    gaps = np.diff(np.concatenate([[4.0], times]))
    starts = np.concatenate([[4.0], times[:-1]])
    tilted = (starts >= 5.0) & (starts < 30.0)
    s = 0.8
    want = sum(
        math.log((math.exp(-u / m) / m) / (math.exp(-u / (m * s)) / (m * s))) for u in gaps[tilted]
    )
    assert tilted.any() and not tilted.all()
    assert tw.log_w[0] == pytest.approx(want, rel=1e-12)
    assert tw.stats[0, ST_GAP_N] == tilted.sum()
    assert tw.stats[0, ST_GAP_SUM] == pytest.approx(np.sum(gaps[tilted]) / m)


def test_profile_and_beta_weights_are_exact():
    tw, g = _draws()
    natural = np.array([0.5, 0.25, 0.25])
    tilt = np.array([True, False, True, True, False, True])
    k = tw.profiles(0, 0, g, natural, tilt).astype(int)
    q = np.array(TILT.profile_p[0])
    want = np.sum(np.log(natural[k[tilt]] / q[k[tilt]]))
    assert tw.log_w[0] == pytest.approx(want, rel=1e-12)
    assert tw.stats[0, ST_PROFILE : ST_PROFILE + 3].sum() == tilt.sum()
    # Beta(2, 1) has density 2y on [0, 1]; the natural draw is uniform (density 1)
    tw2, g2 = _draws()
    values = tw2.band(0, 0, g2, (0.8, 1.2), tilt)
    y = (values - 0.8) / 0.4
    assert np.all((values >= 0.8) & (values <= 1.2))
    assert tw2.log_w[0] == pytest.approx(-np.sum(np.log(2 * y[tilt])), rel=1e-9)
    assert tw2.stats[0, ST_BETA] == tilt.sum()
    # a band of zero width is a fixed value: nothing tilted, nothing weighed
    tw3, g3 = _draws()
    assert np.all(tw3.band(0, 1, g3, (1.5, 1.5), tilt) == 1.5) and tw3.log_w[0] == 0.0


@pytest.mark.slow
def test_weighted_estimate_is_unbiased_on_a_known_rate():
    """P(y < 0.002) = 0.002 for uniform y: drawn from Beta(0.5, 3) and weighed by p/q through
    `TiltedDraws.band`, the estimate is within 3 standard errors of the truth (seed by seed and
    pooled) and its standard error far below plain sampling's at the same number of draws."""
    prop = Proposal((0.0, 1.0), TILT.profile_p, beta=((0.5, 3.0),) * 4)
    events, log_w = [], []
    for seed in range(5):
        tw = TiltedDraws(prop, 20_000)
        g = np.random.default_rng(seed)
        y = np.array([tw.band(i, 0, g, (0.0, 1.0), np.array([True]))[0] for i in range(20_000)])
        est = weighted_estimate(y < 0.002, tw.log_w)
        assert abs(est["rate"] - 0.002) < 3 * est["se"]
        assert est["se"] < math.sqrt(0.002 * 0.998 / 20_000) / 2
        events.append(y < 0.002)
        log_w.append(tw.log_w)
    pooled = weighted_estimate(np.concatenate(events), np.concatenate(log_w))
    assert abs(pooled["rate"] - 0.002) < 3 * pooled["se"]
    assert pooled["mc_equivalent_episodes"] > 4 * 100_000


def test_a_weighted_estimate_without_events_has_no_upper_bound(tmp_path, capsys):
    """No event: the weighted sample's variance is 0 whatever the rate, so the interval is
    [0, nan], not [0, 0] (which would claim the rate is exactly 0), in the estimate, the
    command's line and the grid's table."""
    est = weighted_estimate(np.zeros(1_000, dtype=bool), np.log(np.full(1_000, 0.5)))
    assert est["rate"] == 0.0 and est["ci95"][0] == 0.0 and math.isnan(est["ci95"][1])
    assert math.isnan(est["se"]) and est["ess"] == 0.0
    one = weighted_estimate(np.arange(1_000) == 3, np.zeros(1_000))  # one event: a bound
    assert one["ci95"][1] > one["rate"] > 0.0
    args = ["estimate", "gap", "--scenario", "light", "--method", "is", "--episodes", "20"]
    assert main([*args, "--rounds", "1", "--round-episodes", "20", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "0 [0, nan]" in out and "no event: no upper bound" in out


def test_the_whole_draw_pipeline_weighs_exactly():
    """Over many tilted roads the mean weight is 1 (E_q[p/q] = 1): a wrong ratio anywhere in the
    arrivals, profiles, driver bands or the ego's start speed would bias it. The natural
    proposal weighs every road exactly 1; no proposal leaves the core's draws as they were."""
    mild = Proposal(
        (18.0, 24.0),
        ((0.3, 0.3, 0.4), (0.4, 0.3, 0.3)),
        gap_scale=(0.9, 1.0),
        beta=((1.2, 1.0), (1.0, 1.2), (1.0, 1.0), (1.3, 1.0)),
    )
    core = TrafficCore(CFG, 2000, seed=11, proposal=mild)
    core.step(np.zeros(2000))
    w = np.exp(core.streams.tilted.log_w)
    se = np.std(w, ddof=1) / math.sqrt(w.size)
    assert core.streams.tilted.stats[:, ST_GAP_N].mean() > 1.0  # the window was drawn in
    assert abs(np.mean(w) - 1.0) < 4 * se and se < 0.05
    natural = TrafficCore(CFG, 16, seed=11, proposal=Proposal.natural(CFG))
    assert np.all(natural.streams.tilted.log_w == 0.0)
    plain, again = TrafficCore(CFG, 16, seed=11), TrafficCore(CFG, 16, seed=11)
    assert plain.streams.tilted is None
    for name in ("vf", "sched"):
        assert np.array_equal(getattr(plain, name), getattr(again, name))


def test_proposals_refuse_what_would_bias_or_break():
    with pytest.raises(ValueError, match=r"profile_p\[0\]\[2\] = 0.0"):
        TrafficCore(CFG, 1, seed=0, proposal=Proposal((5.0, 30.0), ((0.5, 0.5, 0.0),) * 2))
    with pytest.raises(ValueError, match="gap_scale"):
        Proposal((5.0, 30.0), TILT.profile_p, gap_scale=(0.0, 1.0))
    with pytest.raises(ValueError, match="window_s"):
        Proposal((30.0, 5.0), TILT.profile_p)
    with pytest.raises(ValueError, match="state_dict"):
        TrafficCore(CFG, 1, seed=0, proposal=TILT).state_dict()
    with pytest.raises(ValueError, match="method = 'x'"):
        EstimateSettings(method="x")
    with pytest.raises(ValueError, match="rel_ci or episodes, not both"):
        EstimateSettings(rel_ci=0.2, episodes=10)


def test_cross_entropy_moves_towards_the_elite():
    """Elite episodes drew adversarial right-lane vehicles and short gaps: the fit raises both."""
    n = 100
    stats = np.zeros((n, N_STATS))
    event = np.zeros(n, dtype=bool)
    event[:10] = True
    stats[:10, ST_PROFILE + 2] = 3.0  # adversarial
    stats[10:, ST_PROFILE + 0] = 3.0
    stats[:, ST_GAP_N] = 4.0
    stats[:10, ST_GAP_SUM] = 2.0
    stats[10:, ST_GAP_SUM] = 4.0
    batch = {
        "event": event,
        "log_weight": np.zeros(n),
        "draw_stats": stats,
        "min_gap_m": np.where(np.arange(n) < 50, -3.0, 10.0),  # overlaps before joining
    }
    settings = EstimateSettings(elite_fraction=0.1, smoothing=1.0)
    fitted, level = fit_proposal(CFG, Proposal.natural(CFG), batch, settings)
    assert level == EVENT_SCORE
    assert fitted.profile_p[0][2] == pytest.approx(0.96 / 1.0, abs=0.01)
    assert fitted.gap_scale[0] == pytest.approx(0.5)
    assert fitted.profile_p[1] == Proposal.natural(CFG).profile_p[1]  # nothing drawn: kept


def test_estimate_resumes_bit_for_bit_and_refuses_another_request(tmp_path):
    cfg = resolve_config("grid_dense_adversarial")
    policy = policy_from_spec("hold", cfg)
    settings = EstimateSettings(episodes=60, batch=30, rounds=2, round_episodes=40, worlds=40)
    out = tmp_path / "est"
    first = Estimator(policy, "hold", cfg, settings, out).run()
    assert first["episodes"] == first["episodes_run"] == first["fitting_episodes"] + 60
    (last,) = (out / "batches").glob("2_1_*.pt")
    last.unlink()  # as if killed before the last batch was written
    again = Estimator(policy, "hold", cfg, settings, out).run()
    assert again["episodes_run"] == 30 and again["rate"] == first["rate"]
    assert again["ci95"] == first["ci95"] and again["proposal"] == first["proposal"]
    # the estimate pools the rounds' episodes with the final stage's, each with its own weight
    batches = [load(f, "batch") for f in sorted((out / "batches").glob("*.pt"))]
    pooled = weighted_estimate(
        np.concatenate([b["event"] for b in batches]),
        np.concatenate([b["log_weight"] for b in batches]),
    )
    assert len(batches) == len(first["rounds"]) + 2
    assert first["rate"] == pytest.approx(pooled["rate"], rel=1e-12)
    assert first["events"] == pooled["events"] > 0
    other = EstimateSettings(episodes=60, batch=30, rounds=2, round_episodes=40, seed=5)
    with pytest.raises(ValueError, match="seed = 0, asked 5"):
        Estimator(policy, "hold", cfg, other, out).run()
    request = out / "request.json"
    older = {k: v for k, v in json.loads(request.read_text()).items() if k != "version"}
    request.write_text(json.dumps(older))  # written before batches were versioned
    with pytest.raises(ValueError, match="holds batches of estimate version 1"):
        Estimator(policy, "hold", cfg, settings, out).run()


def test_estimate_command_prints_the_summary_last(tmp_path, capsys):
    out = tmp_path / "mc"
    argv = ["estimate", "hold", "--scenario", "grid_dense_adversarial", "--method", "mc"]
    assert main([*argv, "--episodes", "50", "--worlds", "25", "--out", str(out)]) == 0
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(last) == {"rate", "ci95", "episodes", "ess", "mc_equivalent_episodes", "method"}
    assert last["method"] == "mc" and last["episodes"] == 50
    assert last["ci95"][0] <= last["rate"] <= last["ci95"][1]
    with pytest.raises(SystemExit):
        main(["estimate", "hold", "--method", "nope"])


def test_cross_entropy_rounds_stop_when_the_level_stalls():
    assert not _stalled([9.0, 8.0])
    assert not _stalled([9.0, 8.0, 7.5, 7.0])  # still falling
    assert _stalled([9.0, 8.0, 8.1, 7.99])  # two rounds without falling below 8.0 - 0.05


def test_rounds_wait_for_the_lapse_fits_events(tmp_path):
    """With lapses tilted, a stalled gap level does not end the rounds before the lapse fit has
    seen its events: rare lapses, tiny rounds, no event, so every round runs."""
    cfg = resolve_config("lapses_rare")
    settings = EstimateSettings(episodes=20, batch=20, rounds=5, round_episodes=20, worlds=20)
    report = Estimator(policy_from_spec("gap", cfg), "gap", cfg, settings, tmp_path).run()
    levels = [r["level"] for r in report["rounds"]]
    assert sum(r["events"] for r in report["rounds"]) < 5
    assert len(levels) == 5 and any(_stalled(levels[:k]) for k in range(3, 5))  # went on


def test_the_grids_table_gives_no_interval_for_a_run_without_events():
    from marlmerge.evaluation.grid import _estimate_table

    cell = {"policy": "gap", "condition": "light", "rate": 0.0, "se": math.nan, "ess": 0.0}
    lines = _estimate_table([cell], ["gap"], ["light"])
    assert any("[no interval: a run without events]" in line for line in lines)
    cell = cell | {"rate": 0.001, "se": 0.0004, "ess": 40.0}
    assert any(
        "0.100 [0.022–0.178] ESS 40" in line for line in _estimate_table([cell], ["gap"], ["light"])
    )
