"""Evaluation metrics of ramp-vehicle episodes, computed from trajectories (not from the reward).

An `EpisodeTrajectory` is one ego episode at simulator-step resolution; `episode_metrics` turns it
into a flat dict of named numbers; `aggregate` summarises one metric over many episodes with a 95 %
interval; `METRICS` is the one table of names, units and directions that reports use.
`TrajectoryRecorder` collects trajectories from the per-simulator-step ego trace of each
`TrafficCore.rollout`.

Conventions: sample k of a trajectory is at time `t0_s + k * dt_s` after the ego departed (the
recorder samples after every simulator step, so its `t0_s = dt_s`). Undefined values are `nan`
(e.g. the time to merge of an ego that never merged); "never happened" values of a minimum are
`inf` (e.g. the minimum time-to-collision of an ego that never closed in on anyone).
NumPy only, like the core.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_NONE, OUTCOME_SUCCESS, OUTCOME_TRUNCATED
from marlmerge.sim.layout import TR_A, TR_AB, TR_DB, TR_DF, TR_V, TR_VB, TR_VF, TR_X
from marlmerge.sim.state import Rollout

Z_95 = 1.959963984540054
"""Two-sided 95 % quantile of the standard normal."""


@dataclass
class EpisodeTrajectory:
    """One ego episode at simulator-step resolution (arrays [T], SI units)."""

    dt_s: float
    x_m: np.ndarray  # ego front-bumper position along its path, 0 = merge point
    v_mps: np.ndarray  # ego speed
    a_mps2: np.ndarray  # ego realised acceleration over the step
    d_front_m: np.ndarray  # bumper gap to the gap-front vehicle (np.inf if none)
    v_front_mps: np.ndarray  # its speed (np.nan if none)
    d_back_m: np.ndarray  # bumper gap to the gap-back vehicle (np.inf if none)
    v_back_mps: np.ndarray  # its speed (np.nan if none)
    a_back_mps2: np.ndarray  # acceleration of the current gap-back vehicle (np.nan if none)
    outcome: int  # marlmerge.sim OUTCOME_* code
    zone_start_m: float  # TTC and conflict metrics count from here (merge-zone start, -100 m)
    t0_s: float = 0.0  # time of sample 0 after the ego departed; sample k is at t0_s + k * dt_s
    filter_interventions: int = 0  # simulator steps whose command the safety filter overrode

    def __len__(self) -> int:
        return int(np.asarray(self.x_m).shape[0])

    @property
    def t_s(self) -> np.ndarray:
        """[T] sample times (s) after the ego departed."""
        return self.t0_s + self.dt_s * np.arange(len(self))


@dataclass(frozen=True)
class Metric:
    """One row of the metrics table."""

    name: str
    unit: str
    kind: str  # "rate" (0/1 per episode), "mean", "min" or "max" (per-episode reduction)
    doc: str
    higher_is_better: bool


METRICS: tuple[Metric, ...] = (
    Metric("success", "-", "rate", "ego passed the success line without collision", True),
    Metric("collision", "-", "rate", "ego collided", False),
    Metric("truncation", "-", "rate", "ego stalled or ran out of time", False),
    Metric("time_to_merge_s", "s", "mean", "time from departure to the merge point (x = 0)", False),
    Metric("mean_abs_accel_mps2", "m/s^2", "mean", "mean |acceleration| of the ego", False),
    Metric("max_abs_accel_mps2", "m/s^2", "max", "largest |acceleration| of the ego", False),
    Metric("max_abs_jerk_mps3", "m/s^3", "max", "largest |jerk| between simulator steps", False),
    Metric("min_ttc_front_s", "s", "min", "min time-to-collision with the gap-front vehicle", True),
    Metric("min_ttc_back_s", "s", "min", "min time-to-collision of the gap-back vehicle", True),
    Metric("time_ttc_below_s", "s", "mean", "time with min TTC below the threshold", False),
    Metric("min_gap_after_merge_m", "m", "min", "min bumper gap to the front after x = 0", True),
    Metric("min_headway_after_merge_s", "s", "min", "min time headway after x = 0", True),
    Metric("mean_speed_mps", "m/s", "mean", "mean ego speed over the episode", True),
    Metric(
        "follower_min_accel_mps2",
        "m/s^2",
        "min",
        "hardest acceleration (most negative) of the new follower after x = 0",
        True,
    ),
)
"""Every metric `episode_metrics` returns, in order. Rates are 0/1 per episode; "min"/"max" name the
per-episode reduction (across episodes they are averaged like "mean")."""

METRIC_BY_NAME: dict[str, Metric] = {m.name: m for m in METRICS}


def ttc_series(traj: EpisodeTrajectory) -> tuple[np.ndarray, np.ndarray]:
    """Time-to-collision (s) with the gap-front and of the gap-back vehicle, each [T].

    Front: d_front / (v - v_front) where the ego is faster, else inf. Back: d_back / (v_back - v)
    where the back vehicle is faster, else inf. Missing vehicles give inf; overlapping (negative)
    gaps count as 0. Every step is included (no zone mask).
    """
    v = np.asarray(traj.v_mps, dtype=np.float64)
    closing_f = v - np.asarray(traj.v_front_mps, dtype=np.float64)
    closing_b = np.asarray(traj.v_back_mps, dtype=np.float64) - v
    d_f = np.maximum(np.asarray(traj.d_front_m, dtype=np.float64), 0.0)
    d_b = np.maximum(np.asarray(traj.d_back_m, dtype=np.float64), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ttc_f = np.where(closing_f > 0.0, d_f / np.where(closing_f > 0.0, closing_f, 1.0), np.inf)
        ttc_b = np.where(closing_b > 0.0, d_b / np.where(closing_b > 0.0, closing_b, 1.0), np.inf)
    # nan speeds (no vehicle) compare False above -> inf; inf gaps stay inf
    return ttc_f, ttc_b


def _min_or(values: np.ndarray, empty: float) -> float:
    return float(np.min(values)) if values.size else empty


def episode_metrics(traj: EpisodeTrajectory, ttc_threshold_s: float = 1.5) -> dict[str, float]:
    """Every metric of `METRICS` for one episode, as floats (nan where undefined).

    Accelerations, jerk and mean speed use every sample; TTC metrics the samples with
    x >= `zone_start_m`; gap, headway and follower metrics the samples with x >= 0 (after the
    merge point). The time to merge is interpolated linearly between samples.
    """
    n = len(traj)
    dt = float(traj.dt_s)
    x = np.asarray(traj.x_m, dtype=np.float64)
    v = np.asarray(traj.v_mps, dtype=np.float64)
    a = np.asarray(traj.a_mps2, dtype=np.float64)
    t = traj.t_s
    out: dict[str, float] = {
        "success": float(traj.outcome == OUTCOME_SUCCESS),
        "collision": float(traj.outcome == OUTCOME_COLLISION),
        "truncation": float(traj.outcome == OUTCOME_TRUNCATED),
    }

    merged = np.flatnonzero(x >= 0.0)
    if merged.size == 0:
        out["time_to_merge_s"] = math.nan
    elif merged[0] == 0 or x[merged[0] - 1] >= x[merged[0]]:
        out["time_to_merge_s"] = float(t[merged[0]])
    else:
        k = merged[0]
        frac = (0.0 - x[k - 1]) / (x[k] - x[k - 1])
        out["time_to_merge_s"] = float(t[k - 1] + frac * dt)

    abs_a = np.abs(a)
    out["mean_abs_accel_mps2"] = float(np.mean(abs_a)) if n else math.nan
    out["max_abs_accel_mps2"] = float(np.max(abs_a)) if n else math.nan
    out["max_abs_jerk_mps3"] = float(np.max(np.abs(np.diff(a))) / dt) if n >= 2 else math.nan

    zone = x >= traj.zone_start_m
    ttc_f, ttc_b = ttc_series(traj)
    out["min_ttc_front_s"] = _min_or(ttc_f[zone], math.inf)
    out["min_ttc_back_s"] = _min_or(ttc_b[zone], math.inf)
    below = np.minimum(ttc_f, ttc_b) < ttc_threshold_s
    out["time_ttc_below_s"] = float(np.count_nonzero(below & zone) * dt)

    after = x >= 0.0
    if after.any():
        d_f = np.asarray(traj.d_front_m, dtype=np.float64)[after]
        v_a = v[after]
        out["min_gap_after_merge_m"] = float(np.min(d_f))
        with np.errstate(divide="ignore", invalid="ignore"):
            headway = np.where(v_a > 0.0, np.maximum(d_f, 0.0) / np.maximum(v_a, 1e-12), np.inf)
        headway = np.where((v_a <= 0.0) & (d_f <= 0.0), 0.0, headway)
        out["min_headway_after_merge_s"] = float(np.min(headway))
        a_b = np.asarray(traj.a_back_mps2, dtype=np.float64)[after]
        a_b = a_b[~np.isnan(a_b)]
        out["follower_min_accel_mps2"] = float(np.min(a_b)) if a_b.size else math.nan
    else:
        out["min_gap_after_merge_m"] = math.nan
        out["min_headway_after_merge_s"] = math.nan
        out["follower_min_accel_mps2"] = math.nan
    out["mean_speed_mps"] = float(np.mean(v)) if n else math.nan
    return {m.name: out[m.name] for m in METRICS}


def wilson_interval(successes: float, n: int, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval (low, high) of a binomial rate; (nan, nan) for n = 0."""
    if n <= 0:
        return (math.nan, math.nan)
    p = successes / n
    z2n = z * z / n
    centre = (p + 0.5 * z2n) / (1.0 + z2n)
    half = z * math.sqrt(p * (1.0 - p) / n + z2n / (4.0 * n)) / (1.0 + z2n)
    lo = 0.0 if successes <= 0 else max(0.0, centre - half)
    hi = 1.0 if successes >= n else min(1.0, centre + half)
    return (lo, hi)


def event_mask(outcome: np.ndarray, event: str) -> np.ndarray:
    """[E] the episodes whose outcome is the `event`: "collision", or "failure" (collided or
    truncated: never merged)."""
    hit = outcome == OUTCOME_COLLISION
    return hit | (outcome == OUTCOME_TRUNCATED) if event == "failure" else hit


def weighted_mean_estimate(z: np.ndarray, y: np.ndarray) -> dict[str, float | list[float]]:
    """A rate estimated as the mean of independent per-episode values z [E] (weighted events):
    the rate, its normal 95 % interval and standard error, the effective number of events of
    the weighted events y [M] ((sum y)^2 / sum y^2), the largest episode's share of the sum,
    and the Monte Carlo episodes the same interval would need, rate (1 - rate) / se^2. With no
    event the sample's variance (0) says nothing about how large the rate could be: the
    interval is [0, nan] and the standard error nan, never [0, 0]."""
    n = z.size
    rate = float(np.mean(z))
    events = bool(np.any(z > 0))
    se = float(np.std(z, ddof=1) / math.sqrt(n)) if n > 1 and events else math.nan
    if n < 2:
        ci95 = [math.nan, math.nan]
    elif not events:
        ci95 = [0.0, math.nan]
    else:
        ci95 = [max(rate - Z_95 * se, 0.0), rate + Z_95 * se]
    sum_y2 = float(np.sum(y * y))
    return {
        "rate": rate,
        "ci95": ci95,
        "se": se,
        "ess": float(np.sum(y) ** 2 / sum_y2) if sum_y2 > 0 else 0.0,
        "max_weight_share": float(np.max(z) / np.sum(z)) if np.sum(z) > 0 else math.nan,
        "mc_equivalent_episodes": rate * (1.0 - rate) / se**2 if se > 0 else math.nan,
    }


def aggregate(values: np.ndarray, kind: str) -> tuple[float, float, float]:
    """(mean, ci_low, ci_high) of one metric over episodes, a 95 % interval. `values`: [n].

    - kind "rate" (values 0/1; nan ignored): the Wilson score interval.
    - kind "mean" (also "min"/"max", per-episode reductions averaged across episodes): mean +-
      1.96 std / sqrt(n) over the finite values only: nan (undefined) **and +-inf** (e.g. a min TTC
      of an episode that never closed in) are ignored, so report the count of finite values next to
      it. With no finite value the result is (inf, inf, inf) if every non-nan value is +inf (or
      -inf for -inf), else (nan, nan, nan); with one finite value the interval is (nan, nan).
    """
    vals = np.asarray(values, dtype=np.float64).ravel()
    if kind == "rate":
        vals = vals[~np.isnan(vals)]
        if vals.size == 0:
            return (math.nan, math.nan, math.nan)
        lo, hi = wilson_interval(float(np.sum(vals)), int(vals.size))
        return (float(np.mean(vals)), lo, hi)
    if kind not in ("mean", "min", "max"):
        raise ValueError(f"unknown aggregate kind {kind!r} (known: rate, mean, min, max)")
    finite = vals[np.isfinite(vals)]
    if finite.size == 0:
        infs = vals[np.isinf(vals)]
        if infs.size and np.all(infs == infs[0]):
            return (float(infs[0]),) * 3
        return (math.nan, math.nan, math.nan)
    mean = float(np.mean(finite))
    if finite.size == 1:
        return (mean, math.nan, math.nan)
    half = Z_95 * float(np.std(finite, ddof=1)) / math.sqrt(finite.size)
    return (mean, mean - half, mean + half)


def summarize(per_episode: list[dict[str, float]]) -> dict[str, tuple[float, float, float]]:
    """`aggregate` of every metric in `METRICS` over a list of `episode_metrics` results."""
    return {
        m.name: aggregate(np.array([e[m.name] for e in per_episode], dtype=np.float64), m.kind)
        for m in METRICS
    }


class TrajectoryRecorder:
    """Collects every world's current ego episode, one sample per simulator step, from the ego
    trace of each `TrafficCore.rollout`:

        rec = TrajectoryRecorder(cfg, batch_size)
        out = core.rollout(a)
        for world, traj in rec.record(out):   # the egos that ended in this call
            ...

    A world is sampled while its ego runs, the step it ends included; a world whose ego was not
    running at the start of a call is not sampled; the next ego starts a new trajectory. Samples
    are taken after each step, so `t0_s = dt_s`.
    """

    _COLS = (TR_X, TR_V, TR_A, TR_DF, TR_VF, TR_DB, TR_VB, TR_AB)

    def __init__(self, cfg: ScenarioConfig, batch_size: int):
        self.dt_s = cfg.sim.dt_s
        self.zone_start_m = cfg.road.x_zone_start_m
        self.max_len = int(math.ceil(cfg.ego.max_episode_s / self.dt_s)) + 2
        self._buf = np.zeros((batch_size, self.max_len, len(self._COLS)))
        self._len = np.zeros(batch_size, dtype=np.int64)

    def record(self, out: Rollout) -> list[tuple[int, EpisodeTrajectory]]:
        """Append the call's samples; returns (world, trajectory) for each ego that ended in it."""
        cols = list(self._COLS)
        for b in np.flatnonzero(out.ego_steps):
            n = int(out.ego_steps[b])
            pos = int(self._len[b])
            take = min(n, self.max_len - pos)
            self._buf[b, pos : pos + take] = out.trace[b, :take][:, cols]
            self._len[b] = pos + take
        done: list[tuple[int, EpisodeTrajectory]] = []
        for b in np.flatnonzero(out.ego_outcome != OUTCOME_NONE):
            c = self._buf[b, : self._len[b]].T.copy()
            done.append(
                (
                    int(b),
                    EpisodeTrajectory(
                        dt_s=self.dt_s,
                        x_m=c[0],
                        v_mps=c[1],
                        a_mps2=c[2],
                        d_front_m=c[3],
                        v_front_mps=c[4],
                        d_back_m=c[5],
                        v_back_mps=c[6],
                        a_back_mps2=c[7],
                        outcome=int(out.ego_outcome[b]),
                        zone_start_m=self.zone_start_m,
                        t0_s=self.dt_s,
                        filter_interventions=_interventions(out, b),
                    ),
                )
            )
            self._len[b] = 0
        return done


def _interventions(out: Rollout, b: int) -> int:
    """The safety filter's overrides in world `b`'s episode that ended in `out` (0 if none)."""
    if out.filter_interventions is None:
        return 0
    return int(out.filter_interventions[b])
