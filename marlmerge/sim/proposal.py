"""Importance sampling of the traffic a ramp vehicle meets: proposal draws and their exact weights.

With a `Proposal`, the core draws some of its random variables from a tilted distribution in
place of the scenario's own, and keeps, per world, the exact log-likelihood ratio
log p(draws) / q(draws) of everything it drew since its last reset. An estimate that weighs each
episode's outcome by exp(log ratio) is then unbiased for the natural rate (Owen 2013, ch. 9),
whatever the proposal, as long as it can draw everything the scenario can.

What is tilted (everything else is drawn as without a proposal):

- mainline **arrivals** whose entrance time falls in `window_s` (seconds after the reset; by default
  the vehicles that reach the merge area while the first ramp vehicle merges): the gap to the next
  arrival (exponential, its mean scaled by `gap_scale[lane]`), the driver profile (categorical,
  `profile_p[lane]`) and the driver's desired-speed factor, time headway and politeness (each a
  Beta(a, b) over the scenario's band in place of the uniform);
- the **start speed of the first `TILTED_DEPARTURES` ramp vehicles** after a reset: Beta(a, b)
  over `ego.start_speed_mps` (two, because an env's reset ends the ego the core's reset sent
  and sends the next one: the first ego an evaluation runs is the second departure);
- with attention lapses (`driver.lapse_rate_per_h`), the **lapses of the driver behind the
  ego's gap** while the ego runs in the merge zone: each step it begins one with probability
  `lapse_p[c]` instead of the natural p, by how soon a lapse could close its gap to the ego
  (`marlmerge.sim.lapses.lapse_class`), until the first such lapse; drawn and weighed in the
  kernel;
- or, in place of that tilt, **splitting** of the same lapses (`lapse_split`): the trunk runs
  without them and a branch replays the world with one of them begun (`marlmerge.sim.lapses`,
  `marlmerge.evaluation.splitting`).

The road filled at a reset and everything after the window are drawn naturally. The weights are
exact for each draw (closed forms below); `stats` keeps the sufficient statistics of the tilted
draws, which the cross-entropy method fits the next proposal from
(`marlmerge.evaluation.estimate`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.sim.layout import N_LAPSE_CLASSES

N_PROFILES = 3
TILTED_DEPARTURES = 2
BETA_KEYS = ("desired_speed_factor", "time_headway_s", "politeness", "start_speed")
"""The Beta-tilted draws, in the order of `Proposal.beta`."""
ST_PROFILE = 0
"""stats columns [ST_PROFILE + 3 * lane + k]: tilted arrivals of `lane` with profile k."""
ST_GAP_SUM = 6
"""stats [ST_GAP_SUM + lane]: sum of the tilted gaps of `lane`, in natural mean gaps."""
ST_GAP_N = 8
"""stats [ST_GAP_N + lane]: number of tilted gaps of `lane`."""
ST_BETA = 10
"""stats [ST_BETA + 3 * j + (0, 1, 2)]: n, sum y, sum y^2 of Beta draw j (`BETA_KEYS`) on [0, 1]."""
ST_LAPSE_STEPS = ST_BETA + 3 * len(BETA_KEYS)
"""stats [ST_LAPSE_STEPS + c]: steps of class c in which the tilted driver could begin a lapse;
[ST_LAPSE_N + c]: lapses it began in them (the kernel's `WF_LAPSE_STEPS` / `WF_LAPSE_N` rows)."""
ST_LAPSE_N = ST_LAPSE_STEPS + N_LAPSE_CLASSES
N_STATS = ST_LAPSE_N + N_LAPSE_CLASSES
BETA_RANGE = (0.5, 50.0)
"""Beta parameters allowed (>= 0.5 keeps every density finite inside the band)."""
GAP_SCALE_RANGE = (0.1, 10.0)
LAPSE_P_MAX = 0.2
"""A tilted per-step lapse probability is in (0, LAPSE_P_MAX]."""
Y_EPS = 1e-12


@dataclass(frozen=True)
class Proposal:
    """A proposal distribution for the traffic a ramp vehicle meets (see the module docstring)."""

    window_s: tuple[float, float]
    """Arrivals entering in [start, end) s after the reset are tilted."""
    profile_p: tuple[tuple[float, float, float], tuple[float, float, float]]
    """Per lane (right, left): probabilities of the neutral, cooperative, adversarial profiles."""
    gap_scale: tuple[float, float] = (1.0, 1.0)
    """Per lane: the tilted arrival gaps' mean, as a multiple of the natural mean."""
    beta: tuple[tuple[float, float], ...] = ((1.0, 1.0),) * len(BETA_KEYS)
    """(a, b) of each Beta draw in `BETA_KEYS` order; (1, 1) is the natural uniform."""
    lapse_p: tuple[float, ...] | None = None
    """Per-step probabilities that the driver behind the ego's gap begins an attention lapse
    while the ego runs in the merge zone, one per `lapse_class` (by how soon a lapse could
    close its gap to the ego); None: the scenario's own."""
    lapse_split: tuple[float, ...] | None = None
    """Per `lapse_class`: the probability that a critical step of that class is a branch
    point, where a branch replays the world with the lapse begun (`marlmerge.sim.lapses`);
    None: no splitting. Not with `lapse_p`."""

    def __post_init__(self) -> None:
        t0, t1 = self.window_s
        if not (math.isfinite(t0) and math.isfinite(t1) and 0.0 <= t0 < t1):
            raise ValueError(f"proposal window_s must be 0 <= start < end, got {self.window_s}")
        for lane, probs in enumerate(self.profile_p):
            if len(probs) != N_PROFILES or min(probs) < 0 or abs(sum(probs) - 1.0) > 1e-9:
                raise ValueError(
                    f"proposal profile_p[{lane}] must be 3 probabilities summing to 1, got {probs}"
                )
        for lane, s in enumerate(self.gap_scale):
            if not GAP_SCALE_RANGE[0] <= s <= GAP_SCALE_RANGE[1]:
                raise ValueError(
                    f"proposal gap_scale[{lane}] must be in {GAP_SCALE_RANGE}, got {s}"
                )
        if len(self.beta) != len(BETA_KEYS):
            raise ValueError(f"proposal beta: one (a, b) per {BETA_KEYS}, got {len(self.beta)}")
        for key, (a, b) in zip(BETA_KEYS, self.beta, strict=True):
            if not (BETA_RANGE[0] <= a <= BETA_RANGE[1] and BETA_RANGE[0] <= b <= BETA_RANGE[1]):
                raise ValueError(f"proposal beta[{key}] = ({a}, {b}): each must be in {BETA_RANGE}")
        if self.lapse_p is not None and (
            len(self.lapse_p) != N_LAPSE_CLASSES
            or not all(0.0 < q <= LAPSE_P_MAX for q in self.lapse_p)
        ):
            raise ValueError(
                f"proposal lapse_p must be {N_LAPSE_CLASSES} probabilities in (0, {LAPSE_P_MAX}], "
                f"got {self.lapse_p}"
            )

        if self.lapse_split is not None:
            if self.lapse_p is not None:
                raise ValueError(
                    "proposal: lapse_p tilts the lapses that lapse_split splits; not both"
                )
            if len(self.lapse_split) != N_LAPSE_CLASSES or not all(
                0.0 < r <= 1.0 for r in self.lapse_split
            ):
                raise ValueError(
                    f"proposal lapse_split must be {N_LAPSE_CLASSES} probabilities in (0, 1], "
                    f"got {self.lapse_split}"
                )

    @classmethod
    def natural(cls, cfg: ScenarioConfig, window_s: tuple[float, float] | None = None) -> Proposal:
        """The scenario's own distribution written as a proposal (every weight is 1)."""
        p = natural_profiles(cfg)
        return cls(window_s or default_window_s(cfg), (p, p))

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        for key in ("lapse_p", "lapse_split"):  # as written before these existed (batch names)
            if data[key] is None:
                del data[key]
        return data

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Proposal:
        return cls(
            window_s=tuple(data["window_s"]),  # type: ignore[arg-type]
            profile_p=tuple(tuple(p) for p in data["profile_p"]),  # type: ignore[arg-type]
            gap_scale=tuple(data["gap_scale"]),  # type: ignore[arg-type]
            beta=tuple(tuple(ab) for ab in data["beta"]),  # type: ignore[arg-type]
            lapse_p=None if data.get("lapse_p") is None else tuple(data["lapse_p"]),
            lapse_split=None if data.get("lapse_split") is None else tuple(data["lapse_split"]),
        )

    def check(self, cfg: ScenarioConfig) -> None:
        """The proposal draws every profile the scenario can (else the estimate is biased); with
        `[sample]` (each world its own mix) every profile."""
        for key in ("lapse_p", "lapse_split"):
            if getattr(self, key) is not None and cfg.driver.lapse_rate_per_h <= 0.0:
                raise ValueError(
                    f"proposal {key} = {getattr(self, key)}: the scenario's drivers never lapse "
                    "(driver.lapse_rate_per_h = 0)"
                )
        p = natural_profiles(cfg)
        for lane, probs in enumerate(self.profile_p):
            for k, (nat, q) in enumerate(zip(p, probs, strict=True)):
                if q <= 0.0 and (nat > 0.0 or cfg.sample.active):
                    raise ValueError(
                        f"proposal profile_p[{lane}][{k}] = {q}: the scenario draws that profile, "
                        "so the proposal must too (> 0)"
                    )


def natural_profiles(cfg: ScenarioConfig) -> tuple[float, float, float]:
    mix = np.asarray(cfg.driver.mix, dtype=np.float64)
    return tuple(float(x) for x in mix / mix.sum())  # type: ignore[return-value]


def default_window_s(cfg: ScenarioConfig) -> tuple[float, float]:
    """Entrance times of the vehicles near the merge area while the first ramp vehicle drives
    its ramp and merge zone: from 15 s before its departure (the end of the warm-up) to 10 s
    after, clipped at the reset."""
    t_dep = cfg.traffic.warmup_s
    return (max(t_dep - 15.0, 0.0), t_dep + 10.0)


def beta_log_pdf(y: np.ndarray, a: float, b: float) -> np.ndarray:
    """log density of Beta(a, b) at y in (0, 1)."""
    log_norm = math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)
    return (a - 1.0) * np.log(y) + (b - 1.0) * np.log1p(-y) - log_norm


class TiltedDraws:
    """The draws of B worlds under one proposal, with each world's log-likelihood ratio and
    sufficient statistics since its last `restart`."""

    def __init__(self, proposal: Proposal, batch_size: int):
        self.proposal = proposal
        self.log_w = np.zeros(batch_size)
        """[B] log p / q of every draw since the world's reset."""
        self.stats = np.zeros((batch_size, N_STATS))
        """[B, N_STATS] sufficient statistics of the tilted draws (`ST_*` columns)."""
        self.first_ego = np.ones(batch_size, dtype=bool)
        """[B] the world's next chunk of departures is its first since the reset (its first
        `TILTED_DEPARTURES` are tilted)."""

    def restart(self, rows: np.ndarray) -> None:
        self.log_w[rows] = 0.0
        self.stats[rows] = 0.0
        self.first_ego[rows] = True

    def gaps(
        self, b: int, lane: int, g: np.random.Generator, mean_s: float, t_last: float, n: int
    ) -> np.ndarray:
        """`n` arrival times after `t_last`: each gap that starts inside the window is drawn
        with its mean scaled; log p/q = log s - u/m + u/(m s) for a gap u of natural mean m."""
        q = self.proposal
        s = q.gap_scale[lane]
        times = np.empty(n)
        t = t_last
        for i in range(n):
            tilt = q.window_s[0] <= t < q.window_s[1]
            u = float(g.exponential(mean_s * s if tilt else mean_s))
            if tilt:
                self.log_w[b] += math.log(s) - u / mean_s + u / (mean_s * s)
                self.stats[b, ST_GAP_SUM + lane] += u / mean_s
                self.stats[b, ST_GAP_N + lane] += 1.0
            t += u
            times[i] = t
        return times

    def in_window(self, times: np.ndarray) -> np.ndarray:
        t0, t1 = self.proposal.window_s
        return (times >= t0) & (times < t1)

    def profiles(
        self, b: int, lane: int, g: np.random.Generator, natural: np.ndarray, tilt: np.ndarray
    ) -> np.ndarray:
        """Profiles by inverse CDF: natural probabilities outside the window, the proposal's
        inside; log p/q = log p_k - log q_k per tilted vehicle."""
        q = np.asarray(self.proposal.profile_p[lane])
        u = g.uniform(size=tilt.size)
        nat = np.minimum(np.searchsorted(np.cumsum(natural), u, side="right"), N_PROFILES - 1)
        prop = np.minimum(np.searchsorted(np.cumsum(q), u, side="right"), N_PROFILES - 1)
        k = np.where(tilt, prop, nat)
        kt = k[tilt]
        with np.errstate(divide="ignore"):
            self.log_w[b] += float(np.sum(np.log(natural[kt]) - np.log(q[kt])))
        np.add.at(self.stats[b], ST_PROFILE + N_PROFILES * lane + kt, 1.0)
        return k.astype(np.float64)

    def band(
        self,
        b: int,
        j: int,
        g: np.random.Generator,
        band: tuple[float, float],
        tilt: np.ndarray,
    ) -> np.ndarray:
        """Values in `band` (uniform outside the window, Beta(a, b) of `BETA_KEYS[j]` inside);
        log p/q = -log Beta_pdf(y) per tilted draw, y the position in the band. A band of zero
        width is a fixed value: nothing to tilt."""
        lo, hi = band
        n = tilt.size
        uni = g.uniform(size=n)
        a, bb = self.proposal.beta[j]
        y = np.clip(g.beta(a, bb, size=n), Y_EPS, 1.0 - Y_EPS)
        if hi <= lo:
            return lo + (hi - lo) * uni
        yt = y[tilt]
        self.log_w[b] -= float(np.sum(beta_log_pdf(yt, a, bb)))
        col = ST_BETA + 3 * j
        self.stats[b, col] += yt.size
        self.stats[b, col + 1] += float(np.sum(yt))
        self.stats[b, col + 2] += float(np.sum(yt * yt))
        return lo + (hi - lo) * np.where(tilt, y, uni)
