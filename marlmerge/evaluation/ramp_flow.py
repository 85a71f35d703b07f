"""The merge as a whole: ramp flow (`ramp.flow_vph > 0`) measured as traffic engineers do.

Ramp vehicles arrive as their own Poisson stream, queue at the ramp's entrance if the ramp is
full, follow each other on the ramp and merge, each an agent driven by one shared policy (a rule
or a learned ego policy, seeing its own observation layout: `marlmerge.evaluation.registry`)
while it is on the ramp; once it has joined the right lane it follows by IDM every simulator
step, as a mainline driver (the views and training keep it an agent until its merge ends, as the
ego: `docs/ramp-flow.md` says why they differ).

    result = run_ramp_flow(cfg, "gap", hours=1.0, worlds=4, seed=0)
    result.merged_vph, result.ramp_delay_s, result.mainline_speed_drop_mps

What is measured (`RampFlowResult`), in a window that starts `skip_s` after the warm-up:

- merged flow: ramp vehicles that pass the merge point x = 0, per hour (per world, then the
  mean over worlds with a 95 % interval);
- ramp travel time: from a vehicle's drawn arrival at the ramp start to x = 0, the entrance
  wait included; ramp delay: that minus the time to drive the same distance at the speed limit,
  so that both simulators of `marlmerge.validation.merge` are judged by the same yardstick;
- the ramp's entrance queue (longest) and its mean entrance wait;
- collisions of ramp vehicles before the merge point, per 1,000 merged vehicles;
- the mainline's mean speed in the merge zone and upstream of the ramp start (the drop is the
  merge's cost to the mainline), and the road's throughput at its downstream end;
- the mainline's lane changes per hour and where they happen, and how hard it brakes around the
  merge (`marlmerge.evaluation.merge_metrics`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
import torch

from marlmerge.config import ScenarioConfig, check_count
from marlmerge.evaluation.merge_metrics import MergeTally
from marlmerge.evaluation.metrics import wilson_interval
from marlmerge.evaluation.registry import ShieldedPolicy, policy_for_evaluation
from marlmerge.policies.gap_acceptance import ShieldTally
from marlmerge.sim import layout as L
from marlmerge.sim.core import TrafficCore
from marlmerge.sim.state import Roster

MAX_RAMP_AGENTS = 16
"""Ramp vehicles per world that act each step (downstream first); the ramp rarely holds more (the
entrance keeps a queue off it), and any beyond drive by IDM behind their ramp leader, counted in
`RampFlowResult.ramp_steps_by_idm_share`."""
UPSTREAM_WINDOW_M = 100.0
"""The mainline's upstream speed is measured over this length, ending at the ramp start."""


@dataclass(frozen=True)
class RampFlowResult:
    """What a ramp-flow run measured (means over worlds; `*_ci95`: 95 % intervals over worlds)."""

    driver: str
    ramp_demand_vph: float
    mainline_demand_vph_per_lane: float
    worlds: int
    measured_s: float
    """Simulated time per world in the measurement window."""
    merged_vph: float
    merged_vph_ci95: tuple[float, float]
    ramp_entered_vph: float
    ramp_travel_s: float
    ramp_delay_s: float
    ramp_delay_s_ci95: tuple[float, float]
    ramp_wait_s: float
    ramp_max_queue: int
    ramp_collisions: int
    ramp_collisions_per_1000: float
    ramp_collisions_per_1000_ci95: tuple[float, float]
    """95 % Wilson interval of the collisions per 1,000 merged, each merged vehicle a trial
    (`per_1000_interval`)."""
    background_collisions: int
    mainline_speed_merge_mps: float
    mainline_speed_upstream_mps: float
    mainline_speed_drop_mps: float
    throughput_vph: float
    """Vehicles leaving by the downstream end per hour, merged ramp vehicles included."""
    lane_changes_per_hour: float
    """Mainline lane changes per hour and world."""
    lane_change_shares: dict[str, float | None]
    """Share of the lane changes in each road section (`merge_metrics.SECTIONS`)."""
    lane_change_shares_ci95: dict[str, tuple[float, float]]
    """... their 95 % intervals over worlds (`merge_metrics.ratio_interval`)."""
    braking_over_b_share: float
    """Share of the mainline's braking samples around the merge harder than b."""
    braking_over_b_share_ci95: tuple[float, float]
    braking_over_4_share: float
    """... harder than 4 m/s^2."""
    braking_over_4_share_ci95: tuple[float, float]
    hardest_braking_mps2: float
    cut_ins: int
    """Mainline vehicles a lane changer moved in ahead of, around the merge."""
    cut_ins_braking_over_b: int
    """... of which braked harder than b within `merge_metrics.CUT_IN_WINDOW_S`."""
    hardest_braking_after_cut_in_mps2: float
    joins: int
    """Mainline vehicles a ramp vehicle joined ahead of."""
    joins_braking_over_b: int
    hardest_braking_after_join_mps2: float
    ramp_steps_by_idm_share: float = 0.0
    """Share of the ramp vehicles' control steps on the ramp in which a vehicle was behind the
    first `MAX_RAMP_AGENTS` of its world's ramp and drove by IDM, not by the policy (0: the
    policy drove every ramp vehicle; only a jammed ramp holds more)."""
    shield_judged: int | None = None
    """Behind `@shield` / `@shield-left`: the ramp vehicles' commands the shield judged (on the
    ramp, in the measurement window; `GapShield.tally`); None without a shield."""
    shield_changed_share: float | None = None
    """... the share of them it changed (None without a shield or with none judged)."""
    wall_s: float = 0.0

    def to_dict(self) -> dict[str, object]:
        """The fields, with a value undefined in this run (NaN: no ramp vehicle merged) as None,
        so the dict is strict JSON."""
        return {k: _defined(v) for k, v in asdict(self).items()}


def bounds_text(bounds: Any, digits: int) -> str:
    """` [low, high]` of a `*_ci95` of `RampFlowResult.to_dict()`, or "" where there is none:
    one world has no interval over worlds, nothing merged has none, and a result written before
    the collisions' interval was reported has none of those (as `merge_line` and the grid's
    ramp-flow table print them)."""
    if bounds is None or bounds[0] is None:
        return ""
    return f" [{bounds[0]:.{digits}f}, {bounds[1]:.{digits}f}]"


def merge_line(row: dict[str, Any]) -> str:
    """One line of what a ramp-flow run measured, from its `RampFlowResult.to_dict()` (as
    `rampflow` and `evaluate` print it)."""
    if row["ramp_delay_s"] is None:  # nothing merged: delay and rates undefined
        return f"no ramp vehicle merged, {row['ramp_collisions']} collisions"
    share = entrance_share_text(row, " %")
    return (
        f"merged {row['merged_vph']:.0f}{bounds_text(row['merged_vph_ci95'], 0)} veh/h, ramp delay "
        f"{row['ramp_delay_s']:.1f}{bounds_text(row['ramp_delay_s_ci95'], 1)} s, longest queue "
        f"{row['ramp_max_queue']}, {row['ramp_collisions']} collisions "
        f"({row['ramp_collisions_per_1000']:.2f}"
        f"{bounds_text(row.get('ramp_collisions_per_1000_ci95'), 2)} per 1,000 merged); mainline "
        f"{row['mainline_speed_upstream_mps']:.1f} -> "
        f"{row['mainline_speed_merge_mps']:.1f} m/s through the merge zone, "
        f"{row['lane_changes_per_hour']:.0f} lane changes/h ({share} at the entrance), braking "
        f"> b in {braking_share_text(row)} % of samples (hardest "
        f"{row['hardest_braking_mps2']:.1f} m/s^2); after {row['cut_ins']} cut-ins "
        f"{row['cut_ins_braking_over_b']} braked > b (hardest "
        f"{row['hardest_braking_after_cut_in_mps2']:.1f}), after {row['joins']} joins "
        f"{row['joins_braking_over_b']} (hardest {row['hardest_braking_after_join_mps2']:.1f})"
        + _shield_part(row)
        + _idm_part(row)
    )


def _idm_part(row: dict[str, Any]) -> str:
    share = row.get("ramp_steps_by_idm_share") or 0.0
    if share <= 0.0:
        return ""
    return (
        f"; {100 * share:.2f} % of the ramp vehicles' steps drove by IDM (more than "
        f"{MAX_RAMP_AGENTS} on the ramp)"
    )


def _shield_part(row: dict[str, Any]) -> str:
    share = row.get("shield_changed_share")
    if share is None:
        return ""
    return f"; the shield changed {100 * share:.1f} % of {row['shield_judged']:,} ramp commands"


def percent_bounds_text(bounds: Any, digits: int) -> str:
    """`bounds_text` of the interval of a share, in %."""
    if bounds is None or bounds[0] is None:
        return ""
    return bounds_text((100 * bounds[0], 100 * bounds[1]), digits)


def entrance_share_text(row: dict[str, Any], unit: str = "") -> str:
    """The share of the lane changes made in the first metres after the entrance, in %, with
    its interval (`RampFlowResult.to_dict()` row; "-" where there were none)."""
    entrance = row["lane_change_shares"]["entrance"]
    if entrance is None:
        return "-"
    bounds = (row.get("lane_change_shares_ci95") or {}).get("entrance")
    return f"{100 * entrance:.0f}{percent_bounds_text(bounds, 0)}{unit}"


def braking_share_text(row: dict[str, Any]) -> str:
    """The share of the braking samples harder than b, in %, with its interval."""
    bounds = row.get("braking_over_b_share_ci95")
    return f"{100 * row['braking_over_b_share']:.2f}{percent_bounds_text(bounds, 2)}"


def _defined(value: object) -> object:
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, tuple):
        return tuple(_defined(v) for v in value)
    if isinstance(value, dict):
        return {k: _defined(v) for k, v in value.items()}
    return value


def _interval(per_world: np.ndarray) -> tuple[float, float]:
    """95 % interval of the mean over worlds (normal quantile); (NaN, NaN) from fewer than two
    worlds, whose spread is unknown."""
    n = per_world.size
    if n < 2:
        return (math.nan, math.nan)
    half = 1.96 * float(per_world.std(ddof=1)) / math.sqrt(n)
    mean = float(per_world.mean())
    return (mean - half, mean + half)


def per_1000_interval(count: int, merged: int) -> tuple[float, float]:
    """95 % Wilson interval of `count` events per 1,000 of `merged` vehicles, each merged vehicle
    a trial (at least `count` of them: a vehicle that collided before it merged counts as
    one); (NaN, NaN) where nothing merged. Vehicles of one world are taken as independent,
    so a jam that causes several collisions at once makes the interval too narrow."""
    if merged <= 0:
        return (math.nan, math.nan)
    lo, hi = wilson_interval(count, max(merged, count))
    return (1000.0 * lo, 1000.0 * hi)


def ramp_commands(policy: object, obs: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """[B, K, 2] commands (acceleration, join) of the masked ramp agents from an ego policy
    (NaN elsewhere: IDM; a join of NaN where the policy sets only the acceleration)."""
    cmd = np.full((*mask.shape, 2), np.nan)
    if mask.any():
        x = torch.as_tensor(obs[mask], dtype=torch.float32)
        with torch.no_grad():
            act = np.asarray(policy(x), dtype=np.float64)  # type: ignore[operator]
        act = act.reshape(int(mask.sum()), -1)
        cmd[mask, : act.shape[1]] = act
    return cmd


def check_ramp_scenario(cfg: ScenarioConfig, who: str) -> None:
    """Ramp flow needs `ramp.flow_vph > 0`; `who` ("policy 'gap'", "scenario 'ramp_flow'")
    names what is checked in the error. Its agents see the ego's layout of `cfg`
    (`ramp_agent_features`)."""
    if not cfg.ramp.flowing:
        raise ValueError(
            f"{who}: ramp flow needs ramp.flow_vph > 0 (got {cfg.ramp.flow_vph}): set it in the "
            "scenario or with --ramp-flow"
        )


def agents_scenario(cfg: ScenarioConfig, specs: list[str]) -> tuple[list, ScenarioConfig]:
    """The policies of `specs` (`policy_for_evaluation`) and the scenario the ramp agents are
    simulated in: `cfg` with the ego-side settings (`EGO_SIDE_KEYS`: the observation layout
    and the filter) of its learned policies, which must agree; rules drive in any."""
    loaded = [policy_for_evaluation(spec, cfg) for spec in specs]
    own = {spec: scen for spec, (_, scen) in zip(specs, loaded, strict=True) if scen != cfg}
    agents_cfg = next(iter(own.values()), cfg)
    policies = []
    for spec, (policy, scen) in zip(specs, loaded, strict=True):
        if spec not in own and agents_cfg != cfg:  # a rule (or alike) in the agents' settings
            policy, scen = policy_for_evaluation(spec, agents_cfg)
        if scen != agents_cfg:
            first = next(iter(own))
            raise ValueError(
                f"the policies of one ramp must see it alike: {first!r} drives with "
                f"ego.observation = {agents_cfg.ego.observation!r} and ego.safety_filter = "
                f"{agents_cfg.ego.safety_filter!r}, {spec!r} with {scen.ego.observation!r} and "
                f"{scen.ego.safety_filter!r}"
            )
        policies.append(policy)
    check_ramp_scenario(agents_cfg, f"policy {' / '.join(specs)!r}")
    return policies, agents_cfg


def parse_mix(driver: str) -> list[tuple[str, float]]:
    """`driver` as (policy spec, share) pairs: one spec (share 1), or a mix of learned and
    scripted merging vehicles, `SPEC=SHARE,SPEC=SHARE,...` with shares summing to 1."""
    if "=" not in driver:
        return [(driver, 1.0)]
    mix = []
    for part in driver.split(","):
        spec, _, share = part.rpartition("=")
        try:
            value = float(share)
        except ValueError:
            value = float("nan")
        if not spec or not 0.0 < value <= 1.0:
            raise ValueError(f"mix {driver!r}: {part!r} is not SPEC=SHARE with 0 < SHARE <= 1")
        mix.append((spec, value))
    if abs(sum(v for _, v in mix) - 1.0) > 1e-6:
        raise ValueError(f"mix {driver!r}: the shares sum to {sum(v for _, v in mix):g}, not 1")
    return mix


class RampDrivers:
    """The policies of a ramp-flow run and which one drives each ramp vehicle: with a mix, each
    vehicle draws its policy once, when first seen, from a generator per world seeded
    `(seed, world)` (so the same vehicles get the same policies on every run)."""

    def __init__(self, policies: list[object], shares: list[float], worlds: int, seed: int):
        self.policies, self.cdf = policies, np.cumsum(shares)
        self.rngs = [np.random.default_rng([seed, b]) for b in range(worlds)]
        self.chosen: list[dict[int, int]] = [{} for _ in range(worlds)]

    def commands(self, roster: Roster, obs: np.ndarray) -> np.ndarray:
        """[B, K, 2] commands (acceleration, join) of the roster's agents (NaN where masked)."""
        if len(self.policies) == 1:
            return ramp_commands(self.policies[0], obs, roster.mask)
        which = np.full(roster.mask.shape, -1)
        for b, j in zip(*np.nonzero(roster.mask), strict=True):
            vid = int(roster.ids[b, j])
            if vid not in self.chosen[b]:
                pick = np.searchsorted(self.cdf, self.rngs[b].random(), side="right")
                self.chosen[b][vid] = int(min(pick, len(self.policies) - 1))
            which[b, j] = self.chosen[b][vid]
        cmd = np.full((*roster.mask.shape, 2), np.nan)
        for i, policy in enumerate(self.policies):
            mine = which == i
            cmd[mine] = ramp_commands(policy, obs, mine)[mine]
        return cmd


def run_ramp_flow(
    cfg: ScenarioConfig,
    driver: str = "gap",
    hours: float = 1.0,
    worlds: int = 4,
    seed: int = 0,
    skip_s: float = 300.0,
) -> RampFlowResult:
    """Every ramp vehicle driven by `driver` (a policy spec of `marlmerge evaluate`: `gap`,
    `hold`, `idm`, a run folder or `policy.pt`; or a mix `SPEC=SHARE,...`, `parse_mix`) for
    `hours` of simulated time per world after `skip_s` of settling, in `worlds` worlds seeded
    `seed`."""
    import time

    if not 0 < hours < math.inf or not 0 <= skip_s < math.inf:
        raise ValueError(
            f"hours must be finite and > 0 and skip_s finite and >= 0, got hours={hours}, "
            f"skip_s={skip_s}"
        )
    worlds = check_count("worlds", worlds)
    mix = parse_mix(driver)
    policies, cfg = agents_scenario(cfg, [spec for spec, _ in mix])
    drivers = RampDrivers(policies, [share for _, share in mix], worlds, seed)
    start = time.perf_counter()
    core = TrafficCore(cfg, batch_size=worlds, seed=seed)
    step_s = cfg.sim.dt_s * cfg.sim.action_repeat
    _drive(core, drivers, int(round(skip_s / step_s)), None, None)
    before = _counters(core)
    shields = [p.shield.tally for p in policies if isinstance(p, ShieldedPolicy)]
    shields_before = [replace(t) for t in shields]
    speeds = np.zeros(4)  # summed speed and samples: merge zone, upstream
    ramp_steps = np.zeros(2)  # ramp vehicle-steps: all, and those beyond the agents (IDM)
    tally = MergeTally(cfg, worlds)
    n_steps = int(round(hours * 3600.0 / step_s))
    _drive(core, drivers, n_steps, speeds, tally, ramp_steps)
    after = _counters(core)
    result = _result(cfg, driver, worlds, n_steps * step_s, before, after, speeds, tally)
    window = [t.since(t0) for t, t0 in zip(shields, shields_before, strict=True)]
    pooled = ShieldTally(sum(w.judged for w in window), sum(w.changed for w in window))
    return replace(
        result,
        shield_judged=pooled.judged if shields else None,
        shield_changed_share=pooled.share,
        ramp_steps_by_idm_share=float(ramp_steps[1] / max(ramp_steps[0], 1.0)),
        wall_s=time.perf_counter() - start,
    )


def evaluate_ramp_flow(
    cfg: ScenarioConfig, driver: str, vehicles: int, seed: int, worlds: int
) -> dict[str, object]:
    """A policy evaluated under ramp flow as `marlmerge evaluate` and training's evaluation do:
    `run_ramp_flow` in at most 8 worlds for about `vehicles` ramp arrivals (at least 3 minutes
    per world), after 2 minutes of settling; the result as strict JSON."""
    worlds = min(worlds, 8)
    hours = max(vehicles / (cfg.ramp.flow_vph * worlds), 0.05)
    return run_ramp_flow(cfg, driver, hours, worlds, seed, skip_s=120.0).to_dict()


def _drive(
    core: TrafficCore,
    drivers: RampDrivers,
    n_steps: int,
    speeds: np.ndarray | None,
    tally: MergeTally | None,
    ramp_steps: np.ndarray | None = None,
) -> None:
    """`n_steps` control steps of every world, the ramp agents driven by `drivers`; with
    `speeds` and `tally`, the mainline's speeds, lane changes and braking sampled after each;
    with `ramp_steps` [2], the ramp vehicles' steps counted: all, and those of vehicles beyond
    the first `MAX_RAMP_AGENTS` (which drive by IDM)."""
    nan = np.full(core.batch_size, np.nan)
    road = core.cfg.road
    upstream = (road.x_ramp_start_m - UPSTREAM_WINDOW_M, road.x_ramp_start_m)
    for _ in range(n_steps):
        roster, obs = core.ramp_agents(MAX_RAMP_AGENTS)
        if ramp_steps is not None:
            on_ramp = core.wi[:, L.WI_N_RAMP]  # [B]
            ramp_steps += (on_ramp.sum(), np.maximum(on_ramp - MAX_RAMP_AGENTS, 0).sum())
        cmd = drivers.commands(roster, obs)
        core.rollout(nan, roster=roster, roster_accel=cmd[..., 0], roster_join=cmd[..., 1])
        if tally is not None:
            tally.add(core)
        if speeds is not None:
            st = core.state
            main = st.active & (st.lane >= 0)  # [B, N] on a highway lane
            x, v = st.x_m, st.v_mps
            for i, (lo, hi) in enumerate(((road.x_zone_start_m, 0.0), upstream)):
                sel = main & (x >= lo) & (x < hi)
                speeds[2 * i] += float(v[sel].sum())
                speeds[2 * i + 1] += float(sel.sum())


_COUNTERS = (
    "ramp_entered",
    "ramp_passed",
    "ramp_collisions",
    "background_collisions",
    "exited",
    "ramp_travel_s",
    "ramp_wait_s",
)


def _counters(core: TrafficCore) -> dict[str, np.ndarray]:
    st = core.state
    out = {name: np.array(getattr(st, name), dtype=np.float64) for name in _COUNTERS}
    out["ramp_max_queue"] = np.array(st.ramp_max_queue)
    return out


def _result(
    cfg: ScenarioConfig,
    driver: str,
    worlds: int,
    measured_s: float,
    before: dict[str, np.ndarray],
    after: dict[str, np.ndarray],
    speeds: np.ndarray,
    tally: MergeTally,
) -> RampFlowResult:
    d = {k: after[k] - before[k] for k in _COUNTERS}  # [B] each, in the window
    per_hour = 3600.0 / measured_s
    merged = d["ramp_passed"] * per_hour  # [B]
    ramp_path_m = -cfg.road.x_ramp_start_m
    free_s = ramp_path_m / cfg.road.speed_limit_mps
    some = d["ramp_passed"] > 0  # [B] worlds where a ramp vehicle merged
    delay = d["ramp_travel_s"][some] / d["ramp_passed"][some] - free_s  # [B'] per world
    total_passed = float(d["ramp_passed"].sum())
    collisions = int(d["ramp_collisions"].sum())

    def per_merged(x: float) -> float:  # none merged: undefined
        return x / total_passed if total_passed > 0 else math.nan

    v_merge = speeds[0] / max(speeds[1], 1.0)
    v_up = speeds[2] / max(speeds[3], 1.0)
    return RampFlowResult(
        driver=driver,
        ramp_demand_vph=cfg.ramp.flow_vph,
        mainline_demand_vph_per_lane=cfg.traffic.flow_vph_per_lane,
        worlds=worlds,
        measured_s=measured_s,
        merged_vph=float(merged.mean()),
        merged_vph_ci95=_interval(merged),
        ramp_entered_vph=float(d["ramp_entered"].mean() * per_hour),
        ramp_travel_s=per_merged(float(d["ramp_travel_s"].sum())),
        ramp_delay_s=per_merged(float(d["ramp_travel_s"].sum())) - free_s,
        ramp_delay_s_ci95=_interval(delay),
        ramp_wait_s=float(d["ramp_wait_s"].sum() / max(float(d["ramp_entered"].sum()), 1.0)),
        ramp_max_queue=int(after["ramp_max_queue"].max()),
        ramp_collisions=collisions,
        ramp_collisions_per_1000=per_merged(1000.0 * collisions),
        ramp_collisions_per_1000_ci95=per_1000_interval(collisions, int(total_passed)),
        background_collisions=int(d["background_collisions"].sum()),
        mainline_speed_merge_mps=float(v_merge),
        mainline_speed_upstream_mps=float(v_up),
        mainline_speed_drop_mps=float(v_up - v_merge),
        throughput_vph=float(d["exited"].mean() * per_hour),
        lane_changes_per_hour=float(tally.lane_changes.sum(axis=1).mean() * per_hour),
        lane_change_shares=tally.shares(),
        lane_change_shares_ci95=tally.shares_ci95(),
        **tally.braking(),
    )
