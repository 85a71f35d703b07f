"""`marlmerge stress POLICY`: search the space of traffic conditions for where a policy fails.

    marlmerge stress quadq:runs/paper --out runs/stress_paper     # or gap, hold, dqn:RUN, ...

The space (`marlmerge.evaluation.space.SPACE`) is every key `[sample]` draws. The search runs on
the batched core, every world with its own condition (`TrafficCore(scenarios=...)`), and
counts a **failure** when the first ramp vehicle of a fresh road does not merge (a collision,
or a truncation: stalled or out of time):

1. **Explore**: a Latin hypercube of `points` conditions, `episodes_per_point` roads each, drawn
   uniformly from the space; their failures estimate the failure rate over the whole space.
2. **Focus**, once per region: the cross-entropy method. Each round fits a Gaussian (per
   dimension) to the elite conditions, the ones that failed most, and draws `points` new ones
   from it; conditions inside a region found before are drawn again, so every region is new.
   After `rounds` rounds, the region is the box of half-width `box` (unit-cube coordinates)
   around the elites' mean.
3. **Verify**: each region's box becomes a scenario preset (`regions/region_KK.toml`, drawing
   each road's condition inside the box) that is run on `verify_episodes` roads the search never
   saw, the failure rate given with its 95 % (Wilson) interval.

The road's geometry (ramp length, merge zone) is snapped to `road_levels` levels per key, and a
batch of worlds shares its road, so a rule (gap acceptance) plans with the road it drives on;
in a region's preset the geometry is fixed.

Outputs in `out`: `report.json` (`policy`, `episodes`, `failure_rate`, `regions`: list of
{`preset`, `failure_rate`, `ci95`, ...}, `wall_s`), `regions.md` (the regions ranked by their
verified failure rate), `regions/region_KK.toml`, and `clips/region_KK.mp4`, the first failing
road of each of the three worst regions (with the `[video]` extra).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from marlmerge.config import ScenarioConfig, load_scenario
from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.metrics import wilson_interval
from marlmerge.evaluation.registry import make_policy, parse_policy, scenario_for
from marlmerge.evaluation.rollout import rollout_first_egos
from marlmerge.evaluation.space import (
    ROAD_KEYS,
    SPACE,
    from_unit,
    latin_hypercube,
    scenario_at,
    write_preset,
)
from marlmerge.io.files import write_text
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_SUCCESS, OUTCOME_TRUNCATED

ROAD_DIMS = [i for i, d in enumerate(SPACE) if d.key in ROAD_KEYS]
VERIFY_SEED_OFFSET = 500_000_000
"""Verification roads are seeded apart from the search's (`seed * 1e9 + offset + e`)."""


@dataclass(frozen=True)
class StressSettings:
    """How hard to search. Counts, not wall time, fix the search, so a seed repeats it."""

    seed: int = 0
    points: int = 512
    """Conditions per round (exploration and each focusing round)."""
    episodes_per_point: int = 4
    """Roads per condition in a round."""
    regions: int = 8
    """Regions to focus on, one after the other."""
    rounds: int = 4
    """Cross-entropy rounds per region."""
    elite_fraction: float = 0.1
    box: float = 0.05
    """Half-width of a region's box in unit-cube coordinates (0.05: 10 % of every range)."""
    road_levels: int = 4
    verify_episodes: int = 200
    worlds: int = 512
    """Worlds stepped at once."""
    budget_s: float = 600.0
    """Wall-time cap: no new region is started past 80 % of it."""

    def __post_init__(self) -> None:
        for key in ("points", "episodes_per_point", "regions", "rounds", "road_levels", "worlds"):
            if getattr(self, key) < 1:
                raise ValueError(f"{key} must be >= 1, got {getattr(self, key)}")
        if not 0.0 < self.box <= 0.5:
            raise ValueError(f"box must be in (0, 0.5], got {self.box}")
        if not 0.0 < self.elite_fraction <= 0.5:
            raise ValueError(f"elite_fraction must be in (0, 0.5], got {self.elite_fraction}")
        if self.verify_episodes < 1:
            raise ValueError(f"verify_episodes must be >= 1, got {self.verify_episodes}")
        if not 0 < self.budget_s < math.inf:
            raise ValueError(f"budget_s must be finite and > 0, got {self.budget_s}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")


class Evaluator:
    """Runs a policy's first ramp vehicle on fresh roads, one condition per road."""

    def __init__(self, spec: str, base: ScenarioConfig, settings: StressSettings) -> None:
        self.spec = parse_policy(_as_spec(spec))
        if len(self.spec.runs) > 1:
            raise ValueError(f"policy {spec!r}: stress one run at a time ({len(self.spec.runs)})")
        self.run = self.spec.runs[0] if self.spec.runs else None
        self.base, self.settings = base, settings
        self.episodes = 0
        self._policies: dict[tuple[float, ...], tuple[ScenarioConfig, Any]] = {}

    def road(self, u: np.ndarray) -> tuple[ScenarioConfig, Any]:
        """The scenario and policy of the road at the (snapped) unit point `u`."""
        point = from_unit(u)
        key = tuple(round(point[SPACE[i].key], 9) for i in ROAD_DIMS)
        if key not in self._policies:
            keys = [SPACE[i].key for i in ROAD_DIMS]
            self._policies[key] = self.policy_on(
                self.base.replace(**{f"road.{k}": point[k] for k in keys})
            )
        return self._policies[key]

    def policy_on(self, condition: ScenarioConfig) -> tuple[ScenarioConfig, Any]:
        """The scenario the policy meets in `condition` (its ego-side settings kept) and the
        policy built for it."""
        cfg = scenario_for(self.spec, self.run, condition)
        return cfg, make_policy(self.spec, self.run, cfg)

    def outcomes(self, u: np.ndarray, seeds: np.ndarray) -> np.ndarray:
        """Outcome codes [N] of the roads seeded `seeds` [N] at the unit points `u` [N, D]."""
        u = snap_roads(u, self.settings.road_levels)
        out = np.zeros(len(u), dtype=np.int64)
        roads = {tuple(row[ROAD_DIMS]) for row in u}
        for road in sorted(roads):
            rows = np.flatnonzero((u[:, ROAD_DIMS] == road).all(axis=1))
            cfg, policy = self.road(u[rows[0]])
            points, which = np.unique(u[rows], axis=0, return_inverse=True)
            own = [scenario_at(cfg, from_unit(p)) for p in points]  # once per condition
            scenarios = [own[i] for i in which.reshape(-1)]
            rec, _ = rollout_first_egos(
                policy, cfg, len(rows), 0, self.settings.worlds,
                road_seeds=[int(s) for s in seeds[rows]], scenarios=scenarios,
            )  # fmt: skip
            out[rows] = rec["outcome"]
        self.episodes += len(u)
        return out


def _as_spec(spec: str) -> str:
    """A run folder or policy file stands for `ALGORITHM:PATH`."""
    path = Path(spec)
    if ":" not in spec and (path.suffix == ".pt" or (path / "policy.pt").exists()):
        from marlmerge.io.policy_file import read_policy

        return f"{read_policy(path, 'ego')['algorithm']}:{spec}"
    return spec


def snap_roads(u: np.ndarray, levels: int) -> np.ndarray:
    """`u` [N, D] with its road dimensions at the centre of one of `levels` levels."""
    u = np.array(u, dtype=np.float64)
    cells = np.clip(np.floor(u[:, ROAD_DIMS] * levels), 0, levels - 1)
    u[:, ROAD_DIMS] = (cells + 0.5) / levels
    return u


RELEASE = 0.3
"""The chance that the release test draws a dimension from its whole range."""


@dataclass
class Region:
    """Where a policy fails: ranges on the few dimensions that define it (the elites of the
    last focusing round are concentrated there), the whole space on the others."""

    dims: list[int]
    """The defining dimensions (indices into `SPACE`), most concentrated first."""
    lo: np.ndarray
    hi: np.ndarray
    """[D] unit-cube bounds: the box on the defining dimensions, [0, 1] elsewhere."""
    centre: np.ndarray
    """[D] the elites' mean (road dimensions snapped)."""
    search_failure_rate: float
    """Failures of the last focusing round's conditions."""
    preset: str = ""
    failure_rate: float = float("nan")
    ci95: tuple[float, float] = (float("nan"), float("nan"))
    collision_rate: float = float("nan")
    truncation_rate: float = float("nan")
    first_failure_seed: int | None = None

    def contains(self, u: np.ndarray) -> np.ndarray:
        """[N] the points [N, D] inside the region."""
        d = self.dims
        return ((u[:, d] >= self.lo[d]) & (u[:, d] <= self.hi[d])).all(axis=1)


def region_of(
    elite: np.ndarray, bounds: dict[int, tuple[float, float]], rate: float, s: StressSettings
) -> Region:
    """The region on its defining dimensions' `bounds` (unit cube; at least 2 `box` wide), the
    whole space on the others; its centre is the elites' [M, D] mean."""
    lo, hi = np.zeros(len(SPACE)), np.ones(len(SPACE))
    for d, (a, b) in bounds.items():
        mid, half = (a + b) / 2, max((b - a) / 2, s.box)
        lo[d], hi[d] = max(mid - half, 0.0), min(mid + half, 1.0)
    centre = snap_roads(elite.mean(axis=0)[None], s.road_levels)[0]
    return Region(list(bounds), lo, hi, centre, rate)


def failing_interval(x: np.ndarray, fail: np.ndarray, bins: int = 10) -> tuple[float, float]:
    """Where along one dimension conditions fail: the run of bins around the worst one whose
    failure rate is at least half of its (x [N] in [0, 1], fail [N] failure fractions)."""
    if x.size == 0:
        return 0.0, 1.0
    idx = np.minimum((x * bins).astype(int), bins - 1)
    rate = np.array([fail[idx == i].mean() if (idx == i).any() else 0.0 for i in range(bins)])
    peak = int(np.argmax(rate))
    lo = hi = peak
    while lo > 0 and rate[lo - 1] >= 0.5 * rate[peak]:
        lo -= 1
    while hi < bins - 1 and rate[hi + 1] >= 0.5 * rate[peak]:
        hi += 1
    return lo / bins, (hi + 1) / bins


class Search:
    """The exploration, the focusing rounds and the regions they find."""

    def __init__(self, evaluator: Any, settings: StressSettings) -> None:
        self.ev, self.s = evaluator, settings
        self.rng = np.random.default_rng(settings.seed)
        self.next_seed = settings.seed * 1_000_000_000
        self.regions: list[Region] = []

    def evaluate(self, u: np.ndarray) -> np.ndarray:
        """Failure fraction [N] of each condition over `episodes_per_point` roads."""
        m = self.s.episodes_per_point
        rep = np.repeat(u, m, axis=0)  # the evaluator snaps the roads
        seeds = self.next_seed + np.arange(len(rep))
        self.next_seed += len(rep)
        failed = self.ev.outcomes(rep, seeds) != OUTCOME_SUCCESS
        return failed.reshape(len(u), m).mean(axis=1)

    def explore(self) -> tuple[np.ndarray, np.ndarray]:
        """`points` conditions of a Latin hypercube over the whole space, and their failures."""
        u = latin_hypercube(self.s.points, len(SPACE), self.rng)
        return u, self.evaluate(u)

    def explore_outside(self) -> tuple[np.ndarray, np.ndarray]:
        """`points` conditions drawn uniformly outside the regions found, and their failures."""
        u = self.outside(lambda n: self.rng.uniform(size=(n, len(SPACE))))
        return u, self.evaluate(u)

    def outside_regions(self, u: np.ndarray) -> np.ndarray:
        """[N] the points that lie in no region found so far (road dimensions snapped)."""
        snapped = snap_roads(u, self.s.road_levels)
        keep = np.ones(len(u), dtype=bool)
        for r in self.regions:
            keep &= ~r.contains(snapped)
        return keep

    def draw(self, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
        """`points` draws of N(mean, std) in the cube, outside the regions found."""
        d = len(SPACE)
        return self.outside(lambda n: np.clip(mean + std * self.rng.standard_normal((n, d)), 0, 1))

    def outside(self, fresh: Callable[[int], np.ndarray]) -> np.ndarray:
        """`points` draws of `fresh(n)` [n, D], those inside a region found drawn again (a few
        tries)."""
        u = fresh(self.s.points)
        for _ in range(20):
            bad = ~self.outside_regions(u)
            if not bad.any():
                break
            u[bad] = fresh(int(bad.sum()))
        return u

    def elite(self, u: np.ndarray, fail: np.ndarray) -> np.ndarray | None:
        """The conditions that failed most (failed at least once), outside the regions found;
        the most failing first (ties at random)."""
        ok = self.outside_regions(u) & (fail > 0)
        if ok.sum() < 2:
            return None
        n = max(2, int(np.ceil(self.s.elite_fraction * len(u))))
        idx = np.flatnonzero(ok)
        order = np.lexsort((self.rng.uniform(size=idx.size), -fail[idx]))
        return u[idx[order[:n]]]

    def focus(self, u: np.ndarray, fail: np.ndarray) -> Region | None:
        """Cross-entropy rounds from the condition that failed most (a broad Gaussian around
        it, so one failure mode is followed); None where nothing outside the regions fails."""
        elite = self.elite(u, fail)
        if elite is None:
            return None
        mean, std = elite[0], np.full(len(SPACE), 0.25)
        for _ in range(self.s.rounds):
            u = self.draw(mean, std)
            fail = self.evaluate(u)
            nxt = self.elite(u, fail)
            if nxt is None:
                return None
            elite = nxt
            mean, std = elite.mean(axis=0), np.maximum(elite.std(axis=0), self.s.box)
        return region_of(elite, self.defining(mean, std), float(fail.mean()), self.s)

    def defining(self, mean: np.ndarray, std: np.ndarray) -> dict[int, tuple[float, float]]:
        """The dimensions the failure depends on, and where along each it fails. Conditions
        are drawn from the focused Gaussian, each dimension released to its whole range with
        probability `RELEASE`; a dimension defines the region if releasing it cuts the failure
        rate to under 75 % (two-proportion z > 2), and where the conditions released along it
        still fail bounds it (`failing_interval`). At most 4, the strongest first."""
        u = self.draw(mean, std)
        released = self.rng.uniform(size=u.shape) < RELEASE
        u[released] = self.rng.uniform(size=int(released.sum()))
        fail = self.evaluate(u)
        effect, z = np.zeros(len(SPACE)), np.zeros(len(SPACE))
        for d in range(len(SPACE)):
            a, b = fail[released[:, d]], fail[~released[:, d]]
            if len(a) and len(b) and b.mean() > 0:
                pooled = np.sqrt(fail.mean() * (1 - fail.mean()) * (1 / len(a) + 1 / len(b)))
                effect[d] = 1 - a.mean() / b.mean()
                z[d] = (b.mean() - a.mean()) / max(pooled, 1e-12)
        order = np.argsort(-effect, kind="stable")
        dims = [int(d) for d in order if effect[d] > 0.25 and z[d] > 2][:4] or [int(order[0])]
        bounds = {}
        for d in dims:  # released along d, the other defining dimensions kept focused
            rows = released[:, d] & ~released[:, [o for o in dims if o != d]].any(axis=1)
            bounds[d] = failing_interval(u[rows, d], fail[rows])
        return bounds


def stress(
    policy: str,
    out: Path,
    scenario: str | Path | ScenarioConfig = "default",
    settings: StressSettings | None = None,
    clip: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Search, verify and report the regions where `policy` fails (see the module docstring)."""
    s = settings or StressSettings()
    base = resolve_config(scenario)
    if base.sample.active:
        raise ValueError(
            "stress: the scenario must not draw its traffic ([sample]); the space does"
        )
    t0 = time.perf_counter()
    ev = Evaluator(policy, base, s)
    search = Search(ev, s)
    u0, fail0 = search.explore()
    n0 = len(u0) * s.episodes_per_point
    space_rate = float(fail0.mean())
    log(f"explore: {n0} roads, failure rate over the space {space_rate:.2%}")
    for k in range(s.regions):
        if time.perf_counter() - t0 > 0.8 * s.budget_s:
            log(f"budget: stopped after {k} regions")
            break
        region = search.focus(u0, fail0)
        if region is None:  # the exploration's failures all lie in the regions: explore anew
            u0, fail0 = search.explore_outside()
            region = search.focus(u0, fail0)
        if region is None:
            log(f"region {k + 1}: nothing more fails outside the regions found")
            break
        search.regions.append(region)
        keys = ", ".join(SPACE[i].key for i in region.dims)
        log(f"region {k + 1}: {keys}; search failure rate {region.search_failure_rate:.1%}")
    out.mkdir(parents=True, exist_ok=True)
    regions = [verify(ev, r, k, s, out) for k, r in enumerate(search.regions, start=1)]
    regions.sort(key=lambda r: -r.failure_rate)
    lo, hi = wilson_interval(space_rate * n0, n0)
    report = {
        "policy": policy,
        "scenario": base.name,
        "episodes": ev.episodes,
        "failure_rate": space_rate,
        "failure_rate_ci95": [lo, hi],
        "regions": [_region_row(r) for r in regions],
        "wall_s": time.perf_counter() - t0,
        "settings": asdict(s),
    }
    write_text(out / "report.json", json.dumps(report, indent=1) + "\n")
    write_text(out / "regions.md", regions_markdown(report, regions))
    if clip:
        report["clips"] = _clips(ev, regions, out, log)
        write_text(out / "report.json", json.dumps(report, indent=1) + "\n")
    return report


def region_preset(region: Region, name: str, note: str) -> dict[str, Any]:
    """The region as a scenario preset: `[sample]` ranges (the region's box on its defining
    dimensions, the whole space on the others) on a fixed road (the region's road level where
    the road defines it, else the scenario's)."""
    lo, hi, centre = from_unit(region.lo), from_unit(region.hi), from_unit(region.centre)
    sample = {d.key: [round(lo[d.key], 4), round(hi[d.key], 4)] for d in SPACE}
    data: dict[str, Any] = {"name": name}
    road = {SPACE[i].key: centre[SPACE[i].key] for i in ROAD_DIMS if i in region.dims}
    if road:
        data["road"] = road
    data["sample"] = {k: v for k, v in sample.items() if k not in ROAD_KEYS}
    return data


def verify(ev: Evaluator, region: Region, k: int, s: StressSettings, out: Path) -> Region:
    """Write the region's preset and run it on `verify_episodes` fresh roads."""
    name = f"region_{k:02d}"
    note = (
        f"A failure region of {ev.spec.name} found by `marlmerge stress` (seed {s.seed}): each\n"
        "road draws its condition from these ranges ([sample]); the ranges that define the\n"
        f"region: {', '.join(SPACE[i].key for i in region.dims)}; the others span the space."
    )
    path = write_preset(out / "regions" / f"{name}.toml", region_preset(region, name, note), note)
    region.preset = str(path)
    cfg, policy = ev.policy_on(load_scenario(path))
    first = s.seed * 1_000_000_000 + VERIFY_SEED_OFFSET + k * s.verify_episodes
    rec, _ = rollout_first_egos(policy, cfg, s.verify_episodes, first, s.worlds)
    ev.episodes += s.verify_episodes
    o = rec["outcome"]
    failed = o != OUTCOME_SUCCESS
    region.failure_rate = float(failed.mean())
    region.ci95 = wilson_interval(float(failed.sum()), s.verify_episodes)
    region.collision_rate = float(np.mean(o == OUTCOME_COLLISION))
    region.truncation_rate = float(np.mean(o == OUTCOME_TRUNCATED))
    region.first_failure_seed = first + int(np.argmax(failed)) if failed.any() else None
    return region


def _region_row(r: Region) -> dict[str, Any]:
    return {
        "preset": r.preset,
        "failure_rate": r.failure_rate,
        "ci95": list(r.ci95),
        "collision_rate": r.collision_rate,
        "truncation_rate": r.truncation_rate,
        "search_failure_rate": r.search_failure_rate,
        "defined_by": {
            SPACE[i].key: [from_unit(r.lo)[SPACE[i].key], from_unit(r.hi)[SPACE[i].key]]
            for i in r.dims
        },
        "first_failure_seed": r.first_failure_seed,
    }


def regions_markdown(report: dict[str, Any], regions: list[Region]) -> str:
    """The ranked regions, each with the conditions that set it apart (farthest from the
    space's middle first)."""
    rate_lo, rate_hi = report["failure_rate_ci95"]
    lines = [
        f"# Failure regions of `{report['policy']}`",
        "",
        f"{report['episodes']:,} episodes in {report['wall_s']:.0f} s. Failure rate over the "
        f"whole space: {report['failure_rate']:.2%} [{rate_lo:.2%}, {rate_hi:.2%}]. A failure: "
        "the ramp vehicle does not merge (collision or truncation). A region is defined by "
        "ranges on a few keys, every other key spanning the whole space; each is verified on "
        "fresh roads "
        "with its preset (`marlmerge evaluate POLICY --scenario PRESET`).",
        "",
        "| rank | preset | failure rate [95 % CI] | collisions | truncations | defined by |",
        "|---|---|---|---|---|---|",
    ]
    for rank, r in enumerate(regions, start=1):
        lo, hi = from_unit(r.lo), from_unit(r.hi)
        apart = ", ".join(
            f"{d.key} {lo[d.key]:.3g}-{hi[d.key]:.3g} {d.unit}".strip()
            for d in (SPACE[i] for i in r.dims)
        )
        lines.append(
            f"| {rank} | `{Path(r.preset).name}` | {r.failure_rate:.1%} "
            f"[{r.ci95[0]:.1%}, {r.ci95[1]:.1%}] | {r.collision_rate:.1%} | "
            f"{r.truncation_rate:.1%} | {apart} |"
        )
    return "\n".join(lines) + "\n"


def _clips(
    ev: Evaluator, regions: list[Region], out: Path, log: Callable[[str], None]
) -> list[str]:
    """A video of the first failing road of each of the (up to) three worst regions."""
    from marlmerge.evaluation.video import record_episodes
    from marlmerge.views.render import write_video

    paths = []
    for r in [r for r in regions if r.first_failure_seed is not None][:3]:
        cfg, policy = ev.policy_on(load_scenario(r.preset))
        frames, _ = record_episodes(policy, cfg, 1, r.first_failure_seed)
        try:
            path = write_video(
                out / "clips" / f"{Path(r.preset).stem}.mp4", frames, 1 / cfg.sim.dt_s
            )
        except (ImportError, RuntimeError, OSError) as err:  # the [video] extra is missing
            log(f"no clip: {err}")
            break
        paths.append(str(path))
    return paths
