"""The entrance: drawn arrivals (mainline and, in ramp flow, the ramp's) become vehicles.

Each world's drawn arrivals wait in entrance queues (`sched`, one per lane and one for the
ramp, filled by `marlmerge.sim.streams`); a due arrival enters at its drawn speed once the gap
ahead allows it (`marlmerge.sim.drivers.entry_speed`), otherwise it waits: nobody is dropped.
"""

from __future__ import annotations

import numpy as np

from marlmerge.sim import lanes as ll
from marlmerge.sim.drivers import entry_speed
from marlmerge.sim.jit import kernel
from marlmerge.sim.layout import (
    EGO_STREAM,
    EV_COLLIDED,
    EV_EXITED,
    NEUTRAL,
    P_A,
    P_B,
    P_ENTRANCE_BEST,
    P_LC_COOLDOWN,
    P_LEN,
    P_RAMP_FLOW,
    P_S0,
    P_X_ENTRANCE,
    P_X_RAMP_START,
    P_X_ZONE_START,
    RAMP,
    RAMP_LIST,
    RIGHT,
    SC_POL,
    SC_PROFILE,
    SC_T,
    SC_T_HW,
    SC_V,
    SC_V0,
    VF_A,
    VF_AGE,
    VF_LAPSE,
    VF_POL,
    VF_SINCE_LC,
    VF_T,
    VF_V,
    VF_V0,
    VF_X,
    VI_ACTIVE,
    VI_COLLIDED,
    VI_FLAGS,
    VI_ID,
    VI_LANE,
    VI_PROFILE,
    VI_RAMP,
    WF_DELAY_SUM,
    WF_RAMP_WAIT_SUM,
    WF_T,
    WI_COUNT_LEFT,
    WI_COUNT_RIGHT,
    WI_ENTERED,
    WI_HEAD_RIGHT,
    WI_N_ACTIVE,
    WI_N_RAMP,
    WI_N_RIGHT,
    WI_NEXT_ID,
    WI_OVERFLOW,
    WI_QUEUE_MAX,
    WI_QUEUE_RIGHT,
    WI_RAMP_ENTERED,
    WI_RAMP_QUEUE,
    WI_RAMP_QUEUE_MAX,
)


@kernel(inline=True)
def free_slot(S: tuple, b: int) -> int:
    """The lowest free mainline slot, -1 if none."""
    vf, vi, wf, wi, lanes, sched = S
    for s in range(1, vi.shape[2]):
        if vi[b, VI_ACTIVE, s] == 0:
            return s
    return -1


@kernel(inline=True)
def fill_slot(
    S: tuple,
    b: int,
    s: int,
    lane: int,
    x: float,
    v: float,
    v0: float,
    headway: float,
    politeness: float,
    profile: int,
    p: np.ndarray,
) -> None:
    """A new vehicle in slot `s` (a fresh vehicle id), in no lane list yet (an arrival then goes
    into its lane's list, a ramp vehicle into the ramp's)."""
    vf, vi, wf, wi, lanes, sched = S
    vf[b, VF_X, s] = x
    vf[b, VF_V, s] = v
    vf[b, VF_A, s] = 0.0
    vf[b, VF_V0, s] = v0
    vf[b, VF_T, s] = headway
    vf[b, VF_POL, s] = politeness
    vf[b, VF_SINCE_LC, s] = p[P_LC_COOLDOWN]
    vf[b, VF_AGE, s] = 0.0
    vf[b, VF_LAPSE, s] = 0.0
    vi[b, VI_LANE, s] = lane
    vi[b, VI_ACTIVE, s] = 1
    vi[b, VI_PROFILE, s] = profile
    vi[b, VI_ID, s] = wi[b, WI_NEXT_ID]
    vi[b, VI_COLLIDED, s] = 0
    vi[b, VI_RAMP, s] = 0
    vi[b, VI_FLAGS, s] &= EV_COLLIDED | EV_EXITED  # what the slot saw earlier in this call
    wi[b, WI_NEXT_ID] += 1
    wi[b, WI_N_ACTIVE] += 1


@kernel(inline=True)
def _due(S: tuple, b: int, stream: int) -> bool:
    """The head of entrance queue `stream` (a lane's drawn arrivals) is due now."""
    vf, vi, wf, wi, lanes, sched = S
    head = wi[b, WI_HEAD_RIGHT + stream]
    return wi[b, WI_COUNT_RIGHT + stream] > 0 and sched[b, stream, head, SC_T] <= wf[b, WF_T]


@kernel(inline=True)
def _enter(S: tuple, b: int, p: np.ndarray, stream: int, lane: int) -> bool:
    """The head of entrance queue `stream` enters lane `lane` at its drawn speed once the gap
    to the lane's last vehicle is at least its IDM desired gap (`entry_speed`: it then brakes
    no harder than its comfortable deceleration b); True if it entered. A full world sets
    `WI_OVERFLOW` and the vehicle waits."""
    vf, vi, wf, wi, lanes, sched = S
    t, q_len = wf[b, WF_T], sched.shape[2]
    head = wi[b, WI_HEAD_RIGHT + stream]
    v_enter = sched[b, stream, head, SC_V]
    n = wi[b, WI_N_RIGHT + lane]
    if n > 0:
        tail = lanes[b, lane, n - 1]
        gap = vf[b, VF_X, tail] - p[P_LEN] - p[P_X_ENTRANCE]
        v_enter = entry_speed(
            v_enter,
            gap,
            vf[b, VF_V, tail],
            sched[b, stream, head, SC_T_HW],
            p[P_A],
            p[P_B],
            p[P_S0],
        )
    if v_enter < 0.0:
        return False
    s = free_slot(S, b)
    if s < 0:
        wi[b, WI_OVERFLOW] = 1
        return False
    fill_slot(
        S,
        b,
        s,
        lane,
        p[P_X_ENTRANCE],
        v_enter,
        sched[b, stream, head, SC_V0],
        sched[b, stream, head, SC_T_HW],
        sched[b, stream, head, SC_POL],
        int(sched[b, stream, head, SC_PROFILE]),
        p,
    )
    ll.insert(S, b, lane, s)
    wf[b, WF_DELAY_SUM] += t - sched[b, stream, head, SC_T]
    wi[b, WI_ENTERED] += 1
    wi[b, WI_HEAD_RIGHT + stream] = (head + 1) % q_len
    wi[b, WI_COUNT_RIGHT + stream] -= 1
    return True


@kernel(inline=True)
def best_lane(S: tuple, b: int, p: np.ndarray) -> int:
    """`traffic.entrance_lane = "best"`: the lane whose last vehicle before the merge zone's
    start is farthest from the entrance (an empty stretch counts as the whole of it), the
    right lane on a tie: SUMO's `departLane="best"` on this road, whose first edge ends at the
    zone's start and whose lanes both continue."""
    vf, vi, wf, wi, lanes, sched = S
    x0 = p[P_X_ENTRANCE]
    room = p[P_X_ZONE_START] - x0
    best, best_gap = RIGHT, -1.0
    for lane in range(2):
        gap = room
        n = wi[b, WI_N_RIGHT + lane]
        if n > 0:
            gap = min(vf[b, VF_X, lanes[b, lane, n - 1]] - x0, room)
        if gap > best_gap:
            best, best_gap = lane, gap
    return best


@kernel(inline=True)
def _best_lane_arrivals(S: tuple, b: int, p: np.ndarray) -> None:
    """Both lanes' drawn arrivals in the order of their drawn times (the right lane's first on
    a tie), each into `best_lane`; the first that cannot enter waits, and those behind it
    too (one queue at the entrance, as SUMO inserts the vehicles of one edge)."""
    vf, vi, wf, wi, lanes, sched = S
    for _ in range(2):
        stream = -1
        for lane in range(2):
            if _due(S, b, lane) and (
                stream < 0
                or sched[b, lane, wi[b, WI_HEAD_RIGHT + lane], SC_T]
                < sched[b, stream, wi[b, WI_HEAD_RIGHT + stream], SC_T]
            ):
                stream = lane
        if stream < 0 or not _enter(S, b, p, stream, best_lane(S, b, p)):
            return


@kernel(inline=True)
def _waiting(S: tuple, b: int, stream: int, known: int) -> int:
    """How many of entrance queue `stream`'s drawn arrivals are due and still waiting.

    A queue's arrivals are drawn in the order of their times, so this is the first not yet
    due. The count goes on from `known` (the last step's count less the arrivals that entered
    since, all still due) instead of walking the whole queue, which grows without bound where
    the demand is above the entrance's capacity. After a reset `known` is 0; where the arrival
    before `known` is not due (a count set by hand) the count starts again from the head."""
    vf, vi, wf, wi, lanes, sched = S
    t, q_len = wf[b, WF_T], sched.shape[2]
    head, count = wi[b, WI_HEAD_RIGHT + stream], wi[b, WI_COUNT_RIGHT + stream]
    if count == 0 or sched[b, stream, head, SC_T] > t:
        return 0  # the head is not due: nobody waits (most steps below capacity)
    queue = known if 1 <= known <= count else 1
    i = head + queue - 1  # the last arrival counted (a ring: wrapped at most once)
    if i >= q_len:
        i -= q_len
    if sched[b, stream, i, SC_T] > t:
        queue, i = 1, head
    i = i + 1 if i + 1 < q_len else 0
    while queue < count and sched[b, stream, i, SC_T] <= t:
        queue += 1
        i = i + 1 if i + 1 < q_len else 0
    return queue


@kernel(inline=True)
def arrivals(S: tuple, b: int, p: np.ndarray) -> None:
    """The drawn arrivals whose time has come enter (`_enter`), each lane's into that lane
    (`traffic.entrance_lane = "drawn"`) or into the best lane (`"best"`,
    `_best_lane_arrivals`); otherwise they wait; nobody is dropped. Queue lengths (per drawn
    lane) are counted every step."""
    vf, vi, wf, wi, lanes, sched = S
    count_right, count_left = wi[b, WI_COUNT_RIGHT], wi[b, WI_COUNT_LEFT]
    if p[P_ENTRANCE_BEST] > 0.0:
        _best_lane_arrivals(S, b, p)
    else:
        for lane in range(2):
            if _due(S, b, lane):
                _enter(S, b, p, lane, lane)
    for lane in range(2):
        entered = (count_left if lane else count_right) - wi[b, WI_COUNT_RIGHT + lane]
        queue = _waiting(S, b, lane, wi[b, WI_QUEUE_RIGHT + lane] - entered)
        wi[b, WI_QUEUE_RIGHT + lane] = queue
        wi[b, WI_QUEUE_MAX] = max(wi[b, WI_QUEUE_MAX], queue)
    if p[P_RAMP_FLOW] > 0.0:
        ramp_arrivals(S, b, p)


@kernel
def ramp_arrivals(S: tuple, b: int, p: np.ndarray) -> None:
    """Ramp flow: the first drawn ramp vehicle whose time has come enters at the ramp start at
    its drawn speed once the gap to the ramp's last vehicle is its IDM desired gap (as on the
    lanes); otherwise it waits in the ramp's entrance queue. Its age counts from its drawn
    arrival, so that it includes the wait."""
    vf, vi, wf, wi, lanes, sched = S
    t, q_len, st = wf[b, WF_T], sched.shape[2], EGO_STREAM
    head, count = wi[b, WI_HEAD_RIGHT + st], wi[b, WI_COUNT_RIGHT + st]
    x0 = p[P_X_RAMP_START]
    if count > 0 and sched[b, st, head, SC_T] <= t:
        n = wi[b, WI_N_RAMP]
        v_enter = sched[b, st, head, SC_V]
        if n > 0:
            tail = lanes[b, RAMP_LIST, n - 1]
            v_enter = entry_speed(
                v_enter,
                vf[b, VF_X, tail] - p[P_LEN] - x0,
                vf[b, VF_V, tail],
                sched[b, st, head, SC_T_HW],
                p[P_A],
                p[P_B],
                p[P_S0],
            )
        s = free_slot(S, b) if v_enter >= 0.0 else -1
        if v_enter >= 0.0 and s < 0:
            wi[b, WI_OVERFLOW] = 1
        elif s >= 0:
            t_drawn = sched[b, st, head, SC_T]
            fill_slot(
                S, b, s, RAMP, x0, v_enter, sched[b, st, head, SC_V0],
                sched[b, st, head, SC_T_HW], sched[b, st, head, SC_POL], NEUTRAL, p,
            )  # fmt: skip
            vf[b, VF_AGE, s] = t - t_drawn
            vi[b, VI_RAMP, s] = 1
            ll.ramp_append(S, b, s)
            wf[b, WF_RAMP_WAIT_SUM] += t - t_drawn
            wi[b, WI_RAMP_ENTERED] += 1
            head = (head + 1) % q_len
            count -= 1
    entered = wi[b, WI_COUNT_RIGHT + st] - count  # 1 if one entered
    wi[b, WI_HEAD_RIGHT + st], wi[b, WI_COUNT_RIGHT + st] = head, count
    queue = _waiting(S, b, st, wi[b, WI_RAMP_QUEUE] - entered)
    wi[b, WI_RAMP_QUEUE] = queue
    wi[b, WI_RAMP_QUEUE_MAX] = max(wi[b, WI_RAMP_QUEUE_MAX], queue)
