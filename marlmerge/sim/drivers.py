"""Driver models, written once: IDM car following, the entrance's safe speed and the three
interaction profiles.

Each model is a scalar function compiled with Numba (`njit`), called by the simulator's kernels
for every vehicle and, through the array wrappers at the bottom (`idm_accel`, `profile_accel`),
by the scripted policies that act through the agent interface. So the simulator and a scripted
agent share one definition of each behaviour. With `NUMBA_DISABLE_JIT=1` the same code runs as
plain Python.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from marlmerge.config import DriverConfig, VehicleConfig
from marlmerge.sim.jit import kernel
from marlmerge.sim.layout import ADVERSARIAL, COOPERATIVE, NEUTRAL

MIN_GAP_FOR_IDM_M = 0.1
"""Gaps are floored here inside IDM so a touching leader gives a large finite braking demand."""
PREDICTION_HORIZON_S = 5.0
"""How far ahead a mainline driver predicts whether the ramp vehicle will merge ahead of it."""


class Profile(IntEnum):
    """How a mainline driver treats the ramp vehicle."""

    NEUTRAL = NEUTRAL
    """Ignores the ramp vehicle until it is in its lane."""
    COOPERATIVE = COOPERATIVE
    """Opens a gap for a ramp vehicle that would merge ahead of it: brakes gently or moves left."""
    ADVERSARIAL = ADVERSARIAL
    """Speeds up to close the gap a ramp vehicle aims for, still following its own leader by IDM."""


@kernel(inline=True)
def idm(
    v_mps: float,
    gap_m: float,
    v_lead_mps: float,
    v0_mps: float,
    headway_s: float,
    a_mps2: float,
    b_mps2: float,
    s0_m: float,
    delta: float,
) -> float:
    """Intelligent Driver Model acceleration (Treiber et al. 2000), m/s^2.

    a_IDM = a [1 - (v/v0)^delta - (s*/s)^2],  s* = s0 + max(0, v T + v dv / (2 sqrt(a b))),
    with dv = v - v_lead and s the bumper-to-bumper gap (inf: no leader).
    """
    ratio = v_mps / v0_mps
    if delta == 4.0:
        sq = ratio * ratio
        free = 1.0 - sq * sq
    else:
        free = 1.0 - ratio**delta
    dyn = v_mps * headway_s + v_mps * (v_mps - v_lead_mps) / (2.0 * math.sqrt(a_mps2 * b_mps2))
    s_star = s0_m + max(dyn, 0.0)
    inter = s_star / max(gap_m, MIN_GAP_FOR_IDM_M)
    return a_mps2 * (free - inter * inter)


def idm_equilibrium_gap_m(
    v_mps: float, v0_mps: float, headway_s: float, s0_m: float, delta: float = 4.0
) -> float:
    """Bumper gap at which IDM holds `v_mps` behind a leader at the same speed (closed form)."""
    return (s0_m + v_mps * headway_s) / math.sqrt(1.0 - (v_mps / v0_mps) ** delta)


@kernel(inline=True)
def desired_gap_m(
    v_mps: float, v_lead_mps: float, headway_s: float, a_mps2: float, b_mps2: float, s0_m: float
) -> float:
    """IDM's desired gap s* = s0 + max(0, v T + v (v - v_lead) / (2 sqrt(a b)))."""
    dyn = v_mps * headway_s + v_mps * (v_mps - v_lead_mps) / (2.0 * math.sqrt(a_mps2 * b_mps2))
    return s0_m + max(dyn, 0.0)


@kernel
def entry_speed(
    v_wanted_mps: float,
    gap_m: float,
    v_lead_mps: float,
    headway_s: float,
    a_mps2: float,
    b_mps2: float,
    s0_m: float,
) -> float:
    """The speed at which a vehicle may enter `gap_m` behind a leader driving `v_lead_mps`, or -1
    if it must wait: its drawn speed `v_wanted_mps` once the gap is at least its IDM desired gap
    s* at that speed, as SUMO inserts IDM vehicles with a given departure speed. At s*, IDM
    brakes at most a (v/v0)^delta (entry speeds are at most v0, so at most a), never harder
    than the comfortable deceleration b. Entering slower instead (at a speed that is safe now)
    would let a queue creep in at walking pace and fill the road far denser than SUMO does."""
    if gap_m >= desired_gap_m(v_wanted_mps, v_lead_mps, headway_s, a_mps2, b_mps2, s0_m):
        return v_wanted_mps
    return -1.0


@kernel(inline=True)
def ego_merges_ahead(
    ego_dx_m: float,
    ego_v_mps: float,
    ego_to_overlap_m: float,
    v_mps: float,
    range_m: float,
) -> bool:
    """A pending ramp vehicle near the merge is predicted to arrive ahead of this driver: its
    relative position after min(time for the ego to reach the overlap point, horizon) at current
    speeds is positive, and it is within `range_m` of the driver and of the merge.

    ego_dx_m: the ramp vehicle's position minus the driver's (both on the common x axis);
    ego_to_overlap_m: how far the ramp vehicle still has to go until it overlaps the right lane.
    """
    if abs(ego_dx_m) >= range_m or ego_to_overlap_m >= range_m:
        return False
    t_ego = min(max(ego_to_overlap_m, 0.0) / max(ego_v_mps, 1.0), PREDICTION_HORIZON_S)
    return ego_dx_m + (ego_v_mps - v_mps) * t_ego > 0.0


@kernel(inline=True)
def profile_accel(
    profile: int,
    v_mps: float,
    gap_m: float,
    v_lead_mps: float,
    v0_mps: float,
    headway_s: float,
    in_right_lane: bool,
    ego_pending: bool,
    ego_dx_m: float,
    ego_v_mps: float,
    ego_to_overlap_m: float,
    p_a: float,
    p_b: float,
    p_s0: float,
    p_delta: float,
    range_m: float,
    yield_max_brake_mps2: float,
    length_m: float,
    adv_v0_mps: float,
    adv_headway_s: float,
    adv_accel_mps2: float,
) -> tuple[float, bool]:
    """A mainline driver's longitudinal acceleration by profile, and whether it is yielding.

    - every profile follows its own-lane leader by IDM (the ramp vehicle is a leader once it is in
      the right lane, through `gap_m`);
    - a cooperative driver with a ramp vehicle predicted ahead also follows the ramp vehicle's
      projection as a virtual leader, braking at most `yield_max_brake_mps2` for it;
    - an adversarial driver in that situation raises its desired speed and shortens its headway to
      close the gap ahead of it, still by IDM towards its real leader, so it never rear-ends it.
    """
    base = idm(v_mps, gap_m, v_lead_mps, v0_mps, headway_s, p_a, p_b, p_s0, p_delta)
    if not (ego_pending and in_right_lane) or profile == NEUTRAL:
        return base, False
    if not ego_merges_ahead(ego_dx_m, ego_v_mps, ego_to_overlap_m, v_mps, range_m):
        return base, False
    if profile == COOPERATIVE:
        virtual_gap = max(ego_dx_m - length_m, MIN_GAP_FOR_IDM_M)
        a_yield = idm(v_mps, virtual_gap, ego_v_mps, v0_mps, headway_s, p_a, p_b, p_s0, p_delta)
        return min(base, max(a_yield, -yield_max_brake_mps2)), True
    a_close = idm(
        v_mps, gap_m, v_lead_mps, adv_v0_mps, adv_headway_s, adv_accel_mps2, p_b, p_s0, p_delta
    )
    return a_close, False


# ----------------------------------------------------------------------------------------------
# Array wrappers for code that acts through the agent interface (policies, baselines, tests)
# ----------------------------------------------------------------------------------------------


@kernel
def _idm_many(v, gap, v_lead, v0, headway, a, b, s0, delta, out):  # noqa: ANN001 - flat arrays
    for i in range(out.size):
        out[i] = idm(v[i], gap[i], v_lead[i], v0[i], headway[i], a[i], b[i], s0[i], delta[i])


def idm_accel(
    v_mps: np.ndarray | float,
    gap_m: np.ndarray | float,
    v_lead_mps: np.ndarray | float,
    v0_mps: np.ndarray | float,
    headway_s: np.ndarray | float,
    a_mps2: np.ndarray | float,
    b_mps2: np.ndarray | float,
    s0_m: np.ndarray | float,
    delta: np.ndarray | float = 4.0,
) -> np.ndarray:
    """`idm` over arrays of any common broadcast shape (the same compiled function)."""
    values = (v_mps, gap_m, v_lead_mps, v0_mps, headway_s, a_mps2, b_mps2, s0_m, delta)
    args = np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in values))
    flat = [np.array(x).ravel() for x in args]
    out = np.empty(flat[0].size)
    _idm_many(*flat, out)
    return out.reshape(args[0].shape)


@dataclass(frozen=True)
class InteractionView:
    """What a mainline driver sees of the ramp vehicle, arrays broadcastable to the drivers.

    `ego_dx_m` is the ramp vehicle's position minus the driver's, on the common x axis (the ramp
    vehicle projected onto the highway); `ego_to_overlap_m` is how far it still has to go until it
    overlaps the right lane; `ego_pending` says a ramp vehicle exists and is not yet in the lane.
    """

    ego_dx_m: np.ndarray
    ego_v_mps: np.ndarray
    ego_to_overlap_m: np.ndarray
    ego_pending: np.ndarray


@kernel
def _profile_many(prof, v, gap, vl, v0, hw, right, pend, dx, ev, to_ov, p, acc, yld):  # noqa: ANN001
    for i in range(acc.size):
        acc[i], yld[i] = profile_accel(
            prof[i], v[i], gap[i], vl[i], v0[i], hw[i], right[i], pend[i], dx[i], ev[i], to_ov[i],
            p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8], p[9],
        )  # fmt: skip


def profile_accel_array(
    profile: np.ndarray,
    v_mps: np.ndarray,
    gap_m: np.ndarray,
    v_lead_mps: np.ndarray,
    v0_mps: np.ndarray | float,
    headway_s: np.ndarray | float,
    in_right_lane: np.ndarray,
    view: InteractionView,
    driver: DriverConfig,
    vehicle: VehicleConfig,
    speed_limit_mps: float,
) -> tuple[np.ndarray, np.ndarray]:
    """`profile_accel` over arrays of any common broadcast shape: (acceleration, yielding)."""
    floats = np.broadcast_arrays(
        *(
            np.asarray(x, dtype=np.float64)
            for x in (
                v_mps,
                gap_m,
                v_lead_mps,
                v0_mps,
                headway_s,
                view.ego_dx_m,
                view.ego_v_mps,
                view.ego_to_overlap_m,
            )
        ),
        np.asarray(profile, dtype=np.int64),
        np.asarray(in_right_lane, dtype=np.bool_),
        np.asarray(view.ego_pending, dtype=np.bool_),
    )
    shape = floats[0].shape
    v, gap, vl, v0, hw, dx, ev, to_ov, prof, right, pend = (np.array(x).ravel() for x in floats)
    d = driver
    params = np.array(
        [
            d.accel_mps2,
            d.comfort_brake_mps2,
            d.min_gap_m,
            d.delta,
            d.interaction_range_m,
            d.yield_max_brake_mps2,
            vehicle.length_m,
            d.adversarial_speed_factor * speed_limit_mps,
            d.adversarial_time_headway_s,
            d.adversarial_accel_mps2,
        ]
    )
    acc = np.empty(v.size)
    yld = np.empty(v.size, dtype=np.bool_)
    _profile_many(prof, v, gap, vl, v0, hw, right, pend, dx, ev, to_ov, params, acc, yld)
    return acc.reshape(shape), yld.reshape(shape)
