"""The one definition of every observation layout: feature order, units and scaling.

An observation is `raw / scale`, float32. The simulator's kernel (`marlmerge.sim.kernels`) writes
the features in the order of these tables; every view returns them as they come, so a layout is
defined here and computed in one place (a test checks the kernel against these tables).

Missing gap vehicles (none in the right lane within the sensing range) are encoded as a virtual
vehicle at the edge of the sensing range (`x_ego +- sensing_range_m`) driving at the speed limit.
A missing leader or follower of a mainline vehicle is encoded as a gap equal to the sensing range
and a speed equal to the vehicle's own speed.

The ego has four layouts, chosen by `ego.observation` (`ego_features(cfg)`): `"paper"`
(`EGO_FEATURES`, the paper's state), `"extended"` (`EGO_EXTENDED_FEATURES`: the paper's state
followed by the right-lane vehicle alongside the ego, the nearest left-lane vehicles and the time
to the join and merge points), `"extended_accel"` (the extended layout, then the ego's own
acceleration) and `"extended_join"` (that, then the gap vehicles' bumper gaps predicted at the
ego's arrival at the join point). With `ego.join = "chosen"` every layout ends with `on_ramp`
(`ON_RAMP_FEATURE`), which an agent choosing its join needs to tell joined from not joined.
Every layout begins with the paper's seven features, so a reader of those
(`marlmerge.policies`: gap acceptance, the scripted rules) works with any. In the extended layout
a missing vehicle (none alongside, none in the left lane within the sensing range, or hidden by
occlusion) is the same virtual vehicle: dx = +sensing range (ahead, alongside) or -sensing range
(behind), at the speed limit, overlap 0.

`Feature.noise` names the measurement noise of `[sensing]` that applies to a feature
(`"position"`: `sensing.position_noise_std_m`, `"speed"`: `sensing.speed_noise_std_mps`): the
positions and speeds of other vehicles, never the ego's own motion or the road. Virtual (missing)
vehicles carry no noise. Highway agents observe without noise, latency or occlusion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from marlmerge.config import OBSERVATION_LAYOUTS, ScenarioConfig

SPEED_SCALE_MPS = 30.0
POSITION_SCALE_M = 100.0
TIME_SCALE_S = 10.0
ACCEL_SCALE_MPS2 = 5.0


@dataclass(frozen=True)
class Feature:
    name: str
    unit: str
    scale: float
    doc: str
    noise: str = ""
    """Measurement noise of `[sensing]` that applies: "position", "speed" or "" (none)."""


EGO_FEATURES: tuple[Feature, ...] = (
    Feature("ego_speed", "m/s", SPEED_SCALE_MPS, "speed of the ramp vehicle (v_ev)"),
    Feature(
        "ego_position",
        "m",
        POSITION_SCALE_M,
        "ramp vehicle position along its path, 0 at the merge point (p_ev)",
    ),
    Feature(
        "front_speed", "m/s", SPEED_SCALE_MPS, "speed of the gap-front vehicle (v_gfv)", "speed"
    ),
    Feature(
        "front_position",
        "m",
        POSITION_SCALE_M,
        "position of the gap-front vehicle (p_gfv)",
        "position",
    ),
    Feature("back_speed", "m/s", SPEED_SCALE_MPS, "speed of the gap-back vehicle (v_gbv)", "speed"),
    Feature(
        "back_position",
        "m",
        POSITION_SCALE_M,
        "position of the gap-back vehicle (p_gbv)",
        "position",
    ),
    Feature("speed_limit", "m/s", SPEED_SCALE_MPS, "posted speed limit"),
)
"""The paper's state s = (v_ev, p_ev, v_gfv, p_gfv, v_gbv, p_gbv) plus the speed limit."""

EGO_EXTRA_FEATURES: tuple[Feature, ...] = (
    Feature(
        "side_dx",
        "m",
        POSITION_SCALE_M,
        "position of the right-lane vehicle alongside the ego (its body overlaps the ego's "
        "longitudinally) minus the ego's; none: +sensing range",
        "position",
    ),
    Feature(
        "side_speed", "m/s", SPEED_SCALE_MPS, "speed of that vehicle; none: speed limit", "speed"
    ),
    Feature(
        "side_overlap",
        "-",
        1.0,
        "overlap of its body with the ego's as a fraction of the vehicle length, from the "
        "reported side_dx: 1 exactly alongside, 0 none",
    ),
    Feature(
        "left_front_dx",
        "m",
        POSITION_SCALE_M,
        "position of the nearest left-lane vehicle at or ahead of the ego minus the ego's; none, "
        "or hidden (occlusion): +sensing range",
        "position",
    ),
    Feature("left_front_speed", "m/s", SPEED_SCALE_MPS, "its speed; none: speed limit", "speed"),
    Feature(
        "left_back_dx",
        "m",
        POSITION_SCALE_M,
        "position of the nearest left-lane vehicle behind the ego minus the ego's (negative); "
        "none, or hidden (occlusion): -sensing range",
        "position",
    ),
    Feature("left_back_speed", "m/s", SPEED_SCALE_MPS, "its speed; none: speed limit", "speed"),
    Feature(
        "time_to_join",
        "s",
        TIME_SCALE_S,
        "time until the ego reaches the join point (`x_overlap_m`) at its current speed; 0 once "
        "there; at most `ego.time_to_merge_cap_s` (also when stopped)",
    ),
    Feature(
        "time_to_merge",
        "s",
        TIME_SCALE_S,
        "time until the ego reaches the merge point (x = 0, the end of the merge zone) at its "
        "current speed; 0 once past; at most `ego.time_to_merge_cap_s`",
    ),
)
"""What the extended layout adds after the paper's state."""
EGO_EXTENDED_FEATURES: tuple[Feature, ...] = EGO_FEATURES + EGO_EXTRA_FEATURES
"""`ego.observation = "extended"`: the paper's state, then `EGO_EXTRA_FEATURES`."""
EGO_ACCEL_FEATURE = Feature(
    "ego_accel",
    "m/s^2",
    ACCEL_SCALE_MPS2,
    "acceleration the ramp vehicle applied in the last simulator step (0 before its first)",
)
EGO_EXTENDED_ACCEL_FEATURES: tuple[Feature, ...] = EGO_EXTENDED_FEATURES + (EGO_ACCEL_FEATURE,)
"""`ego.observation = "extended_accel"`: the extended layout, then the ego's own acceleration
(what a policy needs to see to keep the `jerk` reward term low)."""
JOIN_GAP_FEATURES: tuple[Feature, ...] = (
    Feature(
        "lead_gap_at_join",
        "m",
        POSITION_SCALE_M,
        "bumper gap from the ego to the gap-front vehicle when the ego reaches the join point, "
        "both holding their speeds: (front_position - ego_position) + (front_speed - ego_speed) "
        "x time_to_join - vehicle length, within +-sensing range; negative: their bodies would "
        "overlap there; none: +sensing range",
        "position",
    ),
    Feature(
        "lag_gap_at_join",
        "m",
        POSITION_SCALE_M,
        "bumper gap from the gap-back vehicle to the ego at the same moment: (ego_position - "
        "back_position) + (ego_speed - back_speed) x time_to_join - vehicle length, within "
        "+-sensing range; none: +sensing range",
        "position",
    ),
)
"""What `"extended_join"` adds: the paper's gap, extrapolated to the join (what gap acceptance
tests, `marlmerge.policies.gap_acceptance`, at the ego's current speed)."""
EGO_EXTENDED_JOIN_FEATURES: tuple[Feature, ...] = EGO_EXTENDED_ACCEL_FEATURES + JOIN_GAP_FEATURES
"""`ego.observation = "extended_join"`: the extended layout with the ego's acceleration, then
`JOIN_GAP_FEATURES`."""
EGO_LAYOUTS: dict[str, tuple[Feature, ...]] = {
    "paper": EGO_FEATURES,
    "extended": EGO_EXTENDED_FEATURES,
    "extended_accel": EGO_EXTENDED_ACCEL_FEATURES,
    "extended_join": EGO_EXTENDED_JOIN_FEATURES,
}
"""The ego's layouts by the name `ego.observation` takes."""
assert tuple(EGO_LAYOUTS) == OBSERVATION_LAYOUTS

HIGHWAY_FEATURES: tuple[Feature, ...] = (
    Feature("speed", "m/s", SPEED_SCALE_MPS, "own speed"),
    Feature("lane", "-", 1.0, "own lane: 0 right, 1 left"),
    Feature("leader_gap", "m", POSITION_SCALE_M, "bumper gap to the own-lane leader"),
    Feature("leader_speed", "m/s", SPEED_SCALE_MPS, "speed of the own-lane leader"),
    Feature("follower_gap", "m", POSITION_SCALE_M, "bumper gap to the own-lane follower"),
    Feature("follower_speed", "m/s", SPEED_SCALE_MPS, "speed of the own-lane follower"),
    Feature("ego_dx", "m", POSITION_SCALE_M, "ramp vehicle position minus own position"),
    Feature("ego_speed", "m/s", SPEED_SCALE_MPS, "speed of the ramp vehicle"),
    Feature(
        "ego_to_merge",
        "m",
        POSITION_SCALE_M,
        "distance the ramp vehicle still has to the merge point (negative once past it)",
    ),
    Feature("ego_in_lane", "-", 1.0, "1 once the ramp vehicle overlaps the right lane"),
    Feature("ego_present", "-", 1.0, "1 while a ramp vehicle is on the road"),
    Feature("speed_limit", "m/s", SPEED_SCALE_MPS, "posted speed limit"),
)
"""What a mainline driver needs: own motion, own-lane neighbours, the ramp vehicle."""

EGO_SCALE = np.array([f.scale for f in EGO_FEATURES])
"""Scales of the paper's features: the first `len(EGO_FEATURES)` columns of every ego layout."""
HIGHWAY_SCALE = np.array([f.scale for f in HIGHWAY_FEATURES])


ON_RAMP_FEATURE = Feature(
    "on_ramp",
    "-",
    1.0,
    "1 while the ramp vehicle is still on the ramp or the acceleration lane, 0 once it has "
    'joined the right lane (`ego.join = "chosen"` only: then it follows every layout)',
)


def ego_layout(observation: str, chooses_join: bool = False) -> tuple[Feature, ...]:
    """The features of the ego layout named `observation` (`EGO_LAYOUTS`), then `on_ramp` when
    the vehicle chooses its join."""
    return EGO_LAYOUTS[observation] + ((ON_RAMP_FEATURE,) if chooses_join else ())


def ego_features(cfg: ScenarioConfig) -> tuple[Feature, ...]:
    """The ego's observation layout of a scenario (`ego.observation`, then `on_ramp` with
    `ego.join = "chosen"`)."""
    return ego_layout(cfg.ego.observation, cfg.ego.chooses_join)


def ramp_agent_features(cfg: ScenarioConfig) -> tuple[Feature, ...]:
    """What a ramp-flow agent sees: the ego's layout (`ego_features`), measured from the agent
    with perfect sensing and no occlusion."""
    return ego_features(cfg)


def ego_obs_size(cfg: ScenarioConfig) -> int:
    """Length of the ego's observation vector in a scenario: size views and networks by this."""
    return len(ego_features(cfg))


def feature_index(features: tuple[Feature, ...], name: str) -> int:
    return [f.name for f in features].index(name)


LEFT_LANE_FEATURES = ("left_front_dx", "left_front_speed", "left_back_dx", "left_back_speed")
"""The nearest left-lane vehicles ahead and behind, in the extended layouts."""


def shows_left_lane(cfg: ScenarioConfig) -> bool:
    """Whether the ego's observation in a scenario has `LEFT_LANE_FEATURES` (not the paper's)."""
    return LEFT_LANE_FEATURES[0] in {f.name for f in ego_features(cfg)}
