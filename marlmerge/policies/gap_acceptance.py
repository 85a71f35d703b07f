"""Rule-based ramp-vehicle baselines on the ego observation (scaled `[..., F]` in, any layout:
they read the paper's 7 features; acceleration `[..., 1]` in m/s^2 out), interchangeable with a
learned ego policy.

- `GapAcceptancePolicy`: the classic gap-acceptance merger (critical lead and lag gaps).
- `GapShield`: gap acceptance's judgement over another policy's commands.
- `IdmEgoPolicy` (from `marlmerge.policies.scripted`): ignores the merge; the lower bound.
- `constant_speed_action` (from `marlmerge.policies.scripted`): holds its speed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.policies.scripted import IdmEgoPolicy, constant_speed_action, joined
from marlmerge.sim.drivers import idm_accel
from marlmerge.sim.observation import (
    EGO_FEATURES,
    EGO_SCALE,
    LEFT_LANE_FEATURES,
    POSITION_SCALE_M,
    SPEED_SCALE_MPS,
    ego_features,
    feature_index,
    shows_left_lane,
)

__all__ = [
    "GapAcceptancePolicy",
    "GapDecision",
    "GapShield",
    "IdmEgoPolicy",
    "ShieldTally",
    "constant_speed_action",
]

_E = {f.name: feature_index(EGO_FEATURES, f.name) for f in EGO_FEATURES}
KEEP_ROLLING_MPS = 2.0
"""`GapShield(keep_rolling=True)`: a command that leaves the ego slower than this (m/s) more
than `ROLL_ROOM_M` before gap acceptance's wait point is raised to gap acceptance's action."""
ROLL_ROOM_M = 5.0
CHANGED_MPS2 = 1e-4
"""A command the shield moved by more than this (m/s^2) counts as changed (`ShieldTally`)."""


class GapDecision(NamedTuple):
    """What gap acceptance decided for a batch of observations [...]."""

    accel: np.ndarray
    """[..., 1] its action (m/s^2, float32); [..., 2] with the join (`ego.join = "chosen"`)."""
    accepts: np.ndarray
    """[...] some plan joins the current gap (on the ramp)."""
    plan_accel: np.ndarray
    """[..., K] the first command (m/s^2) of each candidate plan."""
    plan_joins: np.ndarray
    """[..., K] the plan joins the current gap with both margins >= 0 (on the ramp)."""


class GapAcceptancePolicy:
    """The classic gap-acceptance merger (critical lead and lag gaps), on the ego observation alone.

    On the ramp (x < x_ov = `cfg.x_overlap_m`, where the ego joins the right lane), every call:

    1. **Plans.** K candidate plans, each a target speed (`speed_fractions` x the speed limit, the
       gap-back or gap-front vehicle's speed + `relative_speeds_mps`, or the current speed)
       reached at a gentle or a firm rate (`accel_mps2`, `brake_mps2`), then held. For each plan:
       the ego's arrival time t_a and speed v_a at x_ov (closed form), and where the gap vehicles
       are at t_a driving at constant speed.
    2. **Gap test.** Predicted lead gap: the ego's time gap to the gap-front vehicle,
       (bumper gap - s0 - (v_a - v_front)+^2 / (2 `lead_brake_mps2`)) / v_a. Predicted lag gap:
       the gap-back vehicle's time gap to the ego, (bumper gap - s0 - (v_back - v_a)+^2 /
       (2 `lag_brake_mps2`)) / v_back. A plan accepts the gap when both are at least the critical
       gaps, which shrink linearly with the remaining distance to x_ov: `critical_*_gap_s` at
       `relax_distance_m` or more (default: the ramp start), `forced_*_gap_s` at x_ov (drivers
       near the end of an acceleration lane accept shorter gaps; the closing-speed terms stay).
    3. **Accept.** If some plan accepts the current gap, the ego drives the best one: largest
       margin over the critical gaps (capped at `margin_cap_s`), minus `speed_weight` x |target -
       speed limit| / speed limit, minus `firm_weight` for a firm rate. A lag-gap problem that
       accelerating fixes is solved here (the ego speeds up to get ahead of the back vehicle), as
       is a lead-gap problem that a little braking fixes.
    4. **Drop behind.** Otherwise the ego aims for the next gap: the best plan under which the
       gap-back vehicle passes it with an acceptable lead gap, so that it becomes the gap-front
       and the vehicle behind it (seen once it has passed) the next candidate. As that next gap is
       unseen, the ego keeps able to stop `wait_before_m` before x_ov, braking `wait_brake_mps2`.
    5. **Wait or force.** If no plan does either, the ego stops `wait_before_m` before x_ov while
       it still can (it waits: from standstill it needs a long lag gap, which cooperative drivers
       open), and past that point takes the plan with the largest margin (in metres).

    From x_ov on it follows the gap-front vehicle by IDM (as `IdmEgoPolicy`). The policy is
    stateless and sees only its observation: the nearest right-lane vehicles ahead and behind its
    projected position (a left-lane vehicle that cuts in next to it cannot be foreseen).

    Defaults. Lead gap 1.0 s: the shortest desired headway of the mainline drivers
    (`driver.time_headway_s`) and the reward's safe headway. Lag gap 1.0 s, shorter than the
    ~1.5 s raw lag gaps measured on freeways because the jam gap and the braking distance for the
    closing speed (at 4 m/s^2, the simulator's MOBIL safety limit `driver.safe_brake_mps2`) are
    already subtracted, and because yielding or gap-closing drivers settle at their own 1.0-1.8 s
    headway: with 1.5 s the ego waits at the end of the ramp in all-adversarial traffic (5.5 %
    truncations against 0.4 %, 2000 episodes). A strong preference for speed (`speed_weight`)
    matters most: an ego that slows down on the ramp needs ever longer lag gaps.
    """

    def __init__(
        self,
        cfg: ScenarioConfig | None = None,
        critical_lead_gap_s: float = 1.0,
        critical_lag_gap_s: float = 1.0,
        forced_lead_gap_s: float = 0.0,
        forced_lag_gap_s: float = 0.0,
        relax_distance_m: float | None = None,
        lead_brake_mps2: float = 3.0,
        lag_brake_mps2: float | None = None,
        accel_mps2: tuple[float, float] = (1.0, 2.5),
        brake_mps2: tuple[float, float] = (1.5, 4.0),
        speed_fractions: tuple[float, ...] = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0),
        relative_speeds_mps: tuple[float, ...] = (-6.0, -3.0, -1.5, 0.0, 1.5),
        margin_cap_s: float = 1.0,
        speed_weight: float = 3.0,
        firm_weight: float = 0.3,
        wait_before_m: float = 1.0,
        wait_brake_mps2: float = 3.0,
    ):
        self.cfg = cfg or ScenarioConfig()
        self.critical_lead_gap_s = critical_lead_gap_s
        self.critical_lag_gap_s = critical_lag_gap_s
        self.forced_lead_gap_s = forced_lead_gap_s
        self.forced_lag_gap_s = forced_lag_gap_s
        ramp_m = self.cfg.x_overlap_m - self.cfg.road.x_ramp_start_m
        self.relax_distance_m = ramp_m if relax_distance_m is None else relax_distance_m
        self.lead_brake_mps2 = lead_brake_mps2
        self.lag_brake_mps2 = (
            self.cfg.driver.safe_brake_mps2 if lag_brake_mps2 is None else lag_brake_mps2
        )
        self.margin_cap_s = margin_cap_s
        self.speed_weight = speed_weight
        self.firm_weight = firm_weight
        self.wait_before_m = wait_before_m
        self.wait_brake_mps2 = wait_brake_mps2
        lo, hi = self.cfg.ego.accel_bounds_mps2
        # plans [K]: a target speed (kind 0: fraction x speed limit, 1: back vehicle's speed +
        # offset, 2: front vehicle's speed + offset, 3: the current speed), each at both rates
        fr = np.asarray(speed_fractions, dtype=np.float64)
        rel = np.asarray(relative_speeds_mps, dtype=np.float64)
        kind = np.concatenate([np.zeros(fr.size), np.ones(rel.size), np.full(rel.size, 2.0)])
        val = np.concatenate([fr, rel, rel])
        n = kind.size
        self.plan_kind = np.append(np.tile(kind, 2), 3.0)
        self.plan_val = np.append(np.tile(val, 2), 0.0)
        up = np.minimum(np.repeat(np.asarray(accel_mps2, dtype=np.float64), n), hi)
        down = np.minimum(np.repeat(np.asarray(brake_mps2, dtype=np.float64), n), -lo)
        self.plan_up = np.append(up, 0.0)
        self.plan_down = np.append(down, 0.0)
        self.plan_firm = np.append(np.repeat([0.0, 1.0], n), 0.0)
        self.control_s = self.cfg.sim.dt_s * self.cfg.sim.action_repeat
        self._in_lane = IdmEgoPolicy(self.cfg)

    @staticmethod
    def _arrival(
        v: np.ndarray, dist: np.ndarray, v_end: np.ndarray, up: np.ndarray, down: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Arrival time (s) and speed (m/s) after `dist` m: change speed from v to v_end at rate
        `up` or `down` (m/s^2), then cruise. Shapes broadcast to [..., K]; inf if it never arrives.
        """
        a = np.where(v_end > v, up, -down)
        a = np.where(v_end == v, 0.0, a)
        safe_a = np.where(a == 0.0, 1.0, a)
        t_ramp = np.where(a == 0.0, 0.0, (v_end - v) / safe_a)
        d_ramp = 0.5 * (v + v_end) * t_ramp
        v_reach = np.sqrt(np.maximum(v * v + 2.0 * a * dist, 0.0))
        within = dist <= d_ramp
        t_within = 2.0 * dist / np.maximum(v + v_reach, 1e-9)
        t_cruise = np.where(v_end > 0.0, t_ramp + (dist - d_ramp) / np.maximum(v_end, 1e-9), np.inf)
        t = np.where(within, t_within, t_cruise)
        v_a = np.where(within, v_reach, v_end)
        return np.where(dist <= 0.0, 0.0, t), np.where(dist <= 0.0, v, v_a)

    def _margins(
        self,
        t: np.ndarray,
        v_a: np.ndarray,
        x_f: np.ndarray,
        v_f: np.ndarray,
        x_b: np.ndarray,
        v_b: np.ndarray,
        t_lead: np.ndarray,
        t_lag: np.ndarray,
        x_ov: np.ndarray | float | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(lead, lag) margins (s) over the critical gaps at arrival at `x_ov` (default: the
        overlap point), [..., K]; >= 0: acceptable."""
        cfg = self.cfg
        length, s0 = cfg.vehicle.length_m, cfg.driver.min_gap_m
        x_ov = cfg.x_overlap_m if x_ov is None else x_ov
        t = np.minimum(t, 1.0e3)
        s_lead = x_f + v_f * t - length - x_ov - s0
        s_lead -= np.maximum(v_a - v_f, 0.0) ** 2 / (2.0 * self.lead_brake_mps2)
        s_lag = x_ov - length - (x_b + v_b * t) - s0
        s_lag -= np.maximum(v_b - v_a, 0.0) ** 2 / (2.0 * self.lag_brake_mps2)
        lead = s_lead / np.maximum(v_a, 1.0) - t_lead
        lag = s_lag / np.maximum(v_b, 1.0) - t_lag
        return lead, lag

    def critical_gaps(self, dist_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The critical (lead, lag) time gaps (s) at `dist_m` before the join point: relaxed
        linearly from `critical_*_gap_s` (at `relax_distance_m` or more) to `forced_*_gap_s`."""
        u = np.clip(1.0 - dist_m / max(self.relax_distance_m, 1e-9), 0.0, 1.0)
        t_lead = self.critical_lead_gap_s + (self.forced_lead_gap_s - self.critical_lead_gap_s) * u
        t_lag = self.critical_lag_gap_s + (self.forced_lag_gap_s - self.critical_lag_gap_s) * u
        return t_lead, t_lag

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """obs: [..., F] scaled ego observation (any layout: it reads the paper's features, the
        first 7) -> [..., 1] acceleration (m/s^2), within bounds; with `ego.join = "chosen"`
        [..., 2], then the join (`join_now`)."""
        return self.decide(obs).accel

    def join_now(self, obs: np.ndarray) -> np.ndarray:
        """`ego.join = "chosen"`: [...] +1 where the ramp vehicle, inside the merge zone, has an
        acceptable gap alongside it now (both margins of the gap test >= 0 at its own position,
        with the critical gaps of its distance to the overlap point), else -1."""
        cfg = self.cfg
        raw = np.nan_to_num(np.asarray(obs, dtype=np.float64)[..., : len(EGO_FEATURES)])
        raw = raw * EGO_SCALE
        col = {k: raw[..., i] for k, i in _E.items()}
        x, v = col["ego_position"], np.maximum(col["ego_speed"], 0.0)
        t_lead, t_lag = self.critical_gaps(np.maximum(cfg.x_overlap_m - x, 0.0))
        lead, lag = self._margins(
            np.zeros_like(x), v, col["front_position"], np.maximum(col["front_speed"], 0.0),
            col["back_position"], np.maximum(col["back_speed"], 0.0), t_lead, t_lag, x,
        )  # fmt: skip
        ok = (lead >= 0.0) & (lag >= 0.0) & (x >= cfg.road.x_zone_start_m)
        return np.where(ok, 1.0, -1.0)

    def decide(self, obs: np.ndarray) -> GapDecision:
        """The action of `__call__` and how it was reached (`GapDecision`)."""
        cfg = self.cfg
        lo, hi = cfg.ego.accel_bounds_mps2
        # junk values (nan, inf) become finite, so the answer stays inside the bounds
        obs_all = np.nan_to_num(np.asarray(obs, dtype=np.float64), nan=0.0, posinf=1e3, neginf=-1e3)
        obs = obs_all[..., : len(EGO_FEATURES)]
        raw = obs * EGO_SCALE
        col = {k: raw[..., i][..., None] for k, i in _E.items()}  # each [..., 1]
        v = np.maximum(col["ego_speed"], 0.0)
        x = col["ego_position"]
        x_f, v_f = col["front_position"], np.maximum(col["front_speed"], 0.0)
        x_b, v_b = col["back_position"], np.maximum(col["back_speed"], 0.0)
        v_lim = np.maximum(col["speed_limit"], 1.0)
        dist = np.maximum(cfg.x_overlap_m - x, 0.0)
        t_lead, t_lag = self.critical_gaps(dist)

        # 1. plans [..., K]
        kind, val = self.plan_kind, self.plan_val
        base = np.where(kind == 1, v_b, np.where(kind == 2, v_f, v))
        v_end = np.where(kind == 0, val * v_lim, np.clip(base + val, 0.0, v_lim))
        t, v_a = self._arrival(v, dist, v_end, self.plan_up, self.plan_down)
        a_cmd = np.clip((v_end - v) / self.control_s, -self.plan_down, self.plan_up)
        pref = (
            -self.speed_weight * np.abs(v_end - v_lim) / v_lim - self.firm_weight * self.plan_firm
        )
        arrives = np.isfinite(t)

        def best(margin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            ok = (margin >= 0.0) & arrives
            score = np.where(ok, np.minimum(margin, self.margin_cap_s) + pref, -np.inf)
            k = np.argmax(score, axis=-1)[..., None]
            return np.take_along_axis(a_cmd, k, -1)[..., 0], ok.any(axis=-1)

        # 2.-3. the current gap
        lead, lag = self._margins(t, v_a, x_f, v_f, x_b, v_b, t_lead, t_lag)
        margin = np.minimum(lead, lag)
        a_gap, accept = best(margin)
        # 4. drop behind: the gap-back vehicle becomes the gap-front, the gap behind it is unseen
        lead_b, _ = self._margins(t, v_a, x_b, v_b, x_b - 1.0e4, v_b, t_lead, t_lag)
        a_behind, behind = best(lead_b)
        # 5. wait (stop before x_ov while braking can still do it) or force the best margin
        v0, d0 = v[..., 0], dist[..., 0]
        d_wait = d0 - self.wait_before_m
        d_wait = np.where(d_wait > 0.5, d_wait, np.maximum(d0 - 0.5, 1e-3))
        a_wait = -(v0**2) / (2.0 * d_wait)
        # dropping behind, the ego stays able to stop there: the gap behind is not seen yet
        v_env = np.sqrt(2.0 * self.wait_brake_mps2 * np.maximum(d_wait - v0 * self.control_s, 0.0))
        a_env = np.where(
            v0**2 > 2.0 * self.wait_brake_mps2 * d_wait, a_wait, (v_env - v0) / self.control_s
        )
        a_behind = np.minimum(a_behind, a_env)
        margin_m = np.minimum(lead * np.maximum(v_a, 1.0), lag * np.maximum(v_b, 1.0))
        k_force = np.argmax(np.where(arrives, margin_m, -np.inf), axis=-1)[..., None]
        a_force = np.take_along_axis(a_cmd, k_force, -1)[..., 0]
        a_ramp = np.where(
            accept,
            a_gap,
            np.where(behind, a_behind, np.where(v0**2 <= -2.0 * lo * d0, a_wait, a_force)),
        )

        a_lane = self._in_lane(obs_all)[..., 0].astype(np.float64)
        in_lane = joined(obs_all, cfg) | (x[..., 0] >= cfg.x_overlap_m)
        accel = np.where(in_lane, a_lane, a_ramp)
        accel = np.clip(np.nan_to_num(accel, nan=0.0), lo, hi)[..., None]
        if cfg.ego.chooses_join:
            accel = np.concatenate([accel, self.join_now(obs_all)[..., None]], axis=-1)
        joins = (margin >= 0.0) & arrives & (x < cfg.x_overlap_m)
        return GapDecision(accel.astype(np.float32), accept & joins.any(-1), a_cmd, joins)


@dataclass
class ShieldTally:
    """How often a `GapShield` stepped in since it was built: the commands it judged (rows on
    the ramp, before the join point x_ov) and how many of those it changed. Rows past x_ov
    (`cap_in_lane`'s) and free agent columns (all-zero observations sit at x = 0) are not
    counted. The share is a number a user of `@shield` should see: a policy the shield keeps
    overruling drives gap acceptance's merge, not its own."""

    judged: int = 0
    changed: int = 0
    last_judged: np.ndarray | None = field(default=None, compare=False, repr=False)
    """[B, 1] the rows of the last call that were judged (a caller that knows which rows are
    live counts per episode from these: `marlmerge.evaluation.rollout`)."""
    last_changed: np.ndarray | None = field(default=None, compare=False, repr=False)
    """[B, 1] ... and changed."""

    def add(self, on_ramp: np.ndarray, asked: np.ndarray, driven: np.ndarray) -> None:
        """Count one call: on_ramp, asked, driven [B, 1]."""
        self.last_judged = on_ramp
        self.last_changed = on_ramp & (np.abs(driven - asked) > CHANGED_MPS2)
        self.judged += int(on_ramp.sum())
        self.changed += int(self.last_changed.sum())

    @property
    def share(self) -> float | None:
        """The share of the judged commands that were changed (None with none judged)."""
        return self.changed / self.judged if self.judged else None

    def since(self, before: ShieldTally) -> ShieldTally:
        """The counts after `before` (a copy taken earlier)."""
        return ShieldTally(self.judged - before.judged, self.changed - before.changed)


class GapShield:
    """Gap acceptance's judgement over another policy's command (the grid's `@shield`).

    On the ramp (before the join point x_ov), each call, the command a (m/s^2) stands if one
    of these holds, judged with gap acceptance's gap test (`GapAcceptancePolicy`: predicted
    lead and lag time gaps after the jam gap and the braking distance for the closing speed)
    at `critical_gap_s` for both gaps, not relaxed towards x_ov (`forced_gap_s`, below):

    1. the command, taken as a plan (speed up at a towards the speed limit, or brake at |a|
       towards a stop, and hold), joins the current gap with both gaps long enough;
    2. after one control step with it (the other vehicles at constant speed), some plan of gap
       acceptance's still joins the current gap;
    3. after that step the ego can still stop `wait_before_m` before x_ov braking at
       `commit_brake_mps2`, and gap acceptance has no plan into the current gap either
       (nothing is committed, nothing better is on offer).

    Otherwise the ego drives, of gap acceptance's plans that join the current gap, the one whose
    first command is nearest its own; if none does, gap acceptance's own action (dropping
    behind, waiting, or, past the point of waiting, the largest margin). From x_ov on, the
    command stands. A merger that floors the throttle on the ramp collides in 55 of 128 dense
    roads and in none behind the shield (`tests/test_gap_acceptance.py`).

    The settings were chosen on the grid and the first held-out set (`docs/robustness.md`):
    `commit_brake_mps2` 1.5 m/s^2 (gap acceptance's 3 m/s^2 hands over so late that the ego
    often has to wait at the end of the ramp); `critical_gap_s` 0.5 s, half gap acceptance's
    own (with its 1 s the shield takes over in a quarter of the episodes, and the ride is as
    rough as gap acceptance's); `forced_gap_s` None: the critical gap is not relaxed towards
    x_ov. Relaxed as gap acceptance relaxes its own (to `forced_gap_s` at x_ov), the ride is
    smoother, but the floored-throttle merger gets through: 6 collisions on the 128 roads with
    0.35 s, 24 with 0 s.

    Like gap acceptance, it sees only the observation (its paper's features, and with
    `watch_left` the left-lane ones): it is a policy wrapper, not the core's safety filter
    (`ego.safety_filter`), and it acts on what the sensors report.

    Three options (the grid's `@shield-left` turns them all on):

    - `watch_left`, with an extended observation (`LEFT_LANE_FEATURES`): a left-lane driver who
      would move right into the ego's gap is judged as if it had, in every test above, in place
      of the gap-front vehicle (if ahead of the ego) or the gap-back vehicle (if behind).
      Predicted by MOBIL as a driver of the scenario's mean settings would judge it
      (`_left_movers`): room to both gap vehicles, the gap-back vehicle braking no harder than
      `driver.safe_brake_mps2` behind it, and IDM's acceleration behind the gap-front vehicle
      at least its acceleration in the left lane (behind the other left-lane vehicle, or on a
      free road) less `left_margin_mps2` (1 m/s^2, chosen on the grid's conditions:
      `docs/stress.md`). The paper's drivers move right without regard to a
      vehicle about to join, and a move in the last second before the join cannot be answered
      once it is seen.
    - `cap_in_lane`: once the ego is in its lane, its command is capped at IDM's behind its
      leader (`IdmEgoPolicy`).
    - `keep_rolling`: a command that would leave the ego nearly stopped (`KEEP_ROLLING_MPS`)
      well before gap acceptance's wait point is raised to gap acceptance's action, which rolls
      on to that point. A learned ego that stops early on a long ramp in slow traffic otherwise
      stalls there until its episode is truncated, and the shield, which judges joins, let it.

    `tally` (`ShieldTally`) counts the commands judged on the ramp and those changed; the
    judgement itself depends on nothing but the call's arguments.
    """

    def __init__(
        self,
        cfg: ScenarioConfig | None = None,
        commit_brake_mps2: float = 1.5,
        critical_gap_s: float = 0.5,
        forced_gap_s: float | None = None,
        watch_left: bool = False,
        cap_in_lane: bool = False,
        left_margin_mps2: float = 1.0,
        keep_rolling: bool = False,
    ):
        if cfg is not None and cfg.ego.chooses_join:
            raise ValueError(
                f"GapShield judges joins at the overlap point; ego.join = {cfg.ego.join!r} "
                "leaves the join to the policy (use ego.join = 'forced')"
            )
        self.gap = GapAcceptancePolicy(cfg)
        self.judge = GapAcceptancePolicy(
            cfg,
            critical_lead_gap_s=critical_gap_s,
            critical_lag_gap_s=critical_gap_s,
            forced_lead_gap_s=critical_gap_s if forced_gap_s is None else forced_gap_s,
            forced_lag_gap_s=critical_gap_s if forced_gap_s is None else forced_gap_s,
        )
        self.cfg = self.gap.cfg
        self.commit_brake_mps2 = commit_brake_mps2
        if watch_left and not shows_left_lane(self.cfg):
            raise ValueError(
                f"GapShield(watch_left=True) reads the left-lane features; ego.observation = "
                f"{self.cfg.ego.observation!r} has none (use any layout but 'paper')"
            )
        names = [f.name for f in ego_features(self.cfg)]
        self._left = tuple(names.index(n) for n in LEFT_LANE_FEATURES) if watch_left else None
        self.left_margin_mps2 = left_margin_mps2
        self._cap = IdmEgoPolicy(self.cfg) if cap_in_lane else None
        self.keep_rolling = keep_rolling
        self.tally = ShieldTally()

    def __call__(self, obs: np.ndarray, cmd: np.ndarray) -> np.ndarray:
        """obs [B, F] scaled ego observation, cmd [B, 1] (m/s^2) -> [B, 1] the command or the
        override (float32)."""
        seen = np.asarray(obs)
        if self._left is not None:
            obs = self._left_movers(seen)
        raw = np.nan_to_num(np.asarray(obs, dtype=np.float64)[..., : len(EGO_FEATURES)]) * EGO_SCALE
        col = {k: raw[..., i][..., None] for k, i in _E.items()}  # each [B, 1]
        a = np.asarray(cmd, dtype=np.float64).reshape(col["ego_speed"].shape)
        x, x_ov = col["ego_position"], self.cfg.x_overlap_m
        v1, x1 = self._one_step(col, a)
        after = self._observation_after_one_step(obs, col, v1, x1)
        still_joins = self.judge.decide(after).accepts[..., None] & (x1 < x_ov)
        stop_m = v1 * v1 / (2.0 * self.commit_brake_mps2)
        can_wait = x1 + stop_m <= x_ov - self.gap.wait_before_m
        gap = self.gap.decide(obs)
        keep = self._joins(col, a) | still_joins | (can_wait & ~gap.accepts[..., None])
        out = np.where(keep | (x >= x_ov), a, self._override(a, gap))
        if self.keep_rolling:  # a stop short of the wait point: gap acceptance's way on
            stops = (v1 < KEEP_ROLLING_MPS) & (x1 < x_ov - self.gap.wait_before_m - ROLL_ROOM_M)
            out = np.where(stops & (x < x_ov), np.maximum(out, gap.accel), out)
        if self._cap is not None:
            in_lane = joined(seen, self.cfg)[..., None]
            out = np.where(in_lane, np.minimum(out, self._cap(seen)), out)
        out = out.astype(np.float32)
        self.tally.add(x < x_ov, a, out)
        return out

    def _left_movers(self, obs: np.ndarray) -> np.ndarray:
        """obs [B, F] with the gap vehicles replaced by the left-lane drivers predicted to move
        right into the ego's gap (`watch_left`, see the class docstring)."""
        cfg, d = self.cfg, self.cfg.driver
        out = np.array(obs, dtype=np.float64)
        raw = np.nan_to_num(out[..., : len(EGO_FEATURES)]) * EGO_SCALE
        x, v_lim = raw[..., _E["ego_position"]], raw[..., _E["speed_limit"]]
        x_f, v_f = raw[..., _E["front_position"]], raw[..., _E["front_speed"]]
        x_b, v_b = raw[..., _E["back_position"]], raw[..., _E["back_speed"]]
        length, s0 = cfg.vehicle.length_m, d.min_gap_m
        v0 = float(np.mean(d.desired_speed_factor)) * v_lim  # the mean driver's settings
        t_hw = float(np.mean(d.time_headway_s))

        def idm(v: np.ndarray, gap: np.ndarray, v_lead: np.ndarray) -> np.ndarray:
            a, b = d.accel_mps2, d.comfort_brake_mps2
            return idm_accel(v, gap, v_lead, v0, t_hw, a, b, s0, d.delta)

        i_fdx, i_fv, i_bdx, i_bv = self._left
        rng = cfg.ego.sensing_range_m - 1e-3  # a missing vehicle sits at +-range
        lf_dx = np.nan_to_num(out[..., i_fdx]) * POSITION_SCALE_M
        lb_dx = np.nan_to_num(out[..., i_bdx]) * POSITION_SCALE_M
        lf_v = np.nan_to_num(out[..., i_fv]) * SPEED_SCALE_MPS
        lb_v = np.nan_to_num(out[..., i_bv]) * SPEED_SCALE_MPS
        # left-lane leaders: the front left vehicle's is unseen (a free road), the back one's is
        # the front left vehicle (or none)
        free = np.full_like(x, np.inf)
        lb_gap = np.where(np.abs(lf_dx) < rng, lf_dx - lb_dx - length, free)
        for dx, v_l, gap_l, v_lead_l, side in (
            (lf_dx, lf_v, free, lf_v, "front"),
            (lb_dx, lb_v, lb_gap, lf_v, "back"),
        ):
            x_l = x + dx
            fits = (np.abs(dx) < rng) & (x_l - x_b - length > s0) & (x_f - x_l - length > s0)
            safe = idm(v_b, x_l - x_b - length, v_l) >= -d.safe_brake_mps2
            wants = idm(v_l, x_f - x_l - length, v_f) >= idm(v_l, gap_l, v_lead_l) - (
                self.left_margin_mps2
            )
            moves = fits & safe & wants
            i_x, i_s = _E[f"{side}_position"], _E[f"{side}_speed"]
            out[..., i_x] = np.where(moves, x_l / EGO_SCALE[i_x], out[..., i_x])
            out[..., i_s] = np.where(moves, v_l / EGO_SCALE[i_s], out[..., i_s])
        return out

    def _one_step(self, col: dict, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The ego's speed and position [B, 1] after one control step at a."""
        step_s = self.gap.control_s
        v = np.maximum(col["ego_speed"], 0.0)
        v1 = np.maximum(v + a * step_s, 0.0)
        return v1, col["ego_position"] + 0.5 * (v + v1) * step_s

    def _observation_after_one_step(
        self, obs: np.ndarray, col: dict, v1: np.ndarray, x1: np.ndarray
    ) -> np.ndarray:
        """The observation predicted one control step on: the ego at (x1, v1), the gap vehicles
        at constant speed."""
        step_s = self.gap.control_s
        after = np.array(obs, dtype=np.float64)
        for name, value in (
            ("ego_speed", v1),
            ("ego_position", x1),
            ("front_position", col["front_position"] + col["front_speed"] * step_s),
            ("back_position", col["back_position"] + col["back_speed"] * step_s),
        ):
            after[..., _E[name]] = value[..., 0] / EGO_SCALE[_E[name]]
        return after

    def _joins(self, col: dict, a: np.ndarray) -> np.ndarray:
        """[B, 1]: the command a [B, 1], taken as a constant-acceleration plan (towards the speed
        limit, or a stop), joins the current gap with both gaps at least `critical_gap_s`."""
        g = self.judge
        v = np.maximum(col["ego_speed"], 0.0)
        dist = np.maximum(self.cfg.x_overlap_m - col["ego_position"], 0.0)
        v_end = np.where(a > 0.0, np.maximum(col["speed_limit"], v), np.where(a < 0.0, 0.0, v))
        t, v_a = g._arrival(v, dist, v_end, np.maximum(a, 1e-6), np.maximum(-a, 1e-6))
        lead, lag = g._margins(
            t, v_a, col["front_position"], np.maximum(col["front_speed"], 0.0),
            col["back_position"], np.maximum(col["back_speed"], 0.0), *g.critical_gaps(dist),
        )  # fmt: skip
        return np.isfinite(t) & (np.minimum(lead, lag) >= 0.0)

    @staticmethod
    def _override(a: np.ndarray, gap: GapDecision) -> np.ndarray:
        """[B, 1]: of gap acceptance's plans into the current gap, the one whose first command
        is nearest a; if none, gap acceptance's action."""
        dist = np.where(gap.plan_joins, np.abs(gap.plan_accel - a), np.inf)
        k = np.argmin(dist, axis=-1)[..., None]
        a_join = np.take_along_axis(gap.plan_accel, k, -1)
        return np.where(gap.accepts[..., None], a_join, gap.accel)


def grid_shield(cfg: ScenarioConfig | None, left: bool) -> GapShield:
    """The shield the grid's policy specs name: `@shield` (`left` False) or `@shield-left`
    (`watch_left`, `cap_in_lane` and `keep_rolling` all on)."""
    return GapShield(cfg, watch_left=left, cap_in_lane=left, keep_rolling=left)
