"""The one configuration schema: frozen dataclasses with defaults in code, loaded strictly.

A scenario preset (`envs/*.toml`) is a partial `ScenarioConfig` written as TOML tables; every key it
names must exist here, and an unknown key raises `ValueError` naming its full path.

Coordinates: `x_m` runs along the highway in the direction of travel, 0 at the **merge point**,
where the ramp centreline has joined the right lane's centreline (the end of the merge zone).
The ramp vehicle's position is measured along its own path, which is parallel to the highway
inside the merge zone, so all positions share one axis.

    x = -highway_upstream_m             highway entrance (traffic spawns here)
    x = -(merge_zone_m + ramp_length_m) ramp start (the ego departs here)
    x = -merge_zone_m                   merge-zone start: the ramp taper begins
    x = 0                               merge point: the ramp vehicle is in the right lane
    x = success_distance_m              success: merged and this far downstream
    x = highway_downstream_m            highway exit (traffic leaves here)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from marlmerge.config.codec import from_dict, read_toml, set_dotted, to_dict
from marlmerge.config.rules import check_values, num, positive, require

MPH_TO_MPS = 0.44704
OBSERVATION_LAYOUTS = ("paper", "extended", "extended_accel", "extended_join")
"""Values of `ego.observation` (the tables: `marlmerge.sim.observation.EGO_LAYOUTS`)."""
RAMP_JOINS = ("forced", "when_safe")
"""Values of `ramp.join`."""
RAMP_COOPERATIONS = ("head", "zipper")
"""Values of `ramp.cooperation`."""
EGO_JOINS = ("forced", "chosen")
"""Values of `ego.join`."""
ENTRANCE_LANES = ("drawn", "best")
"""Values of `traffic.entrance_lane`."""
MAX_LATENCY_S = 2.0
"""`sensing.latency_s` is at most this (the core keeps that many steps of observations)."""
MAX_WARMUP_S = 600.0
"""A fresh road is simulated this long at most before its first episode (steady flow is reached
within one pass of the road, well under a minute at any legal speed)."""
MAX_WEIGHT = 1.0e4
"""Reward weights and penalties are at most this (the terms are of order 1 per step)."""
MAX_HIGHWAY_AGENTS = 32
"""`sim.n_highway_agents` is at most this (a merge meets a handful of right-lane vehicles)."""


@dataclass(frozen=True)
class RoadConfig:
    """Geometry of the ramp and the two highway lanes in the merge direction."""

    lane_width_m: float = num(3.75, 2.5, 5.0)
    """Width of each highway lane."""
    ramp_width_m: float = num(3.5, 2.5, 5.0)
    """Width of the single ramp lane."""
    highway_upstream_m: float = positive(400.0, 4000.0, high_open=True)
    """Highway length from the entrance to the merge point."""
    highway_downstream_m: float = positive(200.0, 4000.0, high_open=True)
    """Highway length from the merge point to the exit."""
    ramp_length_m: float = num(150.0, 0.0, 2000.0)
    """Ramp length from the ramp start to the merge-zone start."""
    merge_zone_m: float = num(100.0, 10.0, 1000.0)
    """Length of the taper in which the ramp centreline moves onto the right lane's centreline."""
    speed_limit_mph: float = num(65.0, 10.0, 100.0)
    """Posted speed limit (65 mph = 29.06 m/s)."""

    @property
    def speed_limit_mps(self) -> float:
        return self.speed_limit_mph * MPH_TO_MPS

    @property
    def ramp_offset_m(self) -> float:
        """Lateral distance from the right lane's centreline to the ramp centreline."""
        return 0.5 * (self.lane_width_m + self.ramp_width_m)

    @property
    def x_entrance_m(self) -> float:
        return -self.highway_upstream_m

    @property
    def x_exit_m(self) -> float:
        return self.highway_downstream_m

    @property
    def x_ramp_start_m(self) -> float:
        return -(self.merge_zone_m + self.ramp_length_m)

    @property
    def x_zone_start_m(self) -> float:
        return -self.merge_zone_m


@dataclass(frozen=True)
class VehicleConfig:
    """Vehicle body and the physical limits shared by every vehicle."""

    length_m: float = num(5.0, 2.0, 20.0)
    width_m: float = num(1.8, 1.0, 3.0)
    max_brake_mps2: float = num(9.0, 1.0, 12.0)
    """Physical braking limit: no vehicle decelerates harder than this."""
    max_accel_mps2: float = num(3.0, 0.5, 8.0)
    """Physical acceleration limit of highway vehicles."""


@dataclass(frozen=True)
class DriverConfig:
    """IDM car following, MOBIL lane changes, and how drivers differ (drawn per vehicle)."""

    accel_mps2: float = num(1.5, 0.1, 8.0)
    """IDM maximum acceleration a."""
    comfort_brake_mps2: float = num(2.0, 0.1, 12.0)
    """IDM comfortable deceleration b."""
    min_gap_m: float = positive(2.0, 20.0)
    """IDM jam distance s0 (bumper to bumper)."""
    delta: float = num(4.0, 1.0, 10.0)
    """IDM free-road exponent."""
    desired_speed_factor: tuple[float, float] = num((0.9, 1.1), 0.3, 2.0, ordered=True)
    """Desired speed = factor x speed limit, factor uniform in this range."""
    time_headway_s: tuple[float, float] = positive((1.0, 1.8), 5.0, ordered=True)
    """IDM desired time headway T, uniform in this range."""
    politeness: tuple[float, float] = num((0.1, 0.5), 0.0, 2.0, ordered=True)
    """MOBIL politeness p, uniform in this range."""
    lane_change_threshold_mps2: float = num(0.2, 0.0, 1.0e6)
    """MOBIL incentive threshold (a huge value, e.g. 1e6, turns lane changes off)."""
    keep_right_bias_mps2: float = num(0.2, 0.0, 5.0)
    """MOBIL keep-right bias: extra incentive needed to move left, granted to move right."""
    safe_brake_mps2: float = positive(4.0, 12.0)
    """MOBIL safety criterion: a lane change may not make the new follower brake harder."""
    lane_change_sees_ramp: bool = False
    """A driver moving right counts the ramp vehicle inside the merge zone (or reaching it before
    the driver's next lane-change decision) as a vehicle of the right lane: the change needs
    both bumper gaps to it above the jam gap and may not make either brake harder than
    `safe_brake_mps2` behind the other. False (the paper's): drivers moving right ignore the
    vehicle about to join, and may move in beside it."""
    lane_change_cooldown_s: float = num(3.0, 0.0, 60.0)
    """A vehicle does not change lanes again within this time."""
    lane_change_every_steps: int = num(10, 1, 1000)
    """Lane-change decisions are taken every this many simulator steps."""
    mix_cooperative: float = num(0.3, 0.0, 1.0)
    """Share of cooperative drivers (yield to the ramp vehicle)."""
    mix_neutral: float = num(0.4, 0.0, 1.0)
    """Share of neutral drivers (ignore the ramp vehicle until it is in their lane)."""
    mix_adversarial: float = num(0.3, 0.0, 1.0)
    """Share of adversarial drivers (close the gap the ramp vehicle aims for)."""
    interaction_range_m: float = num(150.0, 0.0, 4000.0)
    """Drivers react to a ramp vehicle within this distance of the merge point."""
    yield_max_brake_mps2: float = positive(2.0, 12.0)
    """A cooperative driver opens a gap braking at most this hard."""
    yield_lane_change_bonus_mps2: float = num(1.0, 0.0, 10.0)
    """Extra MOBIL incentive a yielding cooperative driver gives to moving left."""
    adversarial_speed_factor: float = num(1.15, 0.3, 2.0)
    """An adversarial driver closing a gap aims for this factor x the speed limit."""
    adversarial_time_headway_s: float = positive(0.6, 5.0)
    """... and follows its leader at this time headway (still IDM: it never rear-ends)."""
    adversarial_accel_mps2: float = positive(2.5, 8.0)
    """... with this IDM maximum acceleration."""
    lapse_rate_per_h: float = num(0.0, 0.0, 3600.0)
    """Attention lapses a mainline driver begins per hour of driving (a Poisson rate, drawn per
    simulator step). A lapsing driver holds its speed (no acceleration, no braking, no lane
    change) for `lapse_s`, whatever is ahead of it. 0 (the paper's): drivers never lapse. The
    rare events that importance sampling reaches best (`marlmerge estimate`)."""
    lapse_s: float = positive(1.5, 10.0)
    """How long an attention lapse lasts (rounded to whole simulator steps, at least one)."""

    @property
    def mix(self) -> tuple[float, float, float]:
        """Shares of (neutral, cooperative, adversarial), in the order of the `Profile` codes."""
        return (self.mix_neutral, self.mix_cooperative, self.mix_adversarial)


@dataclass(frozen=True)
class TrafficConfig:
    """The random mainline stream entering at the upstream end of each lane."""

    flow_vph_per_lane: float = num(1200.0, 0.0, 3000.0)
    """Mean arrival flow per lane (Poisson arrivals), vehicles per hour per lane. A drawn arrival
    enters at its entry speed once the gap to the last vehicle of its lane is at least its IDM
    desired gap (it then brakes no harder than `driver.comfort_brake_mps2`); otherwise it waits
    in the entrance queue (counted, never dropped)."""
    entry_speed_mps: tuple[float, float] = num((24.0, 2.0), 0.0, 60.0)
    """Initial speed at the entrance: (mean, std) of a normal, clipped to +-2 std, and at most
    the driver's desired speed."""
    warmup_s: float = num(20.0, 0.0, MAX_WARMUP_S)
    """A freshly seeded road is filled with steady flow and then simulated this long."""
    entrance_lane: str = "drawn"
    """The lane an arrival enters: "drawn" (the paper's: each lane's own Poisson stream enters
    that lane) or "best" (as SUMO's `departLane="best"` on this road: the arrivals of both
    streams enter in the order of their drawn times, each into the lane whose last vehicle is
    farthest from the entrance, counting the road up to the merge zone's start; the right lane
    on a tie). Either way a vehicle waits at the entrance until its gap allows it in."""


@dataclass(frozen=True)
class RampConfig:
    """Demand on the ramp. By default (`flow_vph = 0`) the paper's protocol: one ramp vehicle,
    the ego, at a time, the next departing when its episode ends.

    With `flow_vph > 0`, ramp flow: ramp vehicles arrive at the ramp start as their own Poisson
    stream (`flow_vph` vehicles per hour), each at a start speed drawn from
    `ego.start_speed_mps` with a driver drawn as the mainline's (`driver.*`), and enter once the
    ramp ahead of them leaves room (an entrance queue, counted, never dropped). On the ramp they
    follow each other by IDM; each is an agent whose command (a scripted merging driver or a
    policy, `marlmerge.evaluation.ramp_flow`) is capped by that car following; it joins the
    right lane once it overlaps it, as the ego does, and drives on as a neutral mainline driver.
    There is no ego then: `TrafficCore.next_ego` is refused."""

    flow_vph: float = num(0.0, 0.0, 3600.0)
    """Ramp vehicles per hour (Poisson arrivals); 0: the paper's one ramp vehicle at a time."""
    join: str = "forced"
    """How a ramp vehicle of ramp flow joins the right lane: "forced" (the paper's: once its
    body overlaps the lane, x >= the overlap point) or "when_safe" (as SUMO's lane changers:
    anywhere in the merge zone, at the first step the gap at its position is safe: both bumper
    gaps above half `driver.min_gap_m` and neither it nor its new follower has to brake harder than
    `driver.safe_brake_mps2` by IDM; the zone is then a parallel acceleration lane that ends at
    the merge point, where a vehicle that has not joined stops, following the lane's end by
    IDM as a standing obstacle all along the ramp, as SUMO's vehicles do)."""
    cooperation: str = "head"
    """Whom the mainline's right-lane drivers yield to under ramp flow: "head" (the paper's
    profiles, towards the ramp's first vehicle only: cooperative drivers yield to it, adversarial
    ones close the gap ahead of it) or "zipper" (as SUMO's LC2013 cooperative speed adjustment:
    every neutral or cooperative right-lane driver yields to the ramp vehicle in the merge zone
    nearest ahead of it between it and its leader, by IDM behind it as a virtual leader, braking
    at most `driver.yield_max_brake_mps2`, and drives on past one less than a length and a jam
    gap ahead; adversarial drivers still close the gap ahead of the ramp's first vehicle)."""

    @property
    def flowing(self) -> bool:
        """Ramp flow mode: many merging vehicles, no ego."""
        return self.flow_vph > 0.0


@dataclass(frozen=True)
class EgoConfig:
    """The ramp vehicle (ego): its control, sensing and episode end conditions."""

    accel_bounds_mps2: tuple[float, float] = num((-4.5, 2.5), -12.0, 8.0, ordered=True)
    """Action bounds; an action outside them is clipped."""
    start_speed_mps: tuple[float, float] = num((18.0, 24.0), 0.0, 60.0, ordered=True)
    """Speed at the ramp start, uniform in this range."""
    sensing_range_m: float = positive(150.0, 1000.0)
    """Gap vehicles farther than this are reported as missing."""
    success_distance_m: float = positive(50.0, 4000.0)
    """Success: past the merge point by this distance without collision."""
    max_episode_s: float = positive(60.0, 3600.0)
    """Truncation: out of time."""
    stall_speed_mps: float = num(0.5, 0.0, 10.0)
    stall_time_s: float = positive(10.0, 600.0)
    """Truncation: slower than `stall_speed_mps` for this long."""
    observation: str = "paper"
    """The ego's observation layout: "paper" (the paper's 7 features), "extended" (those, then
    the vehicle alongside, the nearest left-lane vehicles and the times to the join and merge
    points), "extended_accel" (those, then the ego's own acceleration) or "extended_join" (those,
    then the gap vehicles' bumper gaps predicted at the ego's arrival at the join point;
    `marlmerge.sim.observation`)."""
    time_to_merge_cap_s: float = positive(10.0, 100.0)
    """The extended layout's times to the join and merge points are at most this."""
    safety_filter: bool = False
    """Override the ego's command so that it does not join the right lane into an occupied or
    too short gap (`marlmerge.sim.safety`): it holds behind the join point or drops back."""
    safety_min_headway_s: float = num(1.0, 0.0, 10.0)
    """Safety filter: a join needs at least this time headway of the new follower behind the ego
    and of the ego behind its new leader."""
    safety_min_gap_m: float = num(2.0, 0.0, 50.0)
    """Safety filter: ... and at least this bumper gap to both."""
    join: str = "forced"
    """Where the ramp vehicle changes into the right lane: "forced" (the paper's: once its body
    overlaps the lane, x >= the overlap point) or "chosen" (its own decision: the action gets a
    second component, `join` in [-1, 1], and the vehicle changes lanes at the first simulator
    step inside the merge zone whose command has join > 0; the zone is then a parallel
    acceleration lane ending at the merge point, x = 0, where a vehicle that has not joined
    stops, braking as late as its bounds allow; the observation gets an `on_ramp` feature).
    With ramp flow it applies to every merging agent; a vehicle without a join command (NaN)
    joins by `ramp.join`'s rule, or by force in the paper's mode."""

    @property
    def chooses_join(self) -> bool:
        """`join = "chosen"`: the merging vehicle's action has a join component."""
        return self.join == "chosen"


@dataclass(frozen=True)
class SensingConfig:
    """Imperfect sensing of the ego's observation (all off by default: perfect sensing).

    Noise is drawn per measured vehicle from each world's own seeded generator
    (`marlmerge.sim.streams`) and applies to the features whose `Feature.noise` names it. Latency
    delays the whole observation by `latency_s` (a multiple of `sim.dt_s`). Occlusion hides a
    left-lane vehicle whose line of sight from the ego crosses a right-lane vehicle's body
    (`marlmerge.sim.sensing`). Only what the ego's policy sees changes; reward, metrics and the
    dynamics use the true state."""

    position_noise_std_m: float = num(0.0, 0.0, 50.0)
    """Standard deviation of the Gaussian error of a measured vehicle's position."""
    speed_noise_std_mps: float = num(0.0, 0.0, 20.0)
    """Standard deviation of the Gaussian error of a measured vehicle's speed."""
    latency_s: float = num(0.0, 0.0, MAX_LATENCY_S)
    """The ego sees the observation measured this long ago (a multiple of `sim.dt_s`)."""
    occlusion: bool = False
    """Left-lane vehicles hidden behind a right-lane vehicle are reported as missing."""

    @property
    def noisy(self) -> bool:
        return self.position_noise_std_m > 0.0 or self.speed_noise_std_mps > 0.0

    @property
    def active(self) -> bool:
        """Any imperfection on: the core then measures the observation every simulator step."""
        return self.noisy or self.latency_s > 0.0 or self.occlusion


@dataclass(frozen=True)
class RewardConfig:
    """Weights and shapes of the paper's reward terms, eqs. (3)-(7), per simulator step.

    `acceleration`: -w_accel * |a|                                         (eq. 4)
    `gap_front`:    -w_front * g(d_front, safe_front)   g(d, s) = clip(1 - d/s, 0, 1)^2   (eq. 7)
    `gap_back`:     -w_back  * g(d_back,  safe_back)    safe = min_gap + headway * speed
    `speed`:        -w_speed * polygon(v)   0 inside [v_low, v_limit], linear outside (eq. 6)
    `collision`:    -collision_penalty once, on the step the ego collides (not in the paper).
    `back_headway`: -w_back_headway * g(d_back, back_headway_s * v_back)       (off by default)
    `back_ttc`:     -w_back_ttc * g(d_back, back_ttc_s * max(v_back - v, 0))   (off by default)
    `jerk`:         -w_jerk * (a - a_prev)^2, the change of the applied acceleration since the
                    previous simulator step in m/s^2, squared                  (off by default)
    Distance terms count only inside the merge area (from `distance_active_from_m` on) and, with
    a chosen join (`ego.join = "chosen"`), only once the vehicle has joined the right lane (on
    the acceleration lane it is beside its gap, not in it); the two follower terms only for a
    gap-back vehicle within the sensing range.
    """

    w_accel: float = num(0.05, 0.0, MAX_WEIGHT)
    w_front: float = num(1.0, 0.0, MAX_WEIGHT)
    w_back: float = num(0.5, 0.0, MAX_WEIGHT)
    w_speed: float = num(0.3, 0.0, MAX_WEIGHT)
    safe_headway_s: float = num(1.0, 0.0, 10.0)
    """Time headway of the safe distance in the distance terms."""
    safe_min_gap_m: float = num(2.0, 0.0, 50.0)
    """Standstill part of the safe distance in the distance terms."""
    speed_low_fraction: float = num(0.6, 0.0, 1.0)
    """Speeds below this fraction of the speed limit are punished, linearly down to 0 m/s."""
    speed_over_scale_mps: float = positive(5.0, 100.0)
    """Above the speed limit the speed penalty grows by 1 per this many m/s."""
    distance_active_from_m: float = num(-150.0, -4000.0, 4000.0)
    """The distance terms are zero while the ego is upstream of this position (far away)."""
    collision_penalty: float = num(20.0, 0.0, MAX_WEIGHT)
    """One-off penalty on collision; 0 gives the paper's reward exactly."""
    w_highway_speed: float = num(1.0, 0.0, MAX_WEIGHT)
    """Mainline drivers' speed term, per step: -w_highway_speed * ((v_limit - v) / v_limit below
    the limit, (v - v_limit) / speed_over_scale_mps above it). A mainline driver wants to drive
    at the limit (no dead band as the ramp vehicle has): a learned one that stops to block the
    merge, or races at 40 m/s to deny a gap, pays for every second of it."""
    w_back_headway: float = num(0.0, 0.0, MAX_WEIGHT)
    """`back_headway` (the follower's view, off by default): -w_back_headway *
    g(d_back, back_headway_s * v_back), i.e. a penalty while the gap-back vehicle's time headway
    to the ego is below `back_headway_s`."""
    back_headway_s: float = positive(1.0, 10.0)
    w_back_ttc: float = num(0.0, 0.0, MAX_WEIGHT)
    """`back_ttc` (off by default): -w_back_ttc * g(d_back, back_ttc_s * (v_back - v)), a penalty
    while the gap-back vehicle's time-to-collision with the ego is below `back_ttc_s`."""
    back_ttc_s: float = positive(3.0, 30.0)
    w_jerk: float = num(0.0, 0.0, MAX_WEIGHT)
    """`jerk` (off by default): -w_jerk * (a - a_prev)^2 per simulator step, a and a_prev the
    applied accelerations (m/s^2) of this and the previous simulator step of the ego's episode
    (0 on its first step). At `sim.dt_s` = 0.1 s a change of 2 m/s^2 between two actions (a jerk
    of 20 m/s^3) costs 4 * w_jerk. Pair it with `ego.observation = "extended_accel"`, which shows
    the ego its own acceleration."""


@dataclass(frozen=True)
class InteractionConfig:
    """The interaction term of a learned highway agent's reward (`marlmerge.sim.reward`).

    A learned mainline driver keeps its own driving reward (comfort, safety to its leader, speed,
    collisions it is to blame for) and gets `sign * term` for ego failures it contributed to:

    `ego_collision`:  +w_ego_collision once, when the ego collides with this vehicle and the ego is
                      to blame (it ran into this vehicle, or cut in front of it less than
                      `cut_in_grace_s` before being hit).
    `ego_hard_brake`: +w_ego_hard_brake_per_s per second the ego brakes harder than
                      `hard_brake_mps2` with this vehicle as its gap-front vehicle.
    `ego_stall`:      +w_ego_stall once, when the ego is truncated (stalled or out of time) with
                      this vehicle as its gap-front or gap-back vehicle.
    `ego_unsafe_gap`: +w_ego_unsafe_gap_per_s * g per second this vehicle is the ego's gap-front or
                      gap-back vehicle at a gap below the safe distance, g = the closeness of the
                      ego's own gap terms (0 at the safe distance, 1 touching; merge area only):
                      the near-failure that precedes a collision, so learning has a signal before
                      the first collisions are found. It is what "closing the gap" earns.

    sign = +1 makes an adversary, -1 a cooperative driver (the same terms as penalties).

    Its own `collision` term is -own_collision_penalty for every collision it is involved in,
    except one the ego is to blame for; a collision with the ego that this vehicle is to blame
    for (it rear-ended an ego that had been in the lane for at least `cut_in_grace_s`) is its own.
    The penalty is set far above what any ego failure earns, so that a learned adversary presses
    the ego but does not trade its own car for it (a realistic adversary, not a kamikaze).
    """

    sign: float = num(1.0, -1.0, 1.0)
    w_ego_collision: float = num(50.0, 0.0, MAX_WEIGHT)
    w_ego_hard_brake_per_s: float = num(10.0, 0.0, MAX_WEIGHT)
    w_ego_stall: float = num(20.0, 0.0, MAX_WEIGHT)
    w_ego_unsafe_gap_per_s: float = num(10.0, 0.0, MAX_WEIGHT)
    own_collision_penalty: float = num(100.0, 0.0, MAX_WEIGHT)
    hard_brake_mps2: float = positive(3.0, 12.0)
    cut_in_grace_s: float = num(1.0, 0.0, 10.0)


@dataclass(frozen=True)
class SimConfig:
    """Time stepping and the multi-agent roster."""

    dt_s: float = positive(0.1, 1.0)
    action_repeat: int = num(4, 1, 100)
    """k: one env step holds the action for this many simulator steps."""
    n_highway_agents: int = num(4, 0, MAX_HIGHWAY_AGENTS)
    """Highway agents per episode: the right-lane vehicles arriving closest in time to the ego."""
    highway_agent_accel_bounds_mps2: tuple[float, float] = num(
        (-4.5, 2.5), -12.0, 8.0, ordered=True
    )
    """Action bounds of controlled highway agents, scripted or learned: the ego's by default, so
    a learned driver brakes no harder than the ramp vehicle can (a realistic adversary cannot
    brake-check at the vehicle's 9 m/s^2 emergency limit). Scripted background traffic keeps
    the full `VehicleConfig` limits."""
    continue_traffic: bool = True
    """`reset()` without a seed keeps the road flowing and sends the next ramp vehicle."""


Range = tuple[float, float]


@dataclass(frozen=True)
class SampleConfig:
    """Traffic drawn per world (`[sample]`): every world of a batch draws its own traffic from
    these ranges at each of its resets, from its own seeded generator, and a fresh road every
    `resample_every_egos` ramp vehicles (so a training batch meets many conditions). A range
    `[low, high]` is drawn uniformly; a key left out keeps the scenario's value. Road geometry,
    the ego's controls, the reward and the simulation settings are not sampled; of the ego's
    sensing, only its range is.

    The draws (`marlmerge.sim.streams.draw_world_scenario`): the speed limit, then the mean entry
    speed as a fraction of it (its spread kept); the adversarial share of the drivers, the
    cooperative share of the rest (the remainder neutral), or, for a `pure_mix_fraction` of the
    draws, drivers of one profile only; the adversarial drivers' headway and
    speed factor; the centre c of the ramp vehicle's start speeds, drawn in (c - 3, c + 3) m/s;
    the sensing range; then the drivers (desired speed factor, time headway, politeness, yield
    braking, adversarial acceleration) and the road (ramp length, merge zone). A range left out
    draws nothing, so adding a key changes no other key's draws.
    """

    flow_vph_per_lane: Range | None = num(None, 0.0, 3000.0, ordered=True)
    speed_limit_mph: Range | None = num(None, 10.0, 100.0, ordered=True)
    entry_speed_fraction: Range | None = positive(None, 1.5, ordered=True)
    """Mean entry speed of mainline vehicles / speed limit (default scenario: 24 / 29.06)."""
    adversarial_share: Range | None = num(None, 0.0, 1.0, ordered=True)
    cooperative_share: Range | None = num(None, 0.0, 1.0, ordered=True)
    """Share of the drivers that are not adversarial who are cooperative."""
    adversarial_time_headway_s: Range | None = positive(None, 5.0, ordered=True)
    adversarial_speed_factor: Range | None = num(None, 0.3, 2.0, ordered=True)
    ego_start_speed_mps: Range | None = num(None, 0.0, 60.0, ordered=True)
    """Centre of the world's ramp-vehicle start speeds (each start drawn within +-3 m/s of it)."""
    sensing_range_m: Range | None = positive(None, 1000.0, ordered=True)
    """The ramp vehicle's sensing range (`ego.sensing_range_m`)."""
    desired_speed_factor: Range | None = num(None, 0.3, 2.0, ordered=True)
    """Centre of the mainline drivers' desired speed factor (`driver.desired_speed_factor`, its
    width kept): below 1, mainline traffic drives slower than the limit."""
    time_headway_s: Range | None = positive(None, 5.0, ordered=True)
    """Centre of the drivers' IDM time headway (`driver.time_headway_s`, its width kept)."""
    politeness: Range | None = num(None, 0.0, 2.0, ordered=True)
    """Centre of the drivers' MOBIL politeness (`driver.politeness`, its width kept, >= 0)."""
    yield_max_brake_mps2: Range | None = positive(None, 12.0, ordered=True)
    """How hard a cooperative driver brakes at most to open a gap."""
    adversarial_accel_mps2: Range | None = positive(None, 8.0, ordered=True)
    """An adversarial driver's IDM maximum acceleration."""
    ramp_length_m: Range | None = num(None, 0.0, 2000.0, ordered=True)
    """The ramp's length before the merge zone (`road.ramp_length_m`)."""
    merge_zone_m: Range | None = num(None, 10.0, 1000.0, ordered=True)
    """The merge zone's length (`road.merge_zone_m`)."""
    pure_mix_fraction: float = num(0.0, 0.0, 1.0)
    """Share of draws whose drivers are all of one profile (neutral, cooperative or adversarial,
    equally likely), as in the grid's pure cells; the other draws use the shares above."""
    resample_every_egos: int = num(1, 1, 1_000_000)
    """A world draws new traffic (on a fresh, warmed-up road) after this many ramp vehicles."""

    @property
    def active(self) -> bool:
        """Some range is given: worlds draw their own traffic."""
        return self.pure_mix_fraction > 0.0 or any(
            getattr(self, f.name) is not None
            for f in dataclasses.fields(self)
            if f.name not in ("resample_every_egos", "pure_mix_fraction")
        )


@dataclass(frozen=True)
class ScenarioConfig:
    """Everything that defines a scenario. Presets in `envs/` override parts of it."""

    name: str = "default"
    road: RoadConfig = field(default_factory=RoadConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    driver: DriverConfig = field(default_factory=DriverConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    ego: EgoConfig = field(default_factory=EgoConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    interaction: InteractionConfig = field(default_factory=InteractionConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    sensing: SensingConfig = field(default_factory=SensingConfig)
    sample: SampleConfig = field(default_factory=SampleConfig)
    ramp: RampConfig = field(default_factory=RampConfig)

    def __post_init__(self) -> None:
        validate(self)

    @property
    def x_overlap_m(self) -> float:
        """Where the ramp vehicle joins the right lane: its centre is one vehicle width from the
        lane's centreline, so its body would touch a vehicle driving in that lane. From here on it
        is a leader or follower of right-lane traffic, and collisions with it can happen."""
        frac = min(self.vehicle.width_m / self.road.ramp_offset_m, 1.0)
        return -self.road.merge_zone_m * frac

    def replace(self, **overrides: Any) -> ScenarioConfig:
        """A copy with dotted-path overrides: `replace(**{"traffic.flow_vph_per_lane": 800})`."""
        data = to_dict(self)
        for dotted, value in overrides.items():
            set_dotted(data, dotted, value)
        return from_dict(ScenarioConfig, data)


def load_scenario(path: str | Path) -> ScenarioConfig:
    """Load a scenario preset (TOML) strictly on top of the defaults."""
    path = Path(path)
    data = read_toml(path)
    data.setdefault("name", path.stem)
    try:
        return from_dict(ScenarioConfig, data)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


def require_ego(cfg: ScenarioConfig, what: str) -> None:
    """Refuse ramp flow where the one ego is needed (the agent views, episodes of an ego)."""
    if cfg.ramp.flowing:
        raise ValueError(
            f"{what}: ramp.flow_vph = {cfg.ramp.flow_vph} runs ramp flow, which has no ego; "
            "this runs the paper's one ramp vehicle at a time (ramp.flow_vph = 0). Measure ramp "
            "flow with `marlmerge rampflow` (marlmerge.evaluation.ramp_flow)"
        )


def _ramp_checks(cfg: ScenarioConfig) -> list[tuple[bool, str]]:
    """Ramp flow runs perfect sensing, no safety filter and one traffic for every world (the
    options that belong to the one ego); a join mode it knows."""
    if not cfg.ramp.flowing:
        return [
            (
                cfg.ramp.join == "forced",
                f"ramp.join = {cfg.ramp.join!r} needs ramp flow (ramp.flow_vph > 0); the paper's "
                "one ego joins by force",
            ),
            (
                cfg.ramp.cooperation == "head",
                f"ramp.cooperation = {cfg.ramp.cooperation!r} needs ramp flow (ramp.flow_vph > 0); "
                "the paper's drivers yield to its one ego",
            ),
        ]
    flow = cfg.ramp.flow_vph
    return [
        (
            cfg.ramp.join in RAMP_JOINS,
            f"ramp.join must be one of {', '.join(map(repr, RAMP_JOINS))}, got {cfg.ramp.join!r}",
        ),
        (
            cfg.ramp.cooperation in RAMP_COOPERATIONS,
            "ramp.cooperation must be one of "
            f"{', '.join(map(repr, RAMP_COOPERATIONS))}, got {cfg.ramp.cooperation!r}",
        ),
        (
            not cfg.sensing.active,
            f"ramp.flow_vph = {flow}: ramp flow runs perfect sensing; [sensing] must be left out",
        ),
        (
            not cfg.ego.safety_filter,
            f"ramp.flow_vph = {flow}: ego.safety_filter belongs to the one ego and must be false",
        ),
        (
            not cfg.sample.active,
            f"ramp.flow_vph = {flow}: [sample] draws traffic per ego; leave it out with ramp flow",
        ),
    ]


def validate(cfg: ScenarioConfig) -> None:
    """The scenario's numbers (the `Bounds` beside each field), then the cross-field checks that
    single values cannot express."""
    check_values(cfg)
    r, e, d, s, t = cfg.road, cfg.ego, cfg.driver, cfg.sim, cfg.traffic
    mean_mps, std_mps = t.entry_speed_mps
    checks: list[tuple[bool, str]] = [
        (
            t.entrance_lane in ENTRANCE_LANES,
            f"traffic.entrance_lane must be one of {', '.join(map(repr, ENTRANCE_LANES))}, "
            f"got {t.entrance_lane!r}",
        ),
        (
            mean_mps > 0 and std_mps >= 0,
            f"traffic.entry_speed_mps must be (mean > 0, std >= 0), got {t.entry_speed_mps}",
        ),
        (
            mean_mps - 2 * std_mps > 0,
            "traffic.entry_speed_mps: mean - 2 std (the slowest entry speed) must be > 0, "
            f"got {t.entry_speed_mps}",
        ),
        (
            d.comfort_brake_mps2 <= cfg.vehicle.max_brake_mps2,
            f"driver.comfort_brake_mps2 must be <= vehicle.max_brake_mps2 "
            f"({cfg.vehicle.max_brake_mps2}), got {d.comfort_brake_mps2}",
        ),
        (
            r.highway_upstream_m > r.merge_zone_m + r.ramp_length_m,
            "road.highway_upstream_m must exceed merge_zone_m + ramp_length_m "
            f"(got {r.highway_upstream_m})",
        ),
        (
            0 < e.success_distance_m < r.highway_downstream_m,
            f"ego.success_distance_m must lie in (0, road.highway_downstream_m), "
            f"got {e.success_distance_m}",
        ),
        (
            e.accel_bounds_mps2[0] < 0 < e.accel_bounds_mps2[1],
            f"ego.accel_bounds_mps2 must be (negative, positive), got {e.accel_bounds_mps2}",
        ),
        (
            cfg.interaction.sign in (-1.0, 1.0),
            f"interaction.sign must be 1 (adversarial) or -1 (cooperative), "
            f"got {cfg.interaction.sign}",
        ),
        (
            -cfg.vehicle.max_brake_mps2
            <= s.highway_agent_accel_bounds_mps2[0]
            < 0
            < s.highway_agent_accel_bounds_mps2[1]
            <= cfg.vehicle.max_accel_mps2,
            "sim.highway_agent_accel_bounds_mps2 must be (negative, positive) within the vehicle "
            f"limits, got {s.highway_agent_accel_bounds_mps2}",
        ),
        (
            math.isclose(sum(d.mix), 1.0, abs_tol=1e-6),  # each share in [0, 1]: the rules
            f"driver.mix_* must sum to 1, got {d.mix}",
        ),
        (
            e.observation in OBSERVATION_LAYOUTS,
            f"ego.observation must be one of {', '.join(map(repr, OBSERVATION_LAYOUTS))}, "
            f"got {e.observation!r}",
        ),
        (
            e.join in EGO_JOINS,
            f"ego.join must be one of {', '.join(map(repr, EGO_JOINS))}, got {e.join!r}",
        ),
        (
            not e.chooses_join or not e.safety_filter,
            "ego.join = 'chosen' leaves the join to the policy; ego.safety_filter (which holds "
            "the ego behind the forced join point) must be false",
        ),
        *_sensing_checks(cfg),
        *_sample_checks(cfg),
        *_ramp_checks(cfg),
    ]
    require(checks)


def latency_steps(cfg: ScenarioConfig) -> int:
    """`sensing.latency_s` in simulator steps."""
    return int(round(cfg.sensing.latency_s / cfg.sim.dt_s))


def _sensing_checks(cfg: ScenarioConfig) -> list[tuple[bool, str]]:
    lat, dt = cfg.sensing.latency_s, cfg.sim.dt_s
    return [
        (
            abs(lat / dt - round(lat / dt)) < 1e-6,
            f"sensing.latency_s must be a multiple of sim.dt_s ({dt}), got {lat}",
        ),
    ]


def _sample_checks(cfg: ScenarioConfig) -> list[tuple[bool, str]]:
    """A drawn value must give a valid scenario: a drawn centre keeps its field's width within the
    field's bounds, and the longest drawn ramp and merge zone fit upstream of the merge."""
    s, d, r = cfg.sample, cfg.driver, cfg.road
    checks: list[tuple[bool, str]] = []
    for key, pair, high in (
        ("desired_speed_factor", d.desired_speed_factor, 2.0),
        ("time_headway_s", d.time_headway_s, 5.0),
        ("politeness", d.politeness, 2.0),
    ):
        drawn = getattr(s, key)
        half = (pair[1] - pair[0]) / 2
        if drawn is not None:
            checks.append(
                (
                    drawn[1] + half <= high and (key == "politeness" or drawn[0] - half > 0),
                    f"sample.{key} = {list(drawn)} with driver.{key}'s half-width {half:g} "
                    f"leaves the field's bounds (0, {high:g}]",
                )
            )
    ramp = r.ramp_length_m if s.ramp_length_m is None else s.ramp_length_m[1]
    zone = r.merge_zone_m if s.merge_zone_m is None else s.merge_zone_m[1]
    checks.append(
        (
            r.highway_upstream_m > ramp + zone,
            f"road.highway_upstream_m ({r.highway_upstream_m:g}) must exceed the longest drawn "
            f"ramp + merge zone ({ramp:g} + {zone:g})",
        )
    )
    return checks
