"""What the ego observes, compiled: its observation vector, and the imperfect sensor around it.

`ego_observation` writes the ego's features (`marlmerge.sim.observation`, the layout of
`ego.observation`) into one row of an output array. With perfect sensing (the default) the core
calls it once, after the last simulator step of a call. With `[sensing]` on, the ego's sensor
measures after every simulator step into a per-world ring (`sense_measure`), each measurement with
its own drawn errors and with occlusion applied, and the ego is shown the measurement of
`latency_s` ago (`sensed_output`). A new ego, or a scene set up by hand, starts a fresh history
(`sense_fill`): until `latency_s` has passed the ego sees its first measurement.

Occlusion (`sensing.occlusion`, extended layout only). Geometry: the right lane's centreline is
y = 0, the left lane's y = lane_width_m; every vehicle is a `length_m` x `width_m` rectangle
centred on its lane, behind its front bumper x. The ego's centre (x_c = x - length_m / 2) is on
the ramp's centreline, y = -ramp_offset_m x clip(-x_c / merge_zone_m, 0, 1): the taper over the
merge zone, as drawn by `marlmerge.views.render`. Rule: a left-lane vehicle is hidden when the
straight line from the ego's centre to that vehicle's centre passes through the body of a
right-lane vehicle (roughly: at least half of it is hidden). A hidden vehicle is reported as
missing. Only the left-lane features (`left_front_*`, `left_back_*`) can be affected: the
gap-front, gap-back and alongside vehicles are the ego's nearest right-lane neighbours, so no
right-lane vehicle lies between them and it.
"""

from __future__ import annotations

import numpy as np

from marlmerge.sim import lanes as ll
from marlmerge.sim.jit import kernel
from marlmerge.sim.layout import (
    EGO,
    LEFT,
    NZ_BACK_X,
    NZ_FRONT_X,
    NZ_LEFT_BACK_X,
    NZ_LEFT_FRONT_X,
    P_ACCEL_SCALE,
    P_LANE_WIDTH,
    P_LEN,
    P_MERGE_ZONE,
    P_NOISE_ON,
    P_OBS_ACCEL,
    P_OBS_EXTENDED,
    P_OBS_JOIN,
    P_OBS_ON_RAMP,
    P_OCCLUSION,
    P_POS_NOISE,
    P_POSITION_SCALE,
    P_RAMP_OFFSET,
    P_SENSE_RING,
    P_SENSING,
    P_SPEED_NOISE,
    P_SPEED_SCALE,
    P_TIME_CAP,
    P_TIME_SCALE,
    P_V_LIMIT,
    P_WIDTH,
    P_X_OVERLAP,
    RAMP,
    RIGHT,
    VF_ACC,
    VF_V,
    VF_X,
    VI_LANE,
    WF_EGO_CMD,
    WF_VB,
    WF_VF,
    WF_XB,
    WF_XF,
    WI_BACK,
    WI_FRONT,
    WI_N_RIGHT,
    WI_NOISE_COUNT,
    WI_NOISE_HEAD,
    WI_OVERFLOW,
    WI_SENSE_HEAD,
)

# ----------------------------------------------------------------------------------------------
# The observation vector
# ----------------------------------------------------------------------------------------------


@kernel
def ego_observation(
    S: tuple, b: int, p: np.ndarray, dst: np.ndarray, row: int, noise: np.ndarray, zi: int
) -> None:
    """The ego's scaled features of world `b` into dst[row, :]. zi: the row of noise[b] holding
    this measurement's errors (-1: exact)."""
    vf, vi, wf, wi, lanes, sched = S
    ss, ps = p[P_SPEED_SCALE], p[P_POSITION_SCALE]
    x_e, v_e = vf[b, VF_X, EGO], vf[b, VF_V, EGO]
    front, back = wi[b, WI_FRONT], wi[b, WI_BACK]
    x_f, v_f, x_b, v_b = wf[b, WF_XF], wf[b, WF_VF], wf[b, WF_XB], wf[b, WF_VB]
    if zi >= 0 and front >= 0:
        x_f, v_f = _noisy(p, noise, b, zi, NZ_FRONT_X, x_f, v_f)
    if zi >= 0 and back >= 0:
        x_b, v_b = _noisy(p, noise, b, zi, NZ_BACK_X, x_b, v_b)
    dst[row, 0], dst[row, 1] = v_e / ss, x_e / ps
    dst[row, 2], dst[row, 3] = v_f / ss, x_f / ps
    dst[row, 4], dst[row, 5] = v_b / ss, x_b / ps
    dst[row, 6] = p[P_V_LIMIT] / ss
    if p[P_OBS_EXTENDED] > 0.0:
        _side(p, dst, row, x_e, front >= 0, x_f, v_f, back >= 0, x_b, v_b)
        _left(S, b, p, dst, row, noise, zi, EGO)
        t_join = _times(p, dst, row, x_e, v_e)
        if p[P_OBS_JOIN] > 0.0:
            _gaps_at_join(p, dst, row, t_join, x_e, v_e, front >= 0, x_f, v_f, back >= 0, x_b, v_b)
    if p[P_OBS_ACCEL] > 0.0:
        dst[row, 16] = wf[b, WF_EGO_CMD] / p[P_ACCEL_SCALE]
    if p[P_OBS_ON_RAMP] > 0.0:  # ego.join = "chosen"
        dst[row, int(p[P_OBS_ON_RAMP])] = 1.0 if vi[b, VI_LANE, EGO] == RAMP else 0.0


@kernel(inline=True)
def _noisy(
    p: np.ndarray, noise: np.ndarray, b: int, zi: int, col: int, x_m: float, v_mps: float
) -> tuple[float, float]:
    """A measured vehicle's position and speed with the errors in noise[b, zi, col : col + 2]."""
    return (
        x_m + p[P_POS_NOISE] * noise[b, zi, col],
        v_mps + p[P_SPEED_NOISE] * noise[b, zi, col + 1],
    )


@kernel
def _side(
    p: np.ndarray,
    dst: np.ndarray,
    row: int,
    x_e: float,
    has_front: bool,
    x_f: float,
    v_f: float,
    has_back: bool,
    x_b: float,
    v_b: float,
) -> None:
    """Columns 7-9: the gap vehicle (front or back, as reported) whose body overlaps the ego's
    most, if any."""
    length, rng = p[P_LEN], p[P_SENSING]
    dx, v, overlap = rng, p[P_V_LIMIT], 0.0
    if has_front and abs(x_f - x_e) < length:
        dx, v, overlap = x_f - x_e, v_f, 1.0 - abs(x_f - x_e) / length
    if has_back and 1.0 - abs(x_b - x_e) / length > overlap:
        dx, v, overlap = x_b - x_e, v_b, 1.0 - abs(x_b - x_e) / length
    dst[row, 7] = dx / p[P_POSITION_SCALE]
    dst[row, 8] = v / p[P_SPEED_SCALE]
    dst[row, 9] = overlap


@kernel
def _left(
    S: tuple,
    b: int,
    p: np.ndarray,
    dst: np.ndarray,
    row: int,
    noise: np.ndarray,
    zi: int,
    s: int,
) -> None:
    """Columns 10-13: the nearest left-lane vehicles at or ahead of and behind slot `s` (the ego,
    or a ramp agent), within the sensing range and, for the ego, not hidden (else the virtual
    vehicle at the range's edge)."""
    vf, vi, wf, wi, lanes, sched = S
    x_e, rng, v_limit = vf[b, VF_X, s], p[P_SENSING], p[P_V_LIMIT]
    ps, ss = p[P_POSITION_SCALE], p[P_SPEED_SCALE]
    lead, follow = ll.neighbours_at(S, b, LEFT, x_e)
    dx_f, v_f, dx_b, v_b = rng, v_limit, -rng, v_limit
    if lead >= 0 and vf[b, VF_X, lead] - x_e <= rng and not (s == EGO and hidden(S, b, p, lead)):
        x, v_f = vf[b, VF_X, lead], vf[b, VF_V, lead]
        if zi >= 0:
            x, v_f = _noisy(p, noise, b, zi, NZ_LEFT_FRONT_X, x, v_f)
        dx_f = x - x_e
    if (
        follow >= 0
        and x_e - vf[b, VF_X, follow] <= rng
        and not (s == EGO and hidden(S, b, p, follow))
    ):
        x, v_b = vf[b, VF_X, follow], vf[b, VF_V, follow]
        if zi >= 0:
            x, v_b = _noisy(p, noise, b, zi, NZ_LEFT_BACK_X, x, v_b)
        dx_b = x - x_e
    dst[row, 10], dst[row, 11] = dx_f / ps, v_f / ss
    dst[row, 12], dst[row, 13] = dx_b / ps, v_b / ss


@kernel
def agent_extended(
    S: tuple, X: tuple, b: int, p: np.ndarray, dst: np.ndarray, row: int, s: int, gap: tuple
) -> None:
    """Ramp flow: columns 7-15 of the extended layouts (and 16 of `extended_accel`) for the ramp
    agent in slot `s` into dst[row, :], as the ego's (`ego_observation`) but measured from the
    agent, with perfect sensing and no occlusion; its last command (`VF_ACC`) for column 16.
    `gap`: the agent's gap vehicles, as `gap_vehicles` returns them."""
    vf, vi, wf, wi, lanes, sched = S
    x, v = vf[b, VF_X, s], vf[b, VF_V, s]
    front, back, x_f, v_f, _, x_b, v_b, _ = gap
    _side(p, dst, row, x, front >= 0, x_f, v_f, back >= 0, x_b, v_b)
    _left(S, b, p, dst, row, X[1], -1, s)
    t_join = _times(p, dst, row, x, v)
    if p[P_OBS_ACCEL] > 0.0:
        dst[row, 16] = vf[b, VF_ACC, s] / p[P_ACCEL_SCALE]
    if p[P_OBS_JOIN] > 0.0:
        _gaps_at_join(p, dst, row, t_join, x, v, front >= 0, x_f, v_f, back >= 0, x_b, v_b)


@kernel(inline=True)
def time_to(distance_m: float, v_mps: float, cap_s: float) -> float:
    """Time to cover `distance_m` at `v_mps`: 0 when already there, at most `cap_s`."""
    if distance_m <= 0.0:
        return 0.0
    if v_mps * cap_s <= distance_m:
        return cap_s
    return distance_m / v_mps


@kernel
def _times(p: np.ndarray, dst: np.ndarray, row: int, x_e: float, v_e: float) -> float:
    """Columns 14-15: the times to the join point and to the merge point; returns the first
    (s, unscaled)."""
    cap, ts = p[P_TIME_CAP], p[P_TIME_SCALE]
    t_join = time_to(p[P_X_OVERLAP] - x_e, v_e, cap)
    dst[row, 14] = t_join / ts
    dst[row, 15] = time_to(-x_e, v_e, cap) / ts
    return t_join


@kernel
def _gaps_at_join(
    p: np.ndarray,
    dst: np.ndarray,
    row: int,
    t: float,
    x_e: float,
    v_e: float,
    has_front: bool,
    x_f: float,
    v_f: float,
    has_back: bool,
    x_b: float,
    v_b: float,
) -> None:
    """Columns 17-18 (`"extended_join"`): the bumper gaps to the gap-front and from the gap-back
    vehicle (as reported) when the ego reaches the join point, `t` s from now (`_times`), all
    holding their speeds; within +-sensing range, +sensing range where the vehicle is
    missing."""
    length, rng, ps = p[P_LEN], p[P_SENSING], p[P_POSITION_SCALE]
    lead, lag = rng, rng
    if has_front:
        lead = min(max(x_f - x_e + (v_f - v_e) * t - length, -rng), rng)
    if has_back:
        lag = min(max(x_e - x_b + (v_e - v_b) * t - length, -rng), rng)
    dst[row, 17] = lead / ps
    dst[row, 18] = lag / ps


# ----------------------------------------------------------------------------------------------
# Occlusion
# ----------------------------------------------------------------------------------------------


@kernel(inline=True)
def ramp_lateral_m(p: np.ndarray, x_m: float) -> float:
    """Lateral position of the ramp's centreline at `x_m` (right lane's centreline 0, left
    positive): the taper over the merge zone, the ramp's offset upstream of it."""
    frac = min(max(-x_m / p[P_MERGE_ZONE], 0.0), 1.0)
    return -p[P_RAMP_OFFSET] * frac


@kernel
def hidden(S: tuple, b: int, p: np.ndarray, target: int) -> bool:
    """With occlusion on: the line from the ego's centre to the centre of the left-lane vehicle
    `target` passes through the body of a right-lane vehicle (see the module docstring)."""
    if p[P_OCCLUSION] <= 0.0:
        return False
    vf, vi, wf, wi, lanes, sched = S
    length, half_w = p[P_LEN], 0.5 * p[P_WIDTH]
    xc_e = vf[b, VF_X, EGO] - 0.5 * length
    y_e = ramp_lateral_m(p, xc_e)
    xc_t, y_t = vf[b, VF_X, target] - 0.5 * length, p[P_LANE_WIDTH]
    if y_t - y_e <= 0.0:
        return False
    # the part of the line inside the right lane's body band |y| <= half_w
    s_in = max((-half_w - y_e) / (y_t - y_e), 0.0)
    s_out = min((half_w - y_e) / (y_t - y_e), 1.0)
    if s_in >= s_out:
        return False
    xa, xb = xc_e + s_in * (xc_t - xc_e), xc_e + s_out * (xc_t - xc_e)
    lo, hi = min(xa, xb), max(xa, xb)
    for i in range(wi[b, WI_N_RIGHT + RIGHT]):
        s = lanes[b, RIGHT, i]
        x_s = vf[b, VF_X, s]
        if x_s - length >= hi:
            continue
        if x_s <= lo:
            break  # downstream first: every later one is further upstream
        if s != EGO:
            return True
    return False


# ----------------------------------------------------------------------------------------------
# The sensor's history
# ----------------------------------------------------------------------------------------------


@kernel(inline=True)
def _pop_noise(S: tuple, noise: np.ndarray, b: int) -> int:
    """The row of noise[b] for the next measurement (the core draws ahead; none left: overflow)."""
    vf, vi, wf, wi, lanes, sched = S
    if wi[b, WI_NOISE_COUNT] < 1:
        wi[b, WI_OVERFLOW] = 1
        return -1
    head = wi[b, WI_NOISE_HEAD]
    wi[b, WI_NOISE_HEAD] = (head + 1) % noise.shape[1]
    wi[b, WI_NOISE_COUNT] -= 1
    return head


@kernel
def sense_measure(S: tuple, X: tuple, b: int, p: np.ndarray) -> int:
    """One measurement of world `b` into the next row of its ring; returns that row."""
    vf, vi, wf, wi, lanes, sched = S
    ring, noise = X
    n_ring = int(p[P_SENSE_RING])
    head = (wi[b, WI_SENSE_HEAD] + 1) % n_ring
    wi[b, WI_SENSE_HEAD] = head
    zi = _pop_noise(S, noise, b) if p[P_NOISE_ON] > 0.0 else -1
    row = b * n_ring + head
    ego_observation(S, b, p, ring, row, noise, zi)
    return row


@kernel
def sense_fill(S: tuple, X: tuple, b: int, p: np.ndarray) -> None:
    """A fresh history: one measurement, as if it had been the same for the whole latency."""
    ring, noise = X
    n_ring = int(p[P_SENSE_RING])
    row = sense_measure(S, X, b, p)
    for r in range(b * n_ring, (b + 1) * n_ring):
        for c in range(ring.shape[1]):
            ring[r, c] = ring[row, c]


@kernel
def sensed_output(S: tuple, X: tuple, b: int, p: np.ndarray, ego_obs: np.ndarray) -> None:
    """ego_obs[b] = the oldest measurement of the ring: the one of `latency_s` ago."""
    vf, vi, wf, wi, lanes, sched = S
    ring, noise = X
    n_ring = int(p[P_SENSE_RING])
    row = b * n_ring + (wi[b, WI_SENSE_HEAD] + 1) % n_ring
    for c in range(ego_obs.shape[1]):
        ego_obs[b, c] = ring[row, c]
