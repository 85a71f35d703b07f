"""Driver models as pure vectorised functions: IDM car following and the three interaction profiles.

Every function takes NumPy arrays of any common broadcast shape (the core passes `[B, N]`, a
scripted policy passes `[n_agents]`) and returns arrays of that shape. Nothing here holds state, so
the simulator core and the scripted highway policies share one definition of each behaviour.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from marlmerge.config import DriverConfig, VehicleConfig

MIN_GAP_FOR_IDM_M = 0.1
"""Gaps are floored here inside IDM so a touching leader gives a large finite braking demand."""


class Profile(IntEnum):
    """How a mainline driver treats the ramp vehicle."""

    NEUTRAL = 0
    """Ignores the ramp vehicle until it is in its lane."""
    COOPERATIVE = 1
    """Opens a gap for a ramp vehicle that would merge ahead of it: brakes gently or moves left."""
    ADVERSARIAL = 2
    """Speeds up to close the gap a ramp vehicle aims for, still following its own leader by IDM."""


_COOPERATIVE = int(Profile.COOPERATIVE)  # plain ints: comparing arrays with an IntEnum is slow
_ADVERSARIAL = int(Profile.ADVERSARIAL)


def idm_accel(
    v_mps: np.ndarray,
    gap_m: np.ndarray,
    v_lead_mps: np.ndarray,
    v0_mps: np.ndarray | float,
    headway_s: np.ndarray | float,
    a_mps2: np.ndarray | float,
    b_mps2: np.ndarray | float,
    s0_m: float,
    delta: float = 4.0,
) -> np.ndarray:
    """Intelligent Driver Model acceleration (Treiber et al. 2000).

    a_IDM = a [1 - (v/v0)^delta - (s*/s)^2],  s* = s0 + max(0, v T + v dv / (2 sqrt(a b))),
    with dv = v - v_lead and s the bumper-to-bumper gap. A missing leader is `gap_m = inf`.
    """
    ratio = v_mps / v0_mps
    if delta == 4.0:
        sq = ratio * ratio
        free = 1.0 - sq * sq
    else:
        free = 1.0 - np.power(ratio, delta)
    dyn = v_mps * headway_s + v_mps * (v_mps - v_lead_mps) / (2.0 * np.sqrt(a_mps2 * b_mps2))
    s_star = s0_m + np.maximum(dyn, 0.0)
    inter = s_star / np.maximum(gap_m, MIN_GAP_FOR_IDM_M)
    return a_mps2 * (free - inter * inter)


def idm_equilibrium_gap_m(
    v_mps: float, v0_mps: float, headway_s: float, s0_m: float, delta: float = 4.0
) -> float:
    """Bumper gap at which IDM holds `v_mps` behind a leader at the same speed (closed form)."""
    return (s0_m + v_mps * headway_s) / np.sqrt(1.0 - (v_mps / v0_mps) ** delta)


@dataclass(frozen=True)
class InteractionView:
    """What a mainline driver sees of the ramp vehicle, each array broadcastable to the drivers.

    `ego_dx_m` is the ramp vehicle's position minus the driver's, both on the common x axis (the
    ramp vehicle projected onto the highway); `ego_to_overlap_m` is how far the ramp vehicle still
    has to go until it overlaps the right lane; `ego_pending` says a ramp vehicle exists and is not
    yet in the right lane.
    """

    ego_dx_m: np.ndarray
    ego_v_mps: np.ndarray
    ego_to_overlap_m: np.ndarray
    ego_pending: np.ndarray


def ego_would_merge_ahead(
    view: InteractionView,
    v_mps: np.ndarray,
    in_right_lane: np.ndarray,
    range_m: float,
    horizon_s: float = 5.0,
) -> np.ndarray:
    """True where a pending ramp vehicle near the merge is predicted to arrive ahead of the driver.

    Prediction: relative position after min(time for the ego to reach the overlap point, horizon)
    at current speeds is positive, and the ego is within `range_m` of the driver and of the merge.
    """
    t_ego = np.minimum(
        np.maximum(view.ego_to_overlap_m, 0.0) / np.maximum(view.ego_v_mps, 1.0), horizon_s
    )
    dx_pred = view.ego_dx_m + (view.ego_v_mps - v_mps) * t_ego
    if not view.ego_pending.any():
        return np.zeros(np.broadcast(view.ego_dx_m, in_right_lane).shape, dtype=bool)
    return (
        view.ego_pending
        & in_right_lane
        & (dx_pred > 0.0)
        & (np.abs(view.ego_dx_m) < range_m)
        & (view.ego_to_overlap_m < range_m)
    )


def profile_accel(
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
    """Longitudinal acceleration of mainline drivers by profile, and where they are yielding.

    - every profile follows its own-lane leader by IDM (the ramp vehicle is a leader once it is in
      the right lane, through `gap_m`);
    - a cooperative driver with a ramp vehicle predicted ahead also follows the ramp vehicle's
      projection as a virtual leader, braking at most `yield_max_brake_mps2` for it;
    - an adversarial driver in that situation raises its desired speed and shortens its headway to
      close the gap ahead of it, still by IDM towards its real leader, so it never rear-ends it.

    Returns (acceleration [shape], yielding mask [shape]).
    """
    a = driver.accel_mps2
    b = driver.comfort_brake_mps2
    s0 = driver.min_gap_m
    base = idm_accel(v_mps, gap_m, v_lead_mps, v0_mps, headway_s, a, b, s0, driver.delta)
    ahead = ego_would_merge_ahead(view, v_mps, in_right_lane, driver.interaction_range_m)

    if not ahead.any():
        return base, ahead
    yielding = ahead & (profile == _COOPERATIVE)
    virtual_gap = np.maximum(view.ego_dx_m - vehicle.length_m, MIN_GAP_FOR_IDM_M)
    a_yield = idm_accel(
        v_mps, virtual_gap, view.ego_v_mps, v0_mps, headway_s, a, b, s0, driver.delta
    )
    a_yield = np.maximum(a_yield, -driver.yield_max_brake_mps2)

    closing = ahead & (profile == _ADVERSARIAL)
    a_close = idm_accel(
        v_mps,
        gap_m,
        v_lead_mps,
        driver.adversarial_speed_factor * speed_limit_mps,
        driver.adversarial_time_headway_s,
        driver.adversarial_accel_mps2,
        b,
        s0,
        driver.delta,
    )
    accel = np.where(yielding, np.minimum(base, a_yield), base)
    accel = np.where(closing, a_close, accel)
    return accel, yielding
