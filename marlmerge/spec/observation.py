"""The one definition of every observation layout: feature order, units and scaling.

An observation is `raw / scale`, float32. The simulator's kernel (`marlmerge.sim.kernels`) writes
the features in the order of these tables; every view returns them as they come, so a layout is
defined here and computed in one place (a test checks the kernel against these tables).

Missing gap vehicles (none in the right lane within the sensing range) are encoded as a virtual
vehicle at the edge of the sensing range (`x_ego +- sensing_range_m`) driving at the speed limit.
A missing leader or follower of a mainline vehicle is encoded as a gap equal to the sensing range
and a speed equal to the vehicle's own speed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

SPEED_SCALE_MPS = 30.0
POSITION_SCALE_M = 100.0


@dataclass(frozen=True)
class Feature:
    name: str
    unit: str
    scale: float
    doc: str


EGO_FEATURES: tuple[Feature, ...] = (
    Feature("ego_speed", "m/s", SPEED_SCALE_MPS, "speed of the ramp vehicle (v_ev)"),
    Feature(
        "ego_position",
        "m",
        POSITION_SCALE_M,
        "ramp vehicle position along its path, 0 at the merge point (p_ev)",
    ),
    Feature("front_speed", "m/s", SPEED_SCALE_MPS, "speed of the gap-front vehicle (v_gfv)"),
    Feature("front_position", "m", POSITION_SCALE_M, "position of the gap-front vehicle (p_gfv)"),
    Feature("back_speed", "m/s", SPEED_SCALE_MPS, "speed of the gap-back vehicle (v_gbv)"),
    Feature("back_position", "m", POSITION_SCALE_M, "position of the gap-back vehicle (p_gbv)"),
    Feature("speed_limit", "m/s", SPEED_SCALE_MPS, "posted speed limit"),
)
"""The paper's state s = (v_ev, p_ev, v_gfv, p_gfv, v_gbv, p_gbv) plus the speed limit."""

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
HIGHWAY_SCALE = np.array([f.scale for f in HIGHWAY_FEATURES])


def feature_index(features: tuple[Feature, ...], name: str) -> int:
    return [f.name for f in features].index(name)
