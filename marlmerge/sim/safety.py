"""The optional safety filter (`ego.safety_filter`), compiled: no join into an occupied gap.

It sits between every policy and the ego's vehicle, in the core, so it works the same for every
view and every policy (the IDM ego included). It acts on the true state, each simulator step,
while the ego is on the ramp and its episode runs:

1. Commit test. The hold line is `HOLD_MARGIN_M` before the join point (`x_overlap_m`, where the
   ego starts to occupy the right lane). If after one step with the command the ego could still
   stop before the hold line braking at its lower action bound, the command stands.
2. Join check. Otherwise the command commits the ego to joining. The ego's arrival at the join
   point is predicted with the command held (time t_j, at most `ego.time_to_merge_cap_s`), the
   right-lane vehicles within the sensing range at constant speed. The join is unsafe if a
   right-lane vehicle overlaps the ego's body now or at t_j (alongside), or at t_j the bumper gap
   to the vehicle behind is below max(`safety_min_gap_m`, `safety_min_headway_s` x its speed),
   or the gap to the vehicle ahead below max(`safety_min_gap_m`, `safety_min_headway_s` x the
   ego's speed).
3. Override. If unsafe, the command becomes min(command, a_hold): a_hold = -v^2 / (2 d) brakes
   the ego to a stop at the hold line, d away (it waits there); where that needs more than the
   lower action bound, or the ego is past the hold line, a_hold is the lower bound: the ego drops
   back behind the vehicle alongside.

Each simulator step whose command it changed counts as one intervention (`WI_FILTER_COUNT`, per
ego episode). The reward's acceleration term sees the applied (filtered) acceleration.
"""

from __future__ import annotations

import math

import numpy as np

from marlmerge.sim.jit import kernel
from marlmerge.sim.layout import (
    EGO,
    P_DT,
    P_EGO_LO,
    P_FILTER_GAP,
    P_FILTER_HEADWAY,
    P_LEN,
    P_SENSING,
    P_TIME_CAP,
    P_X_OVERLAP,
    RIGHT,
    VF_V,
    VF_X,
    WI_N_RIGHT,
)

HOLD_MARGIN_M = 0.5
"""The hold line's distance before the join point: a held ego stands clear of the lane."""


@kernel
def filtered_accel(S: tuple, b: int, p: np.ndarray, x_m: float, v_mps: float, cmd: float) -> float:
    """The ego's acceleration after the filter, for a command `cmd` (m/s^2, within the bounds)
    at its pre-step position and speed (see the module docstring)."""
    lo, dt = p[P_EGO_LO], p[P_DT]
    x_hold = p[P_X_OVERLAP] - HOLD_MARGIN_M
    v_next = max(v_mps + cmd * dt, 0.0)
    x_next = x_m + 0.5 * (v_mps + v_next) * dt
    if x_next + v_next * v_next / (-2.0 * lo) < x_hold:
        return cmd
    if join_is_safe(S, b, p, x_m, v_mps, cmd):
        return cmd
    room = x_hold - x_m
    a_hold = -v_mps * v_mps / (2.0 * room) if room > 0.0 else lo
    return min(cmd, max(a_hold, lo))


@kernel(inline=True)
def arrival_s(distance_m: float, v_mps: float, a_mps2: float, cap_s: float) -> float:
    """Time to cover `distance_m` from speed `v_mps` at constant `a_mps2` (at most `cap_s`; the
    cap if the ego stops first)."""
    if distance_m <= 0.0:
        return 0.0
    disc = v_mps * v_mps + 2.0 * a_mps2 * distance_m
    if disc < 0.0:
        return cap_s
    if abs(a_mps2) > 1e-9:
        t = (math.sqrt(disc) - v_mps) / a_mps2
    else:
        t = distance_m / v_mps if v_mps > 0.0 else cap_s
    return min(t, cap_s)


@kernel
def join_is_safe(S: tuple, b: int, p: np.ndarray, x_m: float, v_mps: float, cmd: float) -> bool:
    """The join check of the filter: no right-lane vehicle alongside now or at the predicted
    join, and the gaps to the vehicles behind and ahead at the join above the thresholds."""
    vf, vi, wf, wi, lanes, sched = S
    length, x_join = p[P_LEN], p[P_X_OVERLAP]
    t_j = arrival_s(x_join - x_m, v_mps, cmd, p[P_TIME_CAP])
    v_join = max(v_mps + cmd * t_j, 0.0)
    s0, hw, rng = p[P_FILTER_GAP], p[P_FILTER_HEADWAY], p[P_SENSING]
    for i in range(wi[b, WI_N_RIGHT + RIGHT]):
        s = lanes[b, RIGHT, i]
        x_s, v_s = vf[b, VF_X, s], vf[b, VF_V, s]
        if s == EGO or abs(x_s - x_m) > rng:
            continue
        if abs(x_s - x_m) < length:
            return False  # alongside now
        dx = x_s + v_s * t_j - x_join
        if abs(dx) < length:
            return False  # alongside at the join
        if dx > 0.0 and dx - length < max(s0, hw * v_join):
            return False  # too close behind its new leader
        if dx < 0.0 and -dx - length < max(s0, hw * v_s):
            return False  # the new follower too close behind
    return True
