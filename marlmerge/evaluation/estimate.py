"""Crash rates users can trust: a policy's collision (or failure) rate with a 95 % interval, by
plain Monte Carlo or by importance sampling of the traffic it meets.

`method="mc"`: first-ego episodes on fresh roads, the rate k/n with its Wilson interval.

`method="is"`: the traffic near the first ramp vehicle's merge is drawn from a `Proposal`
(`marlmerge.sim.proposal`) and each episode weighed by its exact likelihood ratio w = p/q, so
mean(1[event] * w) is an unbiased estimate of the natural rate. The proposal is fitted by the
adaptive (multilevel) cross-entropy method (Rubinstein & Kroese 2004; O'Kelly et al. 2018).
Each round runs `round_episodes` episodes under the current proposal and ranks them by a danger
score: an event scores `EVENT_SCORE`, below any gap; any other episode its smallest gap to the
right-lane vehicles in the merge zone (m; negative while it overlaps one before joining). It
keeps the `elite_fraction` most dangerous (or every event once there are that many) and refits
the proposal to the elite's draws, each weighed by w (weighted maximum likelihood for the
profiles and gaps, moments for the Betas), smoothed. Attention lapses are fitted to the events
alone, pooled over the rounds so far: the probabilities that minimise the estimate's second
moment as those events measure it (`_fit_lapse`). The rounds stop when the elite is all events,
when its danger level has not fallen for `STALL_ROUNDS` rounds (the family can get no closer;
with lapses tilted, not before the lapse fit has had its events), or after `rounds`. The
final stage then runs fresh episodes under the last proposal, in batches, until the interval's
half-width is at most `rel_ci` times the rate (after `min_events` events) or `episodes` are
done. The estimate pools every episode, the rounds' included: each is weighed by the exact
ratio of the proposal it was drawn under, a proposal fitted to the episodes before it only, so
every term has the rate as its expectation and their mean stays unbiased (the pooled adaptive
importance-sampling estimator); the rounds' episodes are paid for anyway.

`method="split"`: with attention lapses, the lapses that could close the ego's gap are split
instead of tilted (`marlmerge.evaluation.splitting`): no fitting rounds; each batch runs its
trunks and then their branches, and `episodes` counts both.

Reported: the rate, its 95 % interval (normal, from the weighted sample's variance), the
episodes used (fitting rounds included), the effective sample size of the event weights
(sum y)^2 / sum y^2 with y = 1[event] w, the mean weight (1 in expectation: far from 1 flags a
proposal that misses part of the natural traffic) and the Monte Carlo episodes the same interval
would have needed, rate (1 - rate) / se^2. An estimate with few effective events (`ess` <
`MIN_TRUSTED_ESS`) is marked untrusted: its variance estimate is itself unreliable.

Every batch is written to `OUT/batches/` as it finishes, and `OUT/request.json` records what
was asked: a rerun with the same request reuses the batches (an interrupted estimate resumes,
bit for bit); a different request, or batches drawn by another `ESTIMATE_VERSION`, refuses,
naming what differs. Episode e of stage s, batch i is the first ego of a world seeded
`SeedSequence(seed, spawn_key=(s, i, e))`.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from marlmerge.config import ScenarioConfig, require_ego, to_dict
from marlmerge.evaluation.metrics import event_mask, weighted_mean_estimate, wilson_interval
from marlmerge.evaluation.splitting import split_batch, split_estimate, split_proposal
from marlmerge.io.files import load, save, write_text
from marlmerge.sim.layout import lapse_step_probability
from marlmerge.sim.proposal import (
    BETA_RANGE,
    GAP_SCALE_RANGE,
    LAPSE_P_MAX,
    N_LAPSE_CLASSES,
    N_PROFILES,
    N_STATS,
    ST_BETA,
    ST_GAP_N,
    ST_GAP_SUM,
    ST_LAPSE_N,
    ST_LAPSE_STEPS,
    ST_PROFILE,
    Proposal,
    natural_profiles,
)

METHODS = ("mc", "is", "split")
EVENTS = ("collision", "failure")
"""collision: the ramp vehicle collided; failure: collided or truncated (never merged)."""
MIN_TRUSTED_ESS = 30.0
DEFAULT_REL_CI = 0.2
PROFILE_FLOOR = 0.02
"""A fitted profile probability is at least this where the scenario draws the profile."""
ESTIMATE_VERSION = 3
"""How the batches are drawn (2: the first tilted lapse only, the lapse fit by second
moment; 3: four lapse classes, the rounds pooled into the estimate); a folder of another
version is refused rather than resumed (1: before the field existed). Monte Carlo batches are
natural draws in every version and stay valid."""
STOP_KEYS = ("rel_ci", "episodes", "max_episodes")
"""Settings that only say when to stop: a rerun may change them and keep the batches."""
STAGE_CE, STAGE_FINAL, STAGE_MC, STAGE_SPLIT = 1, 2, 3, 4
MIN_LAPSE_EVENTS = 5
"""Events the rounds need (pooled) before they fit the lapse probabilities to them."""
LAPSE_GRID = 48
"""Candidate probabilities per lapse class (`lapse_grid`)."""
LAPSE_SWEEPS = 4
"""Rounds of coordinate descent over the classes in the lapse fit."""
LAPSE_START_P = (0.1, 0.04, 0.05, 0.01)
"""With attention lapses the fit starts from these per-step lapse probabilities (by class,
`marlmerge.sim.lapses.lapse_class`; at least the natural p) for the driver behind the ego's gap:
natural lapses are too rare for a first round to see any. Classes 0-2 near where the fit took
them on `envs/lapses.toml`; class 3, whose lapses seldom end in a collision, at the floor."""
LAPSE_Q_MIN = 0.01
"""The fit keeps every class's probability at least this (or the natural p, if higher): fitted
to a few events, the second moment drives a class that none of them came from down to p, and a
later collision from it then weighs about 1, tens of times the others (on two held-out
scenarios one such collision carried half the estimate's variance)."""
EVENT_SCORE = -1.0e6
"""The danger score of an event: below any gap an episode without one can have (m)."""

if TYPE_CHECKING:  # torch is imported only once the arguments are checked
    from marlmerge.evaluation.rollout import EgoPolicy


@dataclass(frozen=True)
class EstimateSettings:
    method: str = "is"
    event: str = "collision"
    rel_ci: float | None = None
    """Stop once the interval's half-width is at most this times the rate (with neither this nor
    `episodes` given: `DEFAULT_REL_CI`)."""
    episodes: int | None = None
    """Final-stage episodes to run (instead of `rel_ci`); with `split`, trunks (each with its
    branches)."""
    max_episodes: int = 2_000_000
    """Final-stage episodes at most, whatever `rel_ci` says."""
    seed: int = 0
    worlds: int = 500
    """Episodes stepped at once."""
    batch: int = 5000
    """Final-stage (and Monte Carlo) episodes per batch."""
    rounds: int = 8
    """Cross-entropy rounds at most."""
    round_episodes: int = 2000
    elite_fraction: float = 0.1
    smoothing: float = 0.7
    """Weight of the new fit against the previous proposal."""
    min_events: int = 10
    """Events needed before `rel_ci` may stop the estimate."""

    def __post_init__(self) -> None:
        def bad(key: str, why: str) -> ValueError:
            return ValueError(f"estimate: {key} = {getattr(self, key)!r}: {why}")

        if self.method not in METHODS:
            raise bad("method", f"must be one of {', '.join(METHODS)}")
        if self.event not in EVENTS:
            raise bad("event", f"must be one of {', '.join(EVENTS)}")
        if self.rel_ci is not None and self.episodes is not None:
            raise ValueError("estimate: give rel_ci or episodes, not both")
        if self.rel_ci is None and self.episodes is None:
            object.__setattr__(self, "rel_ci", DEFAULT_REL_CI)
        if self.rel_ci is not None and not 0.0 < self.rel_ci < 10.0:
            raise bad("rel_ci", "must be in (0, 10)")
        for key in ("episodes", "max_episodes", "worlds", "batch", "rounds", "round_episodes"):
            value = getattr(self, key)
            if value is not None and (not isinstance(value, int) or value < 1):
                raise bad(key, "must be an integer >= 1")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise bad("seed", "must be an integer >= 0")
        if not 0.0 < self.elite_fraction < 0.5:
            raise bad("elite_fraction", "must be in (0, 0.5)")
        if not 0.0 < self.smoothing <= 1.0:
            raise bad("smoothing", "must be in (0, 1]")
        if not isinstance(self.min_events, int) or self.min_events < 1:
            raise bad("min_events", "must be an integer >= 1")


# ---------------------------------------------------------------------- estimates from samples
def weighted_estimate(event: np.ndarray, log_w: np.ndarray) -> dict[str, Any]:
    """The importance-sampling estimate of P(event) from episodes drawn under a proposal:
    rate, 95 % interval, ESS of the event weights, mean weight, MC-equivalent episodes."""
    w = np.exp(log_w)
    y = np.where(event, w, 0.0)
    return weighted_mean_estimate(y, y) | {
        "events": int(np.count_nonzero(event)),
        "mean_weight": float(np.mean(w)),
    }


def mc_estimate(event: np.ndarray) -> dict[str, Any]:
    """Plain Monte Carlo: k/n with its Wilson interval."""
    n, k = event.size, int(np.count_nonzero(event))
    lo, hi = wilson_interval(k, n)
    return {
        "rate": k / n,
        "ci95": [lo, hi],
        "se": math.sqrt(k / n * (1 - k / n) / n),
        "events": k,
        "ess": float(n),
        "mean_weight": 1.0,
        "max_weight_share": 1.0 / k if k else math.nan,
        "mc_equivalent_episodes": float(n),
    }


def _pooled_weighted(parts: list[dict[str, np.ndarray]]) -> dict[str, Any]:
    return weighted_estimate(
        np.concatenate([p["event"] for p in parts]),
        np.concatenate([p["log_weight"] for p in parts]),
    )


def _pooled_mc(parts: list[dict[str, np.ndarray]]) -> dict[str, Any]:
    return mc_estimate(np.concatenate([p["event"] for p in parts]))


def precise_enough(est: dict[str, Any], settings: EstimateSettings) -> bool:
    if settings.rel_ci is None or est["events"] < settings.min_events or est["rate"] <= 0:
        return False
    half = (est["ci95"][1] - est["ci95"][0]) / 2
    return half <= settings.rel_ci * est["rate"]


# ---------------------------------------------------------------------- the cross-entropy fit
def danger_score(event: np.ndarray, min_gap_m: np.ndarray) -> np.ndarray:
    """`EVENT_SCORE` for an event, else the smallest merge-zone gap (m; inf if never in the
    zone; negative while the ego overlaps a right-lane vehicle before joining)."""
    return np.where(event, EVENT_SCORE, min_gap_m)


def fit_proposal(
    cfg: ScenarioConfig,
    current: Proposal,
    batch: dict[str, np.ndarray],
    settings: EstimateSettings,
    events: dict[str, np.ndarray] | None = None,
) -> tuple[Proposal, float]:
    """One cross-entropy step: the proposal refitted to the elite of `batch` (drawn under
    `current`), smoothed towards `current`, and the elite's danger level (`EVENT_SCORE`: events
    only). The lapse probabilities are fitted to `events` (`events_of` every round so far;
    default: those of `batch`)."""
    score = danger_score(batch["event"], batch["min_gap_m"])
    n_elite = max(int(math.ceil(settings.elite_fraction * score.size)), 1)
    level = float(np.sort(score)[n_elite - 1])
    elite = score <= level
    s = _weighted_stats(batch, elite)  # [N_STATS]
    alpha = settings.smoothing

    def mix(new: float, old: float) -> float:
        return alpha * new + (1.0 - alpha) * old

    natural = np.asarray(natural_profiles(cfg))
    drawn = (natural > 0) | cfg.sample.active
    profiles = []
    for lane in range(2):
        counts = s[ST_PROFILE + N_PROFILES * lane : ST_PROFILE + N_PROFILES * (lane + 1)]
        old = np.asarray(current.profile_p[lane])
        if counts.sum() <= 0:
            profiles.append(tuple(old))
            continue
        fit = np.where(drawn, np.maximum(counts / counts.sum(), PROFILE_FLOOR), 0.0)
        new = alpha * fit / fit.sum() + (1.0 - alpha) * old
        profiles.append(tuple(float(p) for p in new / new.sum()))
    gaps = []
    for lane in range(2):
        n = s[ST_GAP_N + lane]
        fit = s[ST_GAP_SUM + lane] / n if n > 0 else current.gap_scale[lane]
        gaps.append(mix(float(np.clip(fit, *GAP_SCALE_RANGE)), current.gap_scale[lane]))
    betas = []
    for j, (a_old, b_old) in enumerate(current.beta):
        n, sy, syy = s[ST_BETA + 3 * j : ST_BETA + 3 * j + 3]
        mean = sy / n if n > 0 else 0.5
        var = syy / n - mean * mean if n > 0 else 0.0
        if n <= 0 or var <= 1e-9 or not 0.0 < mean < 1.0:
            betas.append((a_old, b_old))
            continue
        common = max(mean * (1.0 - mean) / var - 1.0, 1e-6)
        a_fit = float(np.clip(mean * common, *BETA_RANGE))
        b_fit = float(np.clip((1.0 - mean) * common, *BETA_RANGE))
        betas.append((mix(a_fit, a_old), mix(b_fit, b_old)))
    fitted = replace(
        current,
        profile_p=tuple(profiles),  # type: ignore[arg-type]
        gap_scale=tuple(gaps),  # type: ignore[arg-type]
        beta=tuple(betas),
        lapse_p=_fit_lapse(
            cfg, current, events_of(batch, current) if events is None else events, alpha
        ),
    )
    return fitted, level


def _fit_lapse(
    cfg: ScenarioConfig, current: Proposal, events: dict[str, np.ndarray], alpha: float
) -> tuple[float, ...] | None:
    """The lapse probabilities (one per class, between the natural p and `LAPSE_P_MAX`) that
    minimise the estimate's second moment over the `events` seen so far, smoothed; kept with
    fewer than `MIN_LAPSE_EVENTS` events (None: lapses are not tilted).

    Under q an event's weight would be w_q = w · exp(L(q) - L(q_own)), where L is the lapse part
    of its log ratio (`lapse_log_ratio`; q_own: the proposal it was drawn under, `lapse_q`), and
    the second moment E_q[w_q^2 1_event] = E_p[w_q 1_event] is estimated from the events by
    sum w · w_q, searched on `lapse_grid` by coordinate descent (one class at a time, the
    others held, `LAPSE_SWEEPS` rounds, from the grid's lowest point). Unlike a cross-entropy
    fit (lapses per step), this weighs what a high q costs in long windows: each step without
    a lapse multiplies the weight by (1 - p) / (1 - q) > 1. The events alone, not the elite by
    gap: a lapse makes no gap smaller until the ego is ahead of the lapsing driver."""
    if current.lapse_p is None:
        return None
    if _too_few_for_lapse_fit(events):
        return current.lapse_p
    p = lapse_step_probability(cfg)
    grid = lapse_grid(p)  # [G]
    stats, log_w = events["draw_stats"], events["log_weight"]
    k = stats[:, ST_LAPSE_N : ST_LAPSE_N + N_LAPSE_CLASSES]  # [E, C]
    n = stats[:, ST_LAPSE_STEPS : ST_LAPSE_STEPS + N_LAPSE_CLASSES]
    base = 2.0 * log_w - lapse_log_ratio(stats, p, events["lapse_q"])  # [E]
    part = _lapse_log_terms(k[:, :, None], n[:, :, None], p, grid)  # [E, C, G]: L_c(q) per event
    classes = np.arange(N_LAPSE_CLASSES)
    best = np.zeros(N_LAPSE_CLASSES, dtype=np.int64)  # grid index per class: the lowest
    for _ in range(LAPSE_SWEEPS):  # coordinate descent: each class's best q given the others
        for c in range(N_LAPSE_CLASSES):
            held = np.delete(part[:, classes, best], c, axis=1).sum(axis=1)  # [E]
            total = (base + held)[:, None] + part[:, c, :]  # [E, G]
            peak = total.max(axis=0)
            best[c] = int(np.argmin(peak + np.log(np.exp(total - peak).sum(axis=0))))
    return tuple(
        float(alpha * grid[i] + (1.0 - alpha) * old)
        for i, old in zip(best, current.lapse_p, strict=True)
    )


def _too_few_for_lapse_fit(events: dict[str, np.ndarray]) -> bool:
    return np.count_nonzero(events["event"]) < MIN_LAPSE_EVENTS


def lapse_grid(p: float) -> np.ndarray:
    """The lapse probabilities the fit chooses from, for every class [LAPSE_GRID]: log-spaced
    from `LAPSE_Q_MIN` (at least the natural p) to `LAPSE_P_MAX`."""
    return np.geomspace(min(max(p, LAPSE_Q_MIN), LAPSE_P_MAX), LAPSE_P_MAX, LAPSE_GRID)


def events_of(batch: dict[str, np.ndarray], proposal: Proposal) -> dict[str, np.ndarray]:
    """The events of a batch drawn under `proposal`, with the lapse probabilities they were
    drawn under (`lapse_q` [E, N_LAPSE_CLASSES]) where lapses are tilted."""
    events = {k: v[batch["event"]] for k, v in batch.items()}
    if proposal.lapse_p is not None:
        events["lapse_q"] = np.tile(proposal.lapse_p, (len(events["event"]), 1))
    return events


def lapse_log_ratio(stats: np.ndarray, p: float, q: np.ndarray) -> np.ndarray:
    """The lapse part of each episode's log ratio [E] from its draw statistics [E, N_STATS]
    under per-class proposal probabilities q ([N_LAPSE_CLASSES] or [E, N_LAPSE_CLASSES]):
    log p/q_c per lapse begun, log (1 - p)/(1 - q_c) per tilted step without one."""
    k = stats[:, ST_LAPSE_N : ST_LAPSE_N + N_LAPSE_CLASSES]  # [E, C]
    n = stats[:, ST_LAPSE_STEPS : ST_LAPSE_STEPS + N_LAPSE_CLASSES]
    return _lapse_log_terms(k, n, p, q).sum(axis=1)


def _lapse_log_terms(k: np.ndarray, n: np.ndarray, p: float, q: np.ndarray) -> np.ndarray:
    """log p/q per lapse begun (k of them) and log (1 - p)/(1 - q) per other tilted step (n - k
    of the n), broadcast over the shapes of k, n and q."""
    return k * np.log(p / q) + (n - k) * (np.log1p(-p) - np.log1p(-q))


def _weighted_stats(batch: dict[str, np.ndarray], chosen: np.ndarray) -> np.ndarray:
    """The draw statistics summed over the `chosen` episodes of the batch, each weighed by its
    ratio relative to the largest among them (relative weights suffice for the fits)."""
    if not chosen.any():
        return np.zeros(batch["draw_stats"].shape[1])
    log_w = batch["log_weight"]
    w = np.where(chosen, np.exp(log_w - np.max(log_w[chosen])), 0.0)
    return w @ batch["draw_stats"]


def initial_proposal(cfg: ScenarioConfig) -> Proposal:
    """Where the cross-entropy rounds start: the scenario's own draws, with lapses (if its
    drivers lapse) at `LAPSE_START_P` per step for the driver behind the ego's gap."""
    natural = Proposal.natural(cfg)
    p = lapse_step_probability(cfg)
    if p <= 0.0:
        return natural
    return replace(natural, lapse_p=tuple(max(p, q) for q in LAPSE_START_P))


STALL_ROUNDS = 2
"""The cross-entropy rounds stop when the elite's danger level has not fallen for this many
rounds in a row (the proposal family cannot move closer to the event)."""
STALL_TOLERANCE_M = 0.05


def _stalled(levels: list[float]) -> bool:
    if len(levels) <= STALL_ROUNDS:
        return False
    best_before = min(levels[:-STALL_ROUNDS])
    return min(levels[-STALL_ROUNDS:]) > best_before - STALL_TOLERANCE_M


# ---------------------------------------------------------------------- running it
WEIGHT_KEYS = ("log_weight", "draw_stats", "min_gap_m")


def _filled(data: dict[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    """A batch with the weight keys a Monte Carlo batch leaves out (weight 1, nothing drawn)."""
    empty = {
        "log_weight": np.zeros(n),
        "draw_stats": np.zeros((n, N_STATS)),
        "min_gap_m": np.full(n, np.inf),
    }
    return empty | data


class Estimator:
    """One estimate (`EstimateSettings`) of one policy on one scenario, writing to `out`."""

    def __init__(
        self,
        policy: EgoPolicy,
        policy_name: str,
        cfg: ScenarioConfig,
        settings: EstimateSettings,
        out: str | Path,
        policy_files: str = "",
    ):
        """`policy_files`: a digest of the policy's saved files (`registry.saved_files_of`), so
        that a run trained again into the same folder does not reuse the old run's batches."""
        require_ego(cfg, f"estimate: scenario {cfg.name!r}")
        self.policy, self.cfg, self.settings = policy, cfg, settings
        self.out = Path(out)
        self.request = {
            "version": ESTIMATE_VERSION,
            "policy": policy_name,
            "policy_files": policy_files,
            "scenario": to_dict(cfg),
            "settings": asdict(settings),
        }
        self.episodes_run = 0
        self.episodes_reused = 0
        self.split = split_proposal(cfg) if settings.method == "split" else None
        """The splitting proposal (refused for a scenario without lapses before any work)."""

    def check_request(self) -> None:
        """A new `out`, or one holding the same request (stopping rules aside)."""
        path = self.out / "request.json"
        if not path.exists():
            self.out.joinpath("batches").mkdir(parents=True, exist_ok=True)
            write_text(path, json.dumps(self.request, indent=1))
            return
        old = json.loads(path.read_text())
        # Monte Carlo draws naturally, as every version did: its batches stay valid
        if self.settings.method != "mc" and old.get("version", 1) != ESTIMATE_VERSION:
            raise ValueError(
                f"{self.out} holds batches of estimate version {old.get('version', 1)}, drawn "
                f"as this one ({ESTIMATE_VERSION}) no longer draws them; use another --out or "
                "delete it"
            )
        for key in ("policy", "scenario"):
            if old.get(key) != self.request[key]:
                raise ValueError(
                    f"{self.out} holds an estimate of another {key}; use another --out or delete it"
                )
        if old.get("policy_files", self.request["policy_files"]) != self.request["policy_files"]:
            raise ValueError(
                f"{self.out} holds an estimate of {old['policy']!r} whose saved policy has changed "
                "since (trained again?); use another --out or delete it"
            )
        mine = self.request["settings"]
        for key, value in sorted(old.get("settings", {}).items()):
            if key not in STOP_KEYS and mine.get(key) != value:
                raise ValueError(
                    f"{self.out} holds an estimate with {key} = {value!r}, asked "
                    f"{mine.get(key)!r}; use another --out or delete it"
                )
        self.out.joinpath("batches").mkdir(parents=True, exist_ok=True)

    def _batch_path(self, spawn: tuple[int, int], proposal: Proposal | None) -> Path:
        """Where a batch is kept: named by its stage and index and by what it was drawn under."""
        drawn = "mc" if proposal is None else json.dumps(proposal.to_dict(), sort_keys=True)
        tag = hashlib.sha256(drawn.encode()).hexdigest()[:12]
        return self.out / "batches" / f"{spawn[0]}_{spawn[1]}_{tag}.pt"

    def batch(
        self, spawn: tuple[int, int], n: int, proposal: Proposal | None
    ) -> dict[str, np.ndarray]:
        """The episodes of one batch (read back if this request ran it before, under the same
        proposal: the file is named by both)."""
        path = self._batch_path(spawn, proposal)
        if path.exists():
            self.episodes_reused += n
            return _filled(load(path, "estimate batch"), n)
        from marlmerge.evaluation.rollout import rollout_first_egos

        s = self.settings
        seeds = [np.random.SeedSequence(s.seed, spawn_key=(*spawn, e)) for e in range(n)]
        rec, _ = rollout_first_egos(
            self.policy, self.cfg, n, 0, s.worlds, road_seeds=seeds, proposal=proposal
        )
        data = {"event": event_mask(rec["outcome"], s.event)} | {
            k: rec[k] for k in WEIGHT_KEYS if k in rec
        }
        save(data, path)  # Monte Carlo batches keep only their events
        self.episodes_run += n
        return _filled(data, n)

    def fit(self) -> tuple[Proposal, list[dict[str, Any]], list[dict[str, np.ndarray]]]:
        """The cross-entropy rounds: the final proposal, what each round saw and its batch."""
        s = self.settings
        proposal = initial_proposal(self.cfg)
        rounds = []
        batches: list[dict[str, np.ndarray]] = []
        seen: list[dict[str, np.ndarray]] = []  # the events of every round so far
        for r in range(s.rounds):
            data = self.batch((STAGE_CE, r), s.round_episodes, proposal)
            batches.append(data)
            seen.append(events_of(data, proposal))
            pooled = {k: np.concatenate([e[k] for e in seen]) for k in seen[-1]}
            fitted, level = fit_proposal(self.cfg, proposal, data, s, events=pooled)
            rounds.append(
                {
                    "round": r,
                    "proposal": proposal.to_dict(),
                    "episodes": s.round_episodes,
                    "events": int(np.count_nonzero(data["event"])),
                    "level": level,
                }
            )
            proposal = fitted
            if level <= EVENT_SCORE:  # the elite is all events: the proposal aims at the event
                break
            # the lapse fit has not run yet: the gap's level says nothing about lapses
            starved = proposal.lapse_p is not None and _too_few_for_lapse_fit(pooled)
            if _stalled([x["level"] for x in rounds]) and not starved:
                break
        return proposal, rounds, batches

    def split_batch(self, i: int, n: int) -> dict[str, np.ndarray]:
        """Batch i of the splitting estimate: n trunks and their branches (read back if this
        request ran it before with the same branch probabilities)."""
        assert self.split is not None
        path = self._batch_path((STAGE_SPLIT, i), self.split)
        if path.exists():
            data = load(path, "estimate batch")
            self.episodes_reused += n + data["branch_of"].size
            return data
        s = self.settings
        seeds = [np.random.SeedSequence(s.seed, spawn_key=(STAGE_SPLIT, i, e)) for e in range(n)]
        data = split_batch(self.policy, self.cfg, seeds, s.worlds, s.event)
        save(data, path)
        self.episodes_run += n + data["branch_of"].size
        return data

    def final(
        self,
        draw: Callable[[int, int], dict[str, np.ndarray]],
        estimate: Callable[[list[dict[str, np.ndarray]]], dict[str, Any]],
        rounds: list[dict[str, np.ndarray]] | None = None,
    ) -> tuple[dict[str, Any], int]:
        """Batches `draw(i, n)` until precise enough (or the episodes asked): the estimate of
        them pooled with the `rounds`' episodes, and the final stage's episodes asked (with
        splitting: trunks)."""
        s = self.settings
        target = s.episodes if s.episodes is not None else s.max_episodes
        parts: list[dict[str, np.ndarray]] = list(rounds or [])
        done, i = 0, 0
        est: dict[str, Any] = {}
        while done < target:
            n = min(s.batch, target - done)
            parts.append(draw(i, n))
            done, i = done + n, i + 1
            est = estimate(parts)
            if s.episodes is None and precise_enough(est, s):
                break
        return est, done

    def run(self) -> dict[str, Any]:
        start = time.perf_counter()
        self.check_request()
        s = self.settings
        rounds: list[dict[str, Any]] = []
        proposal = None
        if s.method == "is":
            proposal, rounds, batches = self.fit()
            est, final_n = self.final(
                lambda i, n: self.batch((STAGE_FINAL, i), n, proposal), _pooled_weighted, batches
            )
        elif s.method == "split":
            proposal = self.split
            est, _ = self.final(self.split_batch, split_estimate)
            final_n = est["trunk_episodes"] + est["branch_episodes"]
        else:
            est, final_n = self.final(lambda i, n: self.batch((STAGE_MC, i), n, None), _pooled_mc)
        fitting_n = sum(r["episodes"] for r in rounds)
        report = {
            "policy": self.request["policy"],
            "scenario": self.cfg.name,
            "method": s.method,
            "event": s.event,
            **est,
            "episodes": final_n + fitting_n,
            "final_episodes": final_n,
            "fitting_episodes": fitting_n,
            "trusted": bool(est["ess"] >= MIN_TRUSTED_ESS),
            "precise_enough": bool(precise_enough(est, s)),
            "proposal": None if proposal is None else proposal.to_dict(),
            "rounds": rounds,
            "episodes_run": self.episodes_run,
            "episodes_reused": self.episodes_reused,
            "wall_s": time.perf_counter() - start,
        }
        write_text(self.out / "report.json", json.dumps(report, indent=1))
        return report
