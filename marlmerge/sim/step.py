"""The simulator steps of one world, compiled: the dynamics, written once.

`run_steps` advances world `b` by `k` steps of `dt_s`, each in this order:

1. MOBIL lane-change decisions on the pre-step state (every `lane_change_every_steps`);
2. accelerations on the pre-step state (IDM and the interaction profiles for mainline drivers,
   who hold their speed while an attention lapse lasts, `marlmerge.sim.lapses`;
   external commands for controlled highway agents, the ego's command; NaN: plain IDM) and the
   ballistic update (a vehicle that stops within the step stops where v reaches 0), in one sweep
   per lane; then the lane changes;
3. exits downstream, arrivals at the entrance (queued until a safe entry exists), the ego joining
   the right lane once it overlaps it (or when it chooses, `ego.join = "chosen"`: `joins_now`);
4. collisions: overlaps of consecutive vehicles in a lane; mainline wrecks are towed away at
   once, the ego's stay until its episode is closed;
5. the ego's episode clock and outcome, and its gap vehicles after the step.

After each step it also takes the ego sensor's measurement (`marlmerge.sim.sensing`) and
records the ego's trace row, its reward terms and the highway agents' (`marlmerge.sim.reward`).

Arrays and rows: `marlmerge.sim.layout`; lane lists: `marlmerge.sim.lanes`.
"""

from __future__ import annotations

import math

import numpy as np

from marlmerge.sim import lanes as ll
from marlmerge.sim.drivers import ego_merges_ahead, idm, profile_accel
from marlmerge.sim.entrance import arrivals
from marlmerge.sim.jit import kernel
from marlmerge.sim.lapses import critical_slot, lapsing
from marlmerge.sim.layout import (
    ADVERSARIAL,
    COOPERATIVE,
    EGO,
    EV_CHANGE,
    EV_CHOOSES,
    EV_COLLIDED,
    EV_CONTROLLED,
    EV_EXITED,
    EV_HIT,
    EV_JOIN,
    EV_TOW,
    LEFT,
    OUTCOME_COLLISION,
    OUTCOME_NONE,
    OUTCOME_SUCCESS,
    OUTCOME_TRUNCATED,
    P_A,
    P_ADV_A,
    P_ADV_T,
    P_ADV_V0,
    P_B,
    P_DELTA,
    P_DT,
    P_EGO_HI,
    P_EGO_LO,
    P_FILTER,
    P_HW_HI,
    P_HW_LO,
    P_INTERACTION_RANGE,
    P_JOIN_CHOSEN,
    P_KEEP_RIGHT,
    P_LAPSE_P,
    P_LC_COOLDOWN,
    P_LC_EVERY,
    P_LC_SEES_RAMP,
    P_LC_THRESHOLD,
    P_LEN,
    P_MAX_ACCEL,
    P_MAX_BRAKE,
    P_MAX_EPISODE,
    P_RAMP_FLOW,
    P_RAMP_WHEN_SAFE,
    P_RAMP_ZIPPER,
    P_S0,
    P_SAFE_BRAKE,
    P_SENSE_ON,
    P_SENSING,
    P_STALL_SPEED,
    P_STALL_TIME,
    P_SUCCESS,
    P_V_LIMIT,
    P_X_EXIT,
    P_X_OVERLAP,
    P_X_ZONE_START,
    P_YIELD_LC_BONUS,
    P_YIELD_MAX_BRAKE,
    RAMP,
    RAMP_LIST,
    RIGHT,
    RO_EXITED,
    RO_ID,
    RO_MASK,
    RO_SLOT,
    TR_A,
    TR_AB,
    TR_DB,
    TR_DF,
    TR_HIT,
    TR_V,
    TR_VB,
    TR_VF,
    TR_X,
    VF_A,
    VF_ACC,
    VF_AGE,
    VF_GAP,
    VF_LAPSE,
    VF_POL,
    VF_SINCE_LC,
    VF_T,
    VF_V,
    VF_V0,
    VF_VLEAD,
    VF_X,
    VI_ACTIVE,
    VI_COLLIDED,
    VI_FLAGS,
    VI_FOLLOWER,
    VI_ID,
    VI_LANE,
    VI_LEADER,
    VI_PROFILE,
    VI_RAMP,
    WF_DB,
    WF_DF,
    WF_EGO_CMD,
    WF_EGO_IN_LANE,
    WF_EGO_STALL,
    WF_EGO_T,
    WF_RAMP_TRAVEL_SUM,
    WF_T,
    WF_VB,
    WF_VF,
    WF_XB,
    WF_XF,
    WI_BACK,
    WI_BG_COLLISIONS,
    WI_EGO_PARTNER,
    WI_EGO_REAR,
    WI_EXITED,
    WI_FILTER_COUNT,
    WI_FRONT,
    WI_N_ACTIVE,
    WI_N_RAMP,
    WI_N_RIGHT,
    WI_OUTCOME,
    WI_RAMP_COLLISIONS,
    WI_RAMP_JOINED,
    WI_RAMP_PASSED,
    WI_RAMP_TOWED,
    WI_STEP_OUTCOME,
    WI_STEPS,
    WI_VEH_STEPS,
)
from marlmerge.sim.reward import (
    add_ego_terms,
    add_highway_terms,
    ego_closeness,
    ego_to_blame,
    merge_gaps,
)
from marlmerge.sim.safety import filtered_accel
from marlmerge.sim.sensing import sense_measure

NAN = math.nan
INF = math.inf


@kernel(inline=True)
def _link(S: tuple, b: int, row: int, n: int, length: float) -> None:
    """Leader, follower, bumper gap and leader speed of the `n` vehicles of `lanes[b, row]`
    (downstream first): gap inf and the own speed when there is no leader."""
    vf, vi, wf, wi, lanes, sched = S
    prev = -1
    for i in range(n):
        s = lanes[b, row, i]
        vi[b, VI_LEADER, s] = prev
        vi[b, VI_FOLLOWER, s] = -1
        if prev >= 0:
            vf[b, VF_GAP, s] = vf[b, VF_X, prev] - length - vf[b, VF_X, s]
            vf[b, VF_VLEAD, s] = vf[b, VF_V, prev]
            vi[b, VI_FOLLOWER, prev] = s
        else:
            vf[b, VF_GAP, s] = INF
            vf[b, VF_VLEAD, s] = vf[b, VF_V, s]
        prev = s


@kernel(inline=True)
def neighbours(S: tuple, b: int, p: np.ndarray) -> None:
    """Leader, follower, bumper gap and leader speed of every vehicle from the lane lists (gap
    inf and the own speed when there is no leader). The ego on the ramp has no neighbours."""
    vf, vi, wf, wi, lanes, sched = S
    length = p[P_LEN]
    for lane in range(2):
        _link(S, b, lane, wi[b, WI_N_RIGHT + lane], length)
    if vi[b, VI_LANE, EGO] == RAMP:
        vi[b, VI_LEADER, EGO] = -1
        vi[b, VI_FOLLOWER, EGO] = -1
        vf[b, VF_GAP, EGO] = INF
        vf[b, VF_VLEAD, EGO] = vf[b, VF_V, EGO]
    _link(S, b, RAMP_LIST, wi[b, WI_N_RAMP], length)  # ramp flow: the ramp list, as a lane


@kernel(inline=True)
def merging_slot(S: tuple, b: int) -> int:
    """The slot of the ramp vehicle the mainline drivers react to: with ramp flow the ramp's
    first vehicle (the ramp list's head), else the ego."""
    vf, vi, wf, wi, lanes, sched = S
    return lanes[b, RAMP_LIST, 0] if wi[b, WI_N_RAMP] > 0 else EGO


@kernel(inline=True)
def merging_vehicle(S: tuple, b: int) -> tuple:
    """(pending, x_m, v_mps) of the ramp vehicle the mainline drivers react to (`merging_slot`):
    pending with ramp flow while the ramp holds a vehicle, else while the ego is on the ramp."""
    vf, vi, wf, wi, lanes, sched = S
    s = merging_slot(S, b)
    pending = wi[b, WI_N_RAMP] > 0 or (vi[b, VI_ACTIVE, EGO] == 1 and vi[b, VI_LANE, EGO] == RAMP)
    return pending, vf[b, VF_X, s], vf[b, VF_V, s]


@kernel(inline=True)
def driver_params(p: np.ndarray) -> tuple:
    """The parameters the driver models need, read once into scalars: a loop that writes to the
    vehicle arrays would otherwise reload them from `p` on every iteration (they might alias)."""
    return (
        p[P_A],
        p[P_B],
        p[P_S0],
        p[P_DELTA],
        p[P_INTERACTION_RANGE],
        p[P_YIELD_MAX_BRAKE],
        p[P_LEN],
        p[P_ADV_V0],
        p[P_ADV_T],
        p[P_ADV_A],
        p[P_X_OVERLAP],
        p[P_MAX_BRAKE],
        p[P_MAX_ACCEL],
    )


@kernel(inline=True)
def _scripted_accel(
    S: tuple,
    b: int,
    s: int,
    dp: tuple,
    x: float,
    v: float,
    gap: float,
    v_lead: float,
    pending: bool,
    x_e: float,
    v_e: float,
) -> float:
    """Scripted acceleration of slot `s` at position x, speed v, and the given leader gap and
    speed (pre-step state), clipped to the vehicle limits. dp: `driver_params`."""
    vf, vi, wf, wi, lanes, sched = S
    acc, _ = profile_accel(
        vi[b, VI_PROFILE, s],
        v,
        gap,
        v_lead,
        vf[b, VF_V0, s],
        vf[b, VF_T, s],
        vi[b, VI_LANE, s] == RIGHT,
        pending,
        x_e - x,
        v_e,
        dp[10] - x_e,
        dp[0],
        dp[1],
        dp[2],
        dp[3],
        dp[4],
        dp[5],
        dp[6],
        dp[7],
        dp[8],
        dp[9],
    )
    return min(max(acc, -dp[11]), dp[12])


@kernel(inline=True)
def _move(S: tuple, b: int, s: int, acc: float, dt: float) -> None:
    """Ballistic update of slot `s`; a vehicle that stops within the step stops where v = 0."""
    vf, vi, wf, wi, lanes, sched = S
    v_old = vf[b, VF_V, s]
    v_new = max(v_old + acc * dt, 0.0)
    if v_new == 0.0:
        dx = 0.5 * v_old * v_old / max(-acc, 1e-9)
    else:
        dx = (v_old + v_new) * (0.5 * dt)
    vf[b, VF_X, s] += dx
    vf[b, VF_A, s] = (v_new - v_old) * (1.0 / dt)
    vf[b, VF_V, s] = v_new
    vf[b, VF_SINCE_LC, s] += dt
    vf[b, VF_AGE, s] += dt


@kernel(inline=True)
def mark_controlled(
    S: tuple, b: int, p: np.ndarray, roster: np.ndarray, roster_cmd: np.ndarray
) -> None:
    """Flag (`EV_CONTROLLED`) the highway agents driven by an external command this step and
    put the command, roster_cmd[b, j, 0] clipped to the agent bounds, into `VF_ACC`. NaN
    commands: scripted. With ramp flow the agents are ramp vehicles: clipped to the ego's
    bounds, on the ramp (capped by IDM behind a ramp leader, `_advance_ramp`) and, as the ego,
    after joining; with `ego.join = "chosen"` a finite join command roster_cmd[b, j, 1] flags
    the vehicle as choosing its join (`EV_CHOOSES`) and, if > 0, as joining now (`EV_JOIN`)."""
    vf, vi, wf, wi, lanes, sched = S
    chosen = p[P_JOIN_CHOSEN] > 0.0
    for j in range(roster.shape[2]):
        s = roster[RO_SLOT, b, j]
        cmd, join = roster_cmd[b, j, 0], roster_cmd[b, j, 1]
        if s <= EGO or roster[RO_MASK, b, j] == 0:
            continue
        if vi[b, VI_ACTIVE, s] == 0 or vi[b, VI_ID, s] != roster[RO_ID, b, j]:
            continue
        if chosen and not math.isnan(join):
            vi[b, VI_FLAGS, s] |= EV_CHOOSES | (EV_JOIN if join > 0.0 else 0)
        if math.isnan(cmd):
            continue
        if p[P_RAMP_FLOW] > 0.0:  # ramp flow: the agents are ramp vehicles, ego bounds
            vf[b, VF_ACC, s] = min(max(cmd, p[P_EGO_LO]), p[P_EGO_HI])
        else:
            vf[b, VF_ACC, s] = min(max(cmd, p[P_HW_LO]), p[P_HW_HI])
        vi[b, VI_FLAGS, s] |= EV_CONTROLLED


@kernel(inline=True)
def advance(S: tuple, b: int, p: np.ndarray, ego_cmd: float, ego_chooses: bool) -> int:
    """Accelerations on the pre-step state and the ballistic update, in one sweep per lane from
    downstream (each vehicle's leader is still known as it was before the step). Mainline drivers
    follow their profile, controlled agents their command (`mark_controlled`), the ego its
    command clipped to its bounds (NaN: plain IDM, ignoring the merge). Returns how many
    vehicles moved. With the safety filter on, the ego's command on the ramp passes through it
    (`marlmerge.sim.safety`), decided on the pre-step state. An ego choosing its join
    (`ego_chooses`) stops at the acceleration lane's end until it joins (`lane_end_guard`)."""
    vf, vi, wf, wi, lanes, sched = S
    dt = p[P_DT]
    dp = driver_params(p)
    length = dp[6]
    ego_on = vi[b, VI_ACTIVE, EGO] == 1
    pending = ego_on and vi[b, VI_LANE, EGO] == RAMP
    x_e, v_e = vf[b, VF_X, EGO], vf[b, VF_V, EGO]
    m_pending, x_m, v_m = merging_vehicle(S, b)
    flowing = p[P_RAMP_FLOW] > 0.0
    ego_idm = math.isnan(ego_cmd)
    ego_a = min(max(ego_cmd, p[P_EGO_LO]), p[P_EGO_HI])
    filtering = pending and p[P_FILTER] > 0.0 and wi[b, WI_OUTCOME] == OUTCOME_NONE
    ramp_a = _ramp_accel(S, b, p, dp, ego_a, ego_idm, x_e, v_e) if filtering else 0.0
    moved = 0
    zipper = flowing and p[P_RAMP_ZIPPER] > 0.0
    lapses = p[P_LAPSE_P] > 0.0
    crit = critical_slot(S, b, p) if lapses else -1
    for lane in range(2):
        n = wi[b, WI_N_RIGHT + lane]
        x_lead, v_lead = INF, 0.0
        j_ramp = 0  # ramp flow, zipper: the ramp list's first vehicle not yet passed
        for i in range(n):
            s = lanes[b, lane, i]
            x, v = vf[b, VF_X, s], vf[b, VF_V, s]
            gap = x_lead - length - x if i > 0 else INF
            vl = v_lead if i > 0 else v
            flags = vi[b, VI_FLAGS, s]
            if s == EGO:
                acc = ego_a
                if ego_idm:
                    acc = _scripted_accel(S, b, s, dp, x, v, gap, vl, False, x_e, v_e)
                wf[b, WF_EGO_CMD] = acc
            elif flags & EV_CONTROLLED:
                acc = vf[b, VF_ACC, s]
            else:  # a scripted mainline driver
                if zipper and lane == RIGHT and vi[b, VI_PROFILE, s] != ADVERSARIAL:
                    acc = _scripted_accel(S, b, s, dp, x, v, gap, vl, False, x_m, v_m)
                    acc, j_ramp = _zipper_yield(S, b, p, dp, s, x, v, x_lead, j_ramp, acc)
                else:
                    # ramp flow: a driver alongside or past the ramp vehicle does not yield to
                    # it (with joins when safe, both would wait for ever)
                    pend = m_pending and not (flowing and x_m - x < length)
                    acc = _scripted_accel(S, b, s, dp, x, v, gap, vl, pend, x_m, v_m)
                if lapses and lapsing(S, b, p, s, s == crit):
                    acc = 0.0  # holds its speed
            vi[b, VI_FLAGS, s] = flags & ~(EV_HIT | EV_TOW | EV_CONTROLLED | EV_CHOOSES | EV_JOIN)
            _move(S, b, s, acc, dt)
            x_lead, v_lead = x, v
        moved += n
    if pending:  # on the ramp: no leader
        acc = ego_a
        if ego_idm:
            acc = _scripted_accel(S, b, EGO, dp, x_e, v_e, INF, v_e, False, x_e, v_e)
        if filtering:
            acc = ramp_a
        if ego_chooses:
            acc = lane_end_guard(p, x_e, v_e, acc)
        wf[b, WF_EGO_CMD] = acc
        vi[b, VI_FLAGS, EGO] &= ~(EV_HIT | EV_TOW)
        _move(S, b, EGO, acc, dt)
        moved += 1
    if wi[b, WI_N_RAMP] > 0:
        moved += _advance_ramp(S, b, p, dp)
    return moved


@kernel(inline=True)
def _zipper_yield(
    S: tuple,
    b: int,
    p: np.ndarray,
    dp: tuple,
    s: int,
    x: float,
    v: float,
    x_lead: float,
    j: int,
    acc: float,
) -> tuple:
    """`ramp.cooperation = "zipper"`: right-lane driver `s` at x (m), v (m/s), its leader at
    x_lead, yields to the ramp vehicle in the merge zone nearest ahead of it and behind its
    leader (pre-step state): its acceleration `acc` capped by IDM behind that vehicle, braking at
    most `yield_max_brake_mps2` for it. Not for a ramp vehicle less than a length plus the jam
    gap ahead (the driver drives on past it), nor beyond the interaction range. j: the first
    ramp-list entry not behind x_lead (the lane is swept downstream first, so the search goes on
    from there). Returns (acc, j)."""
    vf, vi, wf, wi, lanes, sched = S
    n = wi[b, WI_N_RAMP]
    while j < n and vf[b, VF_X, lanes[b, RAMP_LIST, j]] >= x_lead:
        j += 1
    r = -1
    while j < n and vf[b, VF_X, lanes[b, RAMP_LIST, j]] > max(x, p[P_X_ZONE_START]):
        r = lanes[b, RAMP_LIST, j]
        j += 1
    if r < 0:
        return acc, j
    dx = vf[b, VF_X, r] - x
    if dx <= dp[6] + dp[2] or dx >= dp[4]:
        return acc, j
    a_yield = idm(
        v, dx - dp[6], vf[b, VF_V, r], vf[b, VF_V0, s], vf[b, VF_T, s], dp[0], dp[1], dp[2], dp[3]
    )
    return min(acc, max(a_yield, -dp[5])), j


@kernel
def _advance_ramp(S: tuple, b: int, p: np.ndarray, dp: tuple) -> int:
    """Ramp flow: the ramp's vehicles on the pre-step state, downstream first: IDM behind their
    ramp leader (their own v0 and T); an agent's command (`EV_CONTROLLED`) in its place, capped
    by that IDM when a ramp leader is ahead; with `ramp.join = "when_safe"`, also capped by IDM
    behind the acceleration lane's end (x = 0) as a standing obstacle; a vehicle choosing its
    join (`EV_CHOOSES`) by `lane_end_guard` instead. Returns how many moved. (The join flags
    stay for `ramp_joins`.)"""
    vf, vi, wf, wi, lanes, sched = S
    dt, length = p[P_DT], dp[6]
    when_safe = p[P_RAMP_WHEN_SAFE] > 0.0
    n = wi[b, WI_N_RAMP]
    x_lead, v_lead = INF, 0.0
    for i in range(n):
        s = lanes[b, RAMP_LIST, i]
        x, v = vf[b, VF_X, s], vf[b, VF_V, s]
        gap = x_lead - length - x if i > 0 else INF
        vl = v_lead if i > 0 else v
        acc = _scripted_accel(S, b, s, dp, x, v, gap, vl, False, x, v)
        flags = vi[b, VI_FLAGS, s]
        if flags & EV_CONTROLLED:
            acc = min(vf[b, VF_ACC, s], acc) if i > 0 else vf[b, VF_ACC, s]
        if flags & EV_CHOOSES:
            acc = lane_end_guard(p, x, v, acc)
        elif when_safe:  # the acceleration lane ends at x = 0: a standing obstacle there
            acc = min(acc, _scripted_accel(S, b, s, dp, x, v, -x, 0.0, False, x, v))
        vi[b, VI_FLAGS, s] = flags & ~(EV_HIT | EV_TOW | EV_CONTROLLED)
        _move(S, b, s, acc, dt)
        x_lead, v_lead = x, v
    return n


LANE_END_STOP_M = 0.5
"""Where a vehicle choosing its join stops, before the acceleration lane's end (m)."""


@kernel(inline=True)
def lane_end_guard(p: np.ndarray, x: float, v: float, acc: float) -> float:
    """`ego.join = "chosen"`: a vehicle that has not joined stops at the acceleration lane's end
    (x = 0; at `LANE_END_STOP_M` before it). It keeps its command `acc` (m/s^2) unless, after a
    step at that command, braking at the ego's bound could no longer stop it there; then it
    brakes to stop exactly there (harder than the bound by at most one step's worth), and there
    it stands."""
    dt = p[P_DT]
    to_stop = -LANE_END_STOP_M - x  # m
    if to_stop <= 0.0:  # at the line: stop within this step
        return min(acc, -v / dt)
    v1 = max(v + acc * dt, 0.0)
    left = to_stop - 0.5 * (v + v1) * dt  # m to the line after that step
    if left <= 0.0 or v1 * v1 >= 2.0 * left * -p[P_EGO_LO]:
        return min(acc, -v * v / (2.0 * to_stop))  # stops it there from here
    return acc


@kernel
def _ramp_accel(
    S: tuple,
    b: int,
    p: np.ndarray,
    dp: tuple,
    ego_a: float,
    ego_idm: bool,
    x_e: float,
    v_e: float,
) -> float:
    """The ego's acceleration on the ramp through the safety filter (its command, or plain IDM
    for a NaN command), counting an intervention when the filter changed it."""
    vf, vi, wf, wi, lanes, sched = S
    cmd = ego_a
    if ego_idm:
        cmd = _scripted_accel(S, b, EGO, dp, x_e, v_e, INF, v_e, False, x_e, v_e)
    acc = filtered_accel(S, b, p, x_e, v_e, cmd)
    if acc != cmd:
        wi[b, WI_FILTER_COUNT] += 1
    return acc


@kernel(inline=True)
def _idm_of(S: tuple, b: int, s: int, gap: float, v_lead: float, dp: tuple) -> float:
    """IDM acceleration of slot `s` (its own v0 and T, the base a, b, s0) at a hypothetical gap."""
    vf, vi, wf, wi, lanes, sched = S
    return idm(
        vf[b, VF_V, s], gap, v_lead, vf[b, VF_V0, s], vf[b, VF_T, s], dp[0], dp[1], dp[2], dp[3]
    )


@kernel(inline=True)
def _mobil_wants_change(
    S: tuple, b: int, s: int, p: np.ndarray, dp: tuple, pending: bool, x_e: float, v_e: float
) -> bool:
    """MOBIL for slot `s` on the pre-step state: incentive + keep-right bias above the threshold,
    and safe (the new follower brakes no harder than `safe_brake_mps2`, both gaps above s0)."""
    vf, vi, wf, wi, lanes, sched = S
    length, s0 = p[P_LEN], p[P_S0]
    lane = vi[b, VI_LANE, s]
    target = 1 - lane
    x, v = vf[b, VF_X, s], vf[b, VF_V, s]
    t_lead, t_follow = ll.neighbours_at(S, b, target, x)
    gap_t, v_t = INF, v
    if t_lead >= 0:
        gap_t, v_t = vf[b, VF_X, t_lead] - x - length, vf[b, VF_V, t_lead]
    back_gap_t = INF
    others = 0.0
    a_nf_after = 0.0
    if t_follow >= 0:  # the new follower: before (behind the target leader) and after (behind s)
        back_gap_t = x - vf[b, VF_X, t_follow] - length
        a_nf_before = _idm_of(
            S, b, t_follow, vf[b, VF_GAP, t_follow], vf[b, VF_VLEAD, t_follow], dp
        )
        a_nf_after = _idm_of(S, b, t_follow, back_gap_t, v, dp)
        others += a_nf_after - a_nf_before
    of = vi[b, VI_FOLLOWER, s]
    if of >= 0:  # the old follower: before (behind s) and after (behind s's leader)
        gap_back = vf[b, VF_GAP, of]
        a_of_before = _idm_of(S, b, of, gap_back, v, dp)
        a_of_after = _idm_of(S, b, of, gap_back + length + vf[b, VF_GAP, s], vf[b, VF_VLEAD, s], dp)
        others += a_of_after - a_of_before
    a_now = _idm_of(S, b, s, vf[b, VF_GAP, s], vf[b, VF_VLEAD, s], dp)
    a_tgt = _idm_of(S, b, s, gap_t, v_t, dp)
    incentive = a_tgt - a_now + vf[b, VF_POL, s] * others
    bias = -p[P_KEEP_RIGHT] if target == LEFT else p[P_KEEP_RIGHT]
    if target == LEFT and pending and vi[b, VI_PROFILE, s] == COOPERATIVE:
        # a cooperative driver that is yielding to the ramp vehicle is keener to move left
        if ego_merges_ahead(x_e - x, v_e, p[P_X_OVERLAP] - x_e, v, p[P_INTERACTION_RANGE]):
            bias += p[P_YIELD_LC_BONUS]
    safe = (t_follow < 0 or a_nf_after >= -p[P_SAFE_BRAKE]) and gap_t > s0 and back_gap_t > s0
    if safe and target == RIGHT and pending and p[P_LC_SEES_RAMP] > 0.0:
        safe = _clear_of_ramp(S, b, s, p, dp, x_e, v_e)
    return safe and incentive + bias > p[P_LC_THRESHOLD]


@kernel(inline=True)
def _clear_of_ramp(
    S: tuple, b: int, s: int, p: np.ndarray, dp: tuple, x_e: float, v_e: float
) -> bool:
    """`driver.lane_change_sees_ramp`: slot `s` moving right keeps clear of the ramp vehicle at
    x_e once that is in the merge zone or reaches it before the next lane-change decision (a
    decision holds until then), as of a vehicle of the right lane: both bumper gaps above s0,
    and neither brakes harder than `safe_brake_mps2` behind the other."""
    vf, vi, wf, wi, lanes, sched = S
    if x_e + v_e * p[P_LC_EVERY] * p[P_DT] < p[P_X_ZONE_START]:
        return True
    length, s0, limit = p[P_LEN], p[P_S0], -p[P_SAFE_BRAKE]
    x, v = vf[b, VF_X, s], vf[b, VF_V, s]
    if x_e >= x:  # the ramp vehicle would lead the mover
        gap = x_e - x - length
        return gap > s0 and _idm_of(S, b, s, gap, v_e, dp) >= limit
    gap = x - x_e - length
    return gap > s0 and _idm_of(S, b, merging_slot(S, b), gap, v, dp) >= limit


@kernel(inline=True)
def lane_change_decisions(S: tuple, b: int, p: np.ndarray) -> int:
    """Flag (`EV_CHANGE`) the scripted mainline vehicles that change lanes after this step,
    decided on the pre-step state. Returns how many."""
    vf, vi, wf, wi, lanes, sched = S
    pending, x_e, v_e = merging_vehicle(S, b)
    dp = driver_params(p)
    n = 0
    for lane in range(2):
        for i in range(wi[b, WI_N_RIGHT + lane]):
            s = lanes[b, lane, i]
            if s == EGO or vi[b, VI_FLAGS, s] & EV_CONTROLLED or vf[b, VF_LAPSE, s] > 0.0:
                continue
            if vf[b, VF_SINCE_LC, s] < p[P_LC_COOLDOWN]:
                continue
            if _mobil_wants_change(S, b, s, p, dp, pending, x_e, v_e):
                vi[b, VI_FLAGS, s] |= EV_CHANGE
                n += 1
    return n


@kernel(inline=True)
def apply_lane_changes(S: tuple, b: int) -> None:
    """Move the flagged vehicles to the other lane, at their new positions."""
    vf, vi, wf, wi, lanes, sched = S
    for lane in range(2):
        i = 0
        while i < wi[b, WI_N_RIGHT + lane]:
            s = lanes[b, lane, i]
            if vi[b, VI_FLAGS, s] & EV_CHANGE:
                vi[b, VI_FLAGS, s] &= ~EV_CHANGE
                ll.remove(S, b, lane, s)
                vi[b, VI_LANE, s] = 1 - lane
                vf[b, VF_SINCE_LC, s] = 0.0
                ll.insert(S, b, 1 - lane, s)
            else:
                i += 1


@kernel(inline=True)
def deactivate(S: tuple, b: int, s: int) -> None:
    """Take slot `s` off the road (out of its lane list, inactive)."""
    vf, vi, wf, wi, lanes, sched = S
    lane = vi[b, VI_LANE, s]
    if lane >= RIGHT:
        ll.remove(S, b, lane, s)
    elif s != EGO and wi[b, WI_N_RAMP] > 0:
        ll.ramp_remove(S, b, s)
    if vi[b, VI_ACTIVE, s] == 1:
        wi[b, WI_N_ACTIVE] -= 1
        if vi[b, VI_RAMP, s] == 1:  # a ramp vehicle towed away before the merge point
            vi[b, VI_RAMP, s] = 0
            wi[b, WI_RAMP_TOWED] += 1
    vi[b, VI_ACTIVE, s] = 0


@kernel(inline=True)
def exits(S: tuple, b: int, p: np.ndarray) -> None:
    """Vehicles past the downstream end leave (the ego never does: its episode ends first)."""
    vf, vi, wf, wi, lanes, sched = S
    for lane in range(2):
        i = 0
        while i < wi[b, WI_N_RIGHT + lane]:
            s = lanes[b, lane, i]
            if vf[b, VF_X, s] <= p[P_X_EXIT]:
                break
            if s == EGO:
                i += 1
                continue
            deactivate(S, b, s)
            vi[b, VI_FLAGS, s] |= EV_EXITED
            wi[b, WI_EXITED] += 1


@kernel
def _safe_join(S: tuple, b: int, s: int, p: np.ndarray) -> bool:
    """Ramp vehicle `s` may join the right lane at its position now (`ramp.join = "when_safe"`):
    both bumper gaps above half the jam gap s0, and by IDM neither it (behind its new leader)
    nor its new follower (behind it) brakes harder than `safe_brake_mps2`. (Half: a driver that
    yields to a vehicle waiting at the lane's end stops about s0 behind it, and a check at s0
    would leave both waiting for ever.)"""
    vf, vi, wf, wi, lanes, sched = S
    dp = driver_params(p)
    length, s0, limit = p[P_LEN], 0.5 * p[P_S0], -p[P_SAFE_BRAKE]
    x, v = vf[b, VF_X, s], vf[b, VF_V, s]
    lead, follow = ll.neighbours_at(S, b, RIGHT, x)
    if lead >= 0:
        gap = vf[b, VF_X, lead] - length - x
        if gap <= s0 or _idm_of(S, b, s, gap, vf[b, VF_V, lead], dp) < limit:
            return False
    if follow >= 0:
        gap = x - length - vf[b, VF_X, follow]
        if gap <= s0 or _idm_of(S, b, follow, gap, v, dp) < limit:
            return False
    return True


@kernel
def ramp_joins(S: tuple, b: int, p: np.ndarray) -> None:
    """Ramp flow: ramp vehicles join the right lane (`joins_now`) and drive on as neutral
    mainline drivers; those past the merge point (x >= 0) count as passed, with their travel
    time from their drawn arrival at the ramp start."""
    vf, vi, wf, wi, lanes, sched = S
    i = 0
    while i < wi[b, WI_N_RAMP]:
        s = lanes[b, RAMP_LIST, i]
        flags = vi[b, VI_FLAGS, s]
        vi[b, VI_FLAGS, s] = flags & ~(EV_CHOOSES | EV_JOIN)
        if joins_now(S, b, p, s, (flags & EV_CHOOSES) != 0, (flags & EV_JOIN) != 0):
            ll.ramp_remove(S, b, s)
            vi[b, VI_LANE, s] = RIGHT
            vf[b, VF_SINCE_LC, s] = 0.0
            ll.insert(S, b, RIGHT, s)
            wi[b, WI_RAMP_JOINED] += 1
        else:
            i += 1
    for lane in range(2):
        for i in range(wi[b, WI_N_RIGHT + lane]):
            s = lanes[b, lane, i]
            if vf[b, VF_X, s] < 0.0:
                break
            if vi[b, VI_RAMP, s] == 1:
                vi[b, VI_RAMP, s] = 0
                wf[b, WF_RAMP_TRAVEL_SUM] += vf[b, VF_AGE, s]
                wi[b, WI_RAMP_PASSED] += 1


@kernel(inline=True)
def joins_now(S: tuple, b: int, p: np.ndarray, s: int, chooses: bool, wants: bool) -> bool:
    """Ramp vehicle `s` changes into the right lane at the end of this step: choosing its join
    (`ego.join = "chosen"`), when its command says so (`wants`) inside the merge zone; else by
    `ramp.join`: once it overlaps the lane ("forced", the paper's, also the ego's) or when the
    gap at its position is safe (`_safe_join`). Past the lane's end (x >= 0), which the lane-end
    braking rules out, it is joined by force."""
    vf, vi, wf, wi, lanes, sched = S
    x = vf[b, VF_X, s]
    if chooses:
        return x >= 0.0 or (wants and x >= p[P_X_ZONE_START])
    if p[P_RAMP_WHEN_SAFE] > 0.0:
        return x >= p[P_X_ZONE_START] and (x >= 0.0 or _safe_join(S, b, s, p))
    return x >= p[P_X_OVERLAP]


@kernel(inline=True)
def ego_join(S: tuple, b: int, p: np.ndarray, chooses: bool, wants: bool) -> None:
    """The ego becomes a right-lane vehicle once it joins (`joins_now`: by default once its body
    overlaps the lane)."""
    vf, vi, wf, wi, lanes, sched = S
    if vi[b, VI_ACTIVE, EGO] == 0:
        return
    if vi[b, VI_LANE, EGO] == RAMP and joins_now(S, b, p, EGO, chooses, wants):
        vi[b, VI_LANE, EGO] = RIGHT
        ll.insert(S, b, RIGHT, EGO)
    if vi[b, VI_LANE, EGO] == RIGHT:
        wf[b, WF_EGO_IN_LANE] += p[P_DT]
    else:
        wf[b, WF_EGO_IN_LANE] = 0.0


@kernel(inline=True)
def collisions(S: tuple, b: int, p: np.ndarray) -> tuple[bool, bool]:
    """Overlapping consecutive vehicles of a lane collide (gaps from `neighbours`). Returns
    whether the ego had a new collision and whether wrecks were towed away; the ego's partner
    and whether it was the rear vehicle go to `WI_EGO_PARTNER` / `WI_EGO_REAR`. Mainline wrecks
    are towed away at once (counted as background collisions); the ego's wreck and its partner
    stay, flagged, until `next_ego`."""
    vf, vi, wf, wi, lanes, sched = S
    ego_was_collided = vi[b, VI_COLLIDED, EGO] == 1
    ego_hit = False
    towed = 0
    for lane in range(2):
        for i in range(1, wi[b, WI_N_RIGHT + lane]):
            rear = lanes[b, lane, i]
            if vf[b, VF_GAP, rear] >= 0.0:
                continue
            front = lanes[b, lane, i - 1]
            vi[b, VI_FLAGS, rear] |= EV_COLLIDED | EV_HIT
            vi[b, VI_FLAGS, front] |= EV_COLLIDED | EV_HIT
            if rear == EGO or front == EGO:
                vi[b, VI_COLLIDED, rear] = 1
                vi[b, VI_COLLIDED, front] = 1
                if not ego_was_collided and not ego_hit:
                    ego_hit = True
                    wi[b, WI_EGO_PARTNER] = front if rear == EGO else rear
                    wi[b, WI_EGO_REAR] = 1 if rear == EGO else 0
            else:
                vi[b, VI_FLAGS, rear] |= EV_TOW
                vi[b, VI_FLAGS, front] |= EV_TOW
                if vi[b, VI_RAMP, rear] == 1 or vi[b, VI_RAMP, front] == 1:
                    wi[b, WI_RAMP_COLLISIONS] += 1
                else:
                    wi[b, WI_BG_COLLISIONS] += 1
                towed += 1
    if wi[b, WI_N_RAMP] > 1:
        towed += _ramp_collisions(S, b)
    if towed:
        for lane in range(2):
            i = 0
            while i < wi[b, WI_N_RIGHT + lane]:
                s = lanes[b, lane, i]
                if vi[b, VI_FLAGS, s] & EV_TOW and vi[b, VI_COLLIDED, s] == 0:
                    deactivate(S, b, s)
                else:
                    i += 1
        i = 0
        while i < wi[b, WI_N_RAMP]:
            s = lanes[b, RAMP_LIST, i]
            if vi[b, VI_FLAGS, s] & EV_TOW:
                deactivate(S, b, s)
            else:
                i += 1
    return ego_hit, towed > 0


@kernel
def _ramp_collisions(S: tuple, b: int) -> int:
    """Ramp flow: overlapping consecutive vehicles of the ramp collide (`WI_RAMP_COLLISIONS`)
    and are flagged to be towed away. Returns how many collisions."""
    vf, vi, wf, wi, lanes, sched = S
    n = 0
    for i in range(1, wi[b, WI_N_RAMP]):
        rear = lanes[b, RAMP_LIST, i]
        if vf[b, VF_GAP, rear] >= 0.0:
            continue
        front = lanes[b, RAMP_LIST, i - 1]
        vi[b, VI_FLAGS, rear] |= EV_COLLIDED | EV_HIT | EV_TOW
        vi[b, VI_FLAGS, front] |= EV_COLLIDED | EV_HIT | EV_TOW
        wi[b, WI_RAMP_COLLISIONS] += 1
        n += 1
    return n


@kernel(inline=True)
def ego_episode(S: tuple, b: int, p: np.ndarray, running: bool, ego_hit: bool) -> None:
    """The running ego's clocks and the outcome it reaches in this step (`WI_STEP_OUTCOME`)."""
    vf, vi, wf, wi, lanes, sched = S
    dt = p[P_DT]
    if not running:
        wf[b, WF_EGO_STALL] = 0.0
        return
    wf[b, WF_EGO_T] += dt
    if vf[b, VF_V, EGO] < p[P_STALL_SPEED]:
        wf[b, WF_EGO_STALL] += dt
    else:
        wf[b, WF_EGO_STALL] = 0.0
    outcome = OUTCOME_NONE
    if wf[b, WF_EGO_T] >= p[P_MAX_EPISODE] - 1e-9 or wf[b, WF_EGO_STALL] >= p[P_STALL_TIME] - 1e-9:
        outcome = OUTCOME_TRUNCATED
    if vf[b, VF_X, EGO] >= p[P_SUCCESS]:
        outcome = OUTCOME_SUCCESS
    if ego_hit:
        outcome = OUTCOME_COLLISION
    wi[b, WI_OUTCOME] = outcome
    wi[b, WI_STEP_OUTCOME] = outcome


@kernel(inline=True)
def gap_vehicles(S: tuple, b: int, p: np.ndarray, s: int) -> tuple:
    """Slot `s`'s gap-front and gap-back vehicles: its right-lane neighbours (its leader and
    follower once it is in the right lane, else those of its projection onto the lane), within
    the sensing range. A missing one is a virtual vehicle at the edge of the range driving at the
    speed limit. Returns (front, back, x_front, v_front, d_front, x_back, v_back, d_back): the
    slots (-1: virtual), positions, speeds and bumper gaps."""
    vf, vi, wf, wi, lanes, sched = S
    x = vf[b, VF_X, s]
    if vi[b, VI_LANE, s] == RIGHT:
        front, back = vi[b, VI_LEADER, s], vi[b, VI_FOLLOWER, s]
    else:
        front, back = ll.neighbours_at(S, b, RIGHT, x)
    rng, length, v_limit = p[P_SENSING], p[P_LEN], p[P_V_LIMIT]
    if front >= 0 and vf[b, VF_X, front] - x > rng:
        front = -1
    if back >= 0 and x - vf[b, VF_X, back] > rng:
        back = -1
    x_f, v_f, d_f = x + rng, v_limit, rng
    if front >= 0:
        x_f, v_f = vf[b, VF_X, front], vf[b, VF_V, front]
        d_f = vf[b, VF_X, front] - x - length
    x_b, v_b, d_b = x - rng, v_limit, rng
    if back >= 0:
        x_b, v_b = vf[b, VF_X, back], vf[b, VF_V, back]
        d_b = x - vf[b, VF_X, back] - length
    return front, back, x_f, v_f, d_f, x_b, v_b, d_b


@kernel(inline=True)
def ego_gaps(S: tuple, b: int, p: np.ndarray) -> None:
    """The ego's gap-front and gap-back vehicles (`gap_vehicles`) into `WI_FRONT`/`WI_BACK` and
    the `WF_XF` ... `WF_VB` rows."""
    vf, vi, wf, wi, lanes, sched = S
    front, back, x_f, v_f, d_f, x_b, v_b, d_b = gap_vehicles(S, b, p, EGO)
    wi[b, WI_FRONT], wi[b, WI_BACK] = front, back
    wf[b, WF_XF], wf[b, WF_DF], wf[b, WF_VF] = x_f, d_f, v_f
    wf[b, WF_XB], wf[b, WF_DB], wf[b, WF_VB] = x_b, d_b, v_b


# ----------------------------------------------------------------------------------------------
# After each simulator step: the ego's trace and terms, the highway agents' terms
# ----------------------------------------------------------------------------------------------


@kernel(inline=True)
def _trace_row(S: tuple, b: int, trace: np.ndarray, i: int) -> None:
    """The ego after a step, with the metrics' conventions (no gap vehicle: inf gap, nan speed)."""
    vf, vi, wf, wi, lanes, sched = S
    front, back = wi[b, WI_FRONT], wi[b, WI_BACK]
    trace[b, i, TR_X] = vf[b, VF_X, EGO]
    trace[b, i, TR_V] = vf[b, VF_V, EGO]
    trace[b, i, TR_A] = vf[b, VF_A, EGO]
    trace[b, i, TR_DF] = wf[b, WF_DF] if front >= 0 else INF
    trace[b, i, TR_VF] = wf[b, WF_VF] if front >= 0 else NAN
    trace[b, i, TR_DB] = wf[b, WF_DB] if back >= 0 else INF
    trace[b, i, TR_VB] = wf[b, WF_VB] if back >= 0 else NAN
    trace[b, i, TR_AB] = vf[b, VF_A, back] if back >= 0 else NAN
    trace[b, i, TR_HIT] = 1.0 if vi[b, VI_FLAGS, EGO] & EV_HIT else 0.0


@kernel(inline=True)
def _roster_step(
    S: tuple, b: int, p: np.ndarray, roster: np.ndarray, hw_terms: np.ndarray, live: bool
) -> None:
    """Add the step's terms of every counting highway agent (while the ego runs; with ramp flow,
    of every ramp agent: the ego's `EGO_TERMS` for its own merge, with its realised acceleration
    and no jerk term), then let go of the agents that left the road: towed away after a
    collision, or off the downstream end (`RO_EXITED`)."""
    vf, vi, wf, wi, lanes, sched = S
    x_e, v_e = vf[b, VF_X, EGO], vf[b, VF_V, EGO]
    close_f, close_b = ego_closeness(p, x_e, v_e, wf[b, WF_DF], wf[b, WF_DB], wf[b, WF_VB])
    blamed = ego_to_blame(p, wi[b, WI_EGO_REAR] == 1, wf[b, WF_EGO_IN_LANE])
    truncated = wi[b, WI_STEP_OUTCOME] == OUTCOME_TRUNCATED
    flowing = p[P_RAMP_FLOW] > 0.0
    for j in range(roster.shape[2]):
        s = roster[RO_SLOT, b, j]
        if roster[RO_MASK, b, j] == 0 or s <= EGO:
            continue
        same = vi[b, VI_ID, s] == roster[RO_ID, b, j]
        if flowing and same:  # a ramp agent: the ego's terms, for its own merge
            _, _, _, _, d_f, _, v_b, d_b = gap_vehicles(S, b, p, s)
            d_f, d_b = merge_gaps(p, vi[b, VI_LANE, s] == RAMP, d_f, d_b)
            add_ego_terms(
                p, hw_terms[:, j], b, vf[b, VF_A, s], vf[b, VF_X, s], vf[b, VF_V, s], d_f, d_b,
                v_b, (vi[b, VI_FLAGS, s] & EV_HIT) != 0, 0.0,
            )  # fmt: skip
        elif live and same:
            add_highway_terms(
                p,
                hw_terms,
                b,
                j,
                vf[b, VF_A, s],
                vf[b, VF_V, s],
                vf[b, VF_GAP, s],
                (vi[b, VI_FLAGS, s] & EV_HIT) != 0,
                s == wi[b, WI_EGO_PARTNER],
                blamed,
                s == wi[b, WI_FRONT],
                s == wi[b, WI_BACK],
                vf[b, VF_A, EGO],
                truncated,
                close_f,
                close_b,
            )
        if not same or vi[b, VI_ACTIVE, s] == 0:
            roster[RO_MASK, b, j] = 0
            # a slot freed at the exit can be refilled by an arrival in the same step; a towed
            # wreck's slot cannot (towing comes after the arrivals)
            if not same or vi[b, VI_FLAGS, s] & EV_EXITED:
                roster[RO_EXITED, b, j] = 1


# ----------------------------------------------------------------------------------------------
# k simulator steps of one world
# ----------------------------------------------------------------------------------------------


@kernel
def run_steps(
    S: tuple,
    X: tuple,
    b: int,
    p: np.ndarray,
    k: int,
    ego_cmd: np.ndarray,
    roster: np.ndarray,
    roster_cmd: np.ndarray,
    ego_terms: np.ndarray,
    hw_terms: np.ndarray,
    trace: np.ndarray,
) -> tuple[int, int, int, int, int]:
    """Up to `k` simulator steps of world `b` (see the module docstring), stopping early when a
    running ego's episode ends: the ego's command ego_cmd[b] (acceleration m/s^2, and with
    `ego.join = "chosen"` the join command: > 0 joins now, NaN joins by force), the agents'
    roster_cmd [B, K, 2]. After each step: the sensor's measurement, the ego's trace row
    trace[b, i], its terms added into ego_terms[b] while it runs, the agents' into hw_terms[b].
    Needs the neighbours of the pre-step state (every step leaves them computed). Returns the
    outcome reached, the ego's collision partner and rear flag, the steps run and the ego's.

    The k steps are one compiled function with everything a step calls inlined: a call per
    step passed 178 machine words (the state's arrays, the roster, the parameters), about a
    seventh of the kernel's time at 400 veh/h/lane."""
    vf, vi, wf, wi, lanes, sched = S
    outcome, partner, rear, steps, ego_steps = OUTCOME_NONE, -1, 0, 0, 0
    started = vi[b, VI_ACTIVE, EGO] == 1 and wi[b, WI_OUTCOME] == OUTCOME_NONE
    for i in range(k):
        live = vi[b, VI_ACTIVE, EGO] == 1 and wi[b, WI_OUTCOME] == OUTCOME_NONE
        if started and not live:
            break
        a_prev, first = wf[b, WF_EGO_CMD], wf[b, WF_EGO_T] <= 0.0  # the ego's last step
        # one simulator step, in the order of the module docstring
        wi[b, WI_EGO_PARTNER], wi[b, WI_EGO_REAR], wi[b, WI_STEP_OUTCOME] = -1, 0, OUTCOME_NONE
        mark_controlled(S, b, p, roster, roster_cmd)
        n_changes = 0
        if wi[b, WI_STEPS] % int(p[P_LC_EVERY]) == 0:
            n_changes = lane_change_decisions(S, b, p)
        ego_chooses = p[P_JOIN_CHOSEN] > 0.0 and not math.isnan(ego_cmd[b, 1])
        wi[b, WI_VEH_STEPS] += advance(S, b, p, ego_cmd[b, 0], ego_chooses)
        wf[b, WF_T] += p[P_DT]
        wi[b, WI_STEPS] += 1
        if n_changes:
            apply_lane_changes(S, b)
        for lane in range(2):
            ll.resort(S, b, lane)
        exits(S, b, p)
        arrivals(S, b, p)
        ego_join(S, b, p, ego_chooses, ego_chooses and ego_cmd[b, 1] > 0.0)
        if p[P_RAMP_FLOW] > 0.0:
            ramp_joins(S, b, p)
        running = vi[b, VI_ACTIVE, EGO] == 1 and wi[b, WI_OUTCOME] == OUTCOME_NONE
        neighbours(S, b, p)
        ego_hit, towed = collisions(S, b, p)
        if towed:
            neighbours(S, b, p)  # the towed wrecks are gone
        ego_episode(S, b, p, running, ego_hit)
        ego_gaps(S, b, p)
        # after it: the sensor, the ego's trace and terms, the agents' terms
        if p[P_SENSE_ON] > 0.0 and vi[b, VI_ACTIVE, EGO] == 1:
            sense_measure(S, X, b, p)
        _trace_row(S, b, trace, i)
        if live:
            ego_steps += 1
            d_f, d_b = merge_gaps(p, vi[b, VI_LANE, EGO] == RAMP, wf[b, WF_DF], wf[b, WF_DB])
            add_ego_terms(
                p, ego_terms, b, wf[b, WF_EGO_CMD], vf[b, VF_X, EGO], vf[b, VF_V, EGO],
                d_f, d_b, wf[b, WF_VB], ego_hit,
                0.0 if first else wf[b, WF_EGO_CMD] - a_prev,
            )  # fmt: skip
        _roster_step(S, b, p, roster, hw_terms, live)
        if wi[b, WI_STEP_OUTCOME] != OUTCOME_NONE:
            outcome = wi[b, WI_STEP_OUTCOME]
            partner, rear = wi[b, WI_EGO_PARTNER], wi[b, WI_EGO_REAR]
        steps = i + 1
    return outcome, partner, rear, steps, ego_steps
