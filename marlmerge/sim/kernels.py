"""The compiled calls of the core: what one env step needs, and the ego's and roster's life cycle.

`rollout` holds the ego commands for `k` simulator steps (`marlmerge.sim.step.run_steps`) in every
world and, after each step, adds up the named reward terms of the ego and of the highway agents
(`marlmerge.sim.reward`) and records the ego's trace; at the end it writes the observations
(`marlmerge.sim.observation` order). A world whose ego was running stops stepping within the
call once its ego's episode ends, so one world of a batch and a single world step alike.
`rollout_parallel` is the same over worlds in parallel threads (worlds are independent).
With imperfect sensing (`[sensing]`) the ego's sensor measures after every simulator step and
the observation is the delayed measurement (`marlmerge.sim.sensing`); `X = (ring, noise)` is its
state (`marlmerge.sim.layout`).

The calls over many worlds take the parameters per world, `p [B, P]` (`marlmerge.sim.layout.P`;
every row the same unless the worlds draw their own traffic, `[sample]`), and hand world `b` its
row `p[b]`.

The drivers return how many worlds need the Python side before another call of the same `k`
(more slots, more drawn arrivals or ego departures): the core serves them between calls.
"""

from __future__ import annotations

import math

import numpy as np
from numba import prange

from marlmerge.sim import lanes as ll
from marlmerge.sim.entrance import free_slot
from marlmerge.sim.jit import kernel
from marlmerge.sim.layout import (
    EGO,
    EGO_STREAM,
    NEUTRAL,
    OUTCOME_NONE,
    OUTCOME_SUCCESS,
    P_DT,
    P_EGO_T,
    P_LC_COOLDOWN,
    P_NOISE_ON,
    P_OBS_EXTENDED,
    P_OBS_ON_RAMP,
    P_POSITION_SCALE,
    P_RAMP_FLOW,
    P_SENSE_ON,
    P_SENSING,
    P_SPEED_SCALE,
    P_V_LIMIT,
    P_X_RAMP_START,
    RAMP,
    RAMP_LIST,
    RIGHT,
    RO_EXITED,
    RO_ID,
    RO_MASK,
    RO_SLOT,
    SC_POL,
    SC_T,
    SC_T_HW,
    SC_V,
    SC_V0,
    VF_A,
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
    VI_PROFILE,
    WF_AFTER_POL,
    WF_AFTER_T,
    WF_AFTER_V0,
    WF_EGO_CMD,
    WF_EGO_IN_LANE,
    WF_EGO_STALL,
    WF_EGO_T,
    WF_T,
    WI_COUNT_EGO,
    WI_COUNT_RIGHT,
    WI_EGO_COUNT,
    WI_EGO_PARTNER,
    WI_EGO_REAR,
    WI_EGO_STEPS,
    WI_FILTER_COUNT,
    WI_HEAD_RIGHT,
    WI_N_ACTIVE,
    WI_N_RAMP,
    WI_N_RIGHT,
    WI_NEED,
    WI_NEXT_ID,
    WI_NOISE_COUNT,
    WI_OUTCOME,
    WI_OVERFLOW,
    WI_STEP_OUTCOME,
    WI_SUBSTEPS,
)
from marlmerge.sim.sensing import (
    agent_extended,
    ego_observation,
    sense_fill,
    sensed_output,
)
from marlmerge.sim.step import (
    deactivate,
    ego_gaps,
    gap_vehicles,
    neighbours,
    run_steps,
)

INF = math.inf
OVERFLOW = 1 << 32
"""Added to a driver's return value for each world that ran out of slots or drawn vehicles."""


# ----------------------------------------------------------------------------------------------
# Observations
# ----------------------------------------------------------------------------------------------


@kernel(inline=True)
def observe_world(
    S: tuple,
    X: tuple,
    b: int,
    p: np.ndarray,
    roster: np.ndarray,
    ego_obs: np.ndarray,
    hw_obs: np.ndarray,
) -> None:
    """Scaled observations of world `b`: the ego's features (`ego_features(cfg)`: exact, or the
    sensor's delayed measurement) into ego_obs[b] and each counting roster agent's
    `HIGHWAY_FEATURES` into hw_obs[b, j] (zeros where not counting)."""
    vf, vi, wf, wi, lanes, sched = S
    ss, ps = p[P_SPEED_SCALE], p[P_POSITION_SCALE]
    v_limit, rng = p[P_V_LIMIT], p[P_SENSING]
    x_e, v_e = vf[b, VF_X, EGO], vf[b, VF_V, EGO]
    if p[P_SENSE_ON] > 0.0:
        sensed_output(S, X, b, p, ego_obs)
    else:
        ego_observation(S, b, p, ego_obs, b, X[1], -1)
    ego_on = vi[b, VI_ACTIVE, EGO] == 1
    ego_in_lane = 1.0 if ego_on and vi[b, VI_LANE, EGO] == RIGHT else 0.0
    for j in range(roster.shape[2]):
        s = roster[RO_SLOT, b, j]
        if roster[RO_MASK, b, j] == 0 or s <= EGO:
            for c in range(hw_obs.shape[2]):
                hw_obs[b, j, c] = 0.0
            continue
        v = vf[b, VF_V, s]
        f = vi[b, VI_FOLLOWER, s]
        gap_back = vf[b, VF_GAP, f] if f >= 0 else INF
        hw_obs[b, j, 0], hw_obs[b, j, 1] = v / ss, float(vi[b, VI_LANE, s])
        hw_obs[b, j, 2], hw_obs[b, j, 3] = min(vf[b, VF_GAP, s], rng) / ps, vf[b, VF_VLEAD, s] / ss
        hw_obs[b, j, 4], hw_obs[b, j, 5] = (
            min(gap_back, rng) / ps,
            (vf[b, VF_V, f] if f >= 0 else v) / ss,
        )
        hw_obs[b, j, 6], hw_obs[b, j, 7] = (x_e - vf[b, VF_X, s]) / ps, v_e / ss
        hw_obs[b, j, 8], hw_obs[b, j, 9] = -x_e / ps, ego_in_lane
        hw_obs[b, j, 10], hw_obs[b, j, 11] = 1.0 if ego_on else 0.0, v_limit / ss


# ----------------------------------------------------------------------------------------------
# One env step of one world, and the drivers over worlds
# ----------------------------------------------------------------------------------------------


@kernel(inline=True)
def _needs_service(S: tuple, b: int, p: np.ndarray, k: int) -> int:
    """1 if world `b` needs the Python side before another call of `k` steps (also `WI_NEED`):
    too few free slots (two arrivals a step, and one merged ego from a `next_ego` in between),
    drawn arrivals ending within the horizon, or fewer than two drawn ego departures left (one
    for a `next_ego` in between, one for the next)."""
    vf, vi, wf, wi, lanes, sched = S
    need = _short(S, b, p, k)
    wi[b, WI_NEED] = need
    return need


@kernel(inline=True)
def _short(S: tuple, b: int, p: np.ndarray, k: int) -> int:
    vf, vi, wf, wi, lanes, sched = S
    flowing = p[P_RAMP_FLOW] > 0.0  # ramp flow: a third stream of arrivals, the ramp's
    if wi[b, WI_N_ACTIVE] + (3 if flowing else 2) * k + 3 > vi.shape[2]:
        return 1
    if p[P_NOISE_ON] > 0.0 and wi[b, WI_NOISE_COUNT] < k + 2:
        return 1  # drawn measurement errors for k steps and one departure
    q_len = sched.shape[2]
    horizon = wf[b, WF_T] + (k + 1) * p[P_DT]
    for stream in range(3 if flowing else 2):
        count = wi[b, WI_COUNT_RIGHT + stream]
        last = (wi[b, WI_HEAD_RIGHT + stream] + count - 1) % q_len
        if count == 0 or count + 1 >= q_len or sched[b, stream, last, SC_T] <= horizon:
            return 1
    return 1 if wi[b, WI_COUNT_RIGHT + EGO_STREAM] < 2 else 0


@kernel
def rollout_world(
    S: tuple,
    X: tuple,
    b: int,
    p: np.ndarray,
    k: int,
    step_mask: np.ndarray,
    ego_cmd: np.ndarray,
    roster: np.ndarray,
    roster_cmd: np.ndarray,
    ego_terms: np.ndarray,
    hw_terms: np.ndarray,
    trace: np.ndarray,
    ego_obs: np.ndarray,
    hw_obs: np.ndarray,
    call_out: np.ndarray,
) -> int:
    """Up to `k` simulator steps of world `b` with the ego command ego_cmd[b] (acceleration,
    join: `run_steps`) and the agents' roster_cmd[b] [K, 2] (see the module docstring). Outputs:
    ego_terms[b] [len(EGO_TERMS)], hw_terms[b] [K, 8], trace[b, :k] [TR_COLS], the
    observations, and per world `WI_SUBSTEPS`, the outcome reached (`WI_STEP_OUTCOME`) with the
    ego's collision partner, also copied to call_out[:, b] (the `WI_CALL` columns). Returns
    `_needs_service`, plus `OVERFLOW` if the world overflowed."""
    vf, vi, wf, wi, lanes, sched = S
    for s in range(vi.shape[2]):
        vi[b, VI_FLAGS, s] = 0
    for c in range(ego_terms.shape[1]):
        ego_terms[b, c] = 0.0
    for j in range(roster.shape[2]):
        roster[RO_EXITED, b, j] = 0
        for c in range(hw_terms.shape[2]):
            hw_terms[b, j, c] = 0.0
    outcome, partner, rear, steps, ego_steps = OUTCOME_NONE, -1, 0, 0, 0
    if step_mask[b]:
        outcome, partner, rear, steps, ego_steps = run_steps(
            S, X, b, p, k, ego_cmd, roster, roster_cmd, ego_terms, hw_terms, trace
        )
    wi[b, WI_STEP_OUTCOME], wi[b, WI_EGO_PARTNER], wi[b, WI_EGO_REAR] = outcome, partner, rear
    wi[b, WI_SUBSTEPS], wi[b, WI_EGO_STEPS] = steps, ego_steps
    for c in range(call_out.shape[0]):  # [5, B]: the call's WI_CALL columns, while they are hot
        call_out[c, b] = wi[b, WI_STEP_OUTCOME + c]
    observe_world(S, X, b, p, roster, ego_obs, hw_obs)
    return _needs_service(S, b, p, k) + OVERFLOW * wi[b, WI_OVERFLOW]


@kernel
def rollout(
    S: tuple,
    X: tuple,
    lo: int,
    hi: int,
    p: np.ndarray,
    k: int,
    step_mask: np.ndarray,
    ego_cmd: np.ndarray,
    roster: np.ndarray,
    roster_cmd: np.ndarray,
    ego_terms: np.ndarray,
    hw_terms: np.ndarray,
    trace: np.ndarray,
    ego_obs: np.ndarray,
    hw_obs: np.ndarray,
    call_out: np.ndarray,
) -> int:
    """`rollout_world` for the worlds lo..hi-1, one after the other. Returns the sum of their
    statuses (how many need service, plus `OVERFLOW` for each that overflowed)."""
    vf, vi, wf, wi, lanes, sched = S
    status = 0
    for b in range(lo, hi):
        status += rollout_world(
            S,
            X,
            b,
            p[b],
            k,
            step_mask,
            ego_cmd,
            roster,
            roster_cmd,
            ego_terms,
            hw_terms,
            trace,
            ego_obs,
            hw_obs,
            call_out,
        )
    return status


@kernel(parallel=True)
def rollout_parallel(
    S: tuple,
    X: tuple,
    n_chunks: int,
    p: np.ndarray,
    k: int,
    step_mask: np.ndarray,
    ego_cmd: np.ndarray,
    roster: np.ndarray,
    roster_cmd: np.ndarray,
    ego_terms: np.ndarray,
    hw_terms: np.ndarray,
    trace: np.ndarray,
    ego_obs: np.ndarray,
    hw_obs: np.ndarray,
    call_out: np.ndarray,
) -> int:
    """`rollout` over `n_chunks` equal chunks of the worlds in parallel threads: the same
    results as one serial call, since worlds are independent."""
    n = S[0].shape[0]
    status = 0
    for c in prange(n_chunks):
        status += rollout(
            S,
            X,
            (c * n) // n_chunks,
            ((c + 1) * n) // n_chunks,
            p,
            k,
            step_mask,
            ego_cmd,
            roster,
            roster_cmd,
            ego_terms,
            hw_terms,
            trace,
            ego_obs,
            hw_obs,
            call_out,
        )
    return status


@kernel
def observe(
    S: tuple,
    X: tuple,
    p: np.ndarray,
    roster: np.ndarray,
    ego_obs: np.ndarray,
    hw_obs: np.ndarray,
) -> None:
    """`observe_world` for every world."""
    for b in range(S[0].shape[0]):
        observe_world(S, X, b, p[b], roster, ego_obs, hw_obs)


@kernel
def sense_restart(S: tuple, X: tuple, p: np.ndarray, mask: np.ndarray) -> None:
    """A fresh sensor history in the worlds of `mask` whose ego is on the road (after a scene
    was set up by hand)."""
    vf, vi, wf, wi, lanes, sched = S
    for b in range(vf.shape[0]):
        if mask[b] and vi[b, VI_ACTIVE, EGO] == 1:
            sense_fill(S, X, b, p[b])


# ----------------------------------------------------------------------------------------------
# The ego's life cycle, the roster, and rebuilding the lane lists
# ----------------------------------------------------------------------------------------------


@kernel
def _tow_wrecks(S: tuple, b: int) -> None:
    vf, vi, wf, wi, lanes, sched = S
    for s in range(1, vi.shape[2]):
        if vi[b, VI_COLLIDED, s] == 1:
            deactivate(S, b, s)
            vi[b, VI_COLLIDED, s] = 0


@kernel
def _keep_merged_ego(S: tuple, b: int, p: np.ndarray) -> None:
    """A merged ego stays on the road as a neutral mainline driver in a free slot, in its place."""
    vf, vi, wf, wi, lanes, sched = S
    s = free_slot(S, b)
    if s < 0:
        wi[b, WI_OVERFLOW] = 1
        return
    vf[b, VF_X, s], vf[b, VF_V, s], vf[b, VF_A, s] = vf[b, VF_X, EGO], vf[b, VF_V, EGO], 0.0
    vf[b, VF_V0, s], vf[b, VF_T, s] = wf[b, WF_AFTER_V0], wf[b, WF_AFTER_T]
    vf[b, VF_POL, s] = wf[b, WF_AFTER_POL]
    vf[b, VF_SINCE_LC, s], vf[b, VF_AGE, s] = p[P_LC_COOLDOWN], vf[b, VF_AGE, EGO]
    vf[b, VF_LAPSE, s] = 0.0
    vi[b, VI_LANE, s], vi[b, VI_ACTIVE, s], vi[b, VI_PROFILE, s] = RIGHT, 1, NEUTRAL
    vi[b, VI_ID, s], vi[b, VI_COLLIDED, s], vi[b, VI_FLAGS, s] = wi[b, WI_NEXT_ID], 0, 0
    wi[b, WI_NEXT_ID] += 1
    wi[b, WI_N_ACTIVE] += 1
    ll.replace(S, b, RIGHT, EGO, s)
    vi[b, VI_LANE, EGO] = RAMP  # no longer in a lane list


@kernel
def next_ego_world(S: tuple, X: tuple, b: int, p: np.ndarray) -> None:
    """End the current ego of world `b` and send the next drawn one from the ramp start (with a
    fresh sensor history when sensing is imperfect).

    A merged ego stays on the road; after a collision the ego and the vehicles it hit are towed
    away; a truncated ego is removed."""
    vf, vi, wf, wi, lanes, sched = S
    if vi[b, VI_ACTIVE, EGO] == 1 and wi[b, WI_OUTCOME] == OUTCOME_SUCCESS:
        _keep_merged_ego(S, b, p)
    _tow_wrecks(S, b)
    deactivate(S, b, EGO)
    vi[b, VI_COLLIDED, EGO] = 0
    stream = EGO_STREAM
    if wi[b, WI_COUNT_RIGHT + stream] < 1:
        wi[b, WI_OVERFLOW] = 1
        return
    head = wi[b, WI_HEAD_RIGHT + stream]
    wi[b, WI_HEAD_RIGHT + stream] = (head + 1) % sched.shape[2]
    wi[b, WI_COUNT_RIGHT + stream] -= 1
    vf[b, VF_X, EGO], vf[b, VF_V, EGO], vf[b, VF_A, EGO] = (
        p[P_X_RAMP_START],
        sched[b, stream, head, SC_V],
        0.0,
    )
    vf[b, VF_V0, EGO], vf[b, VF_T, EGO], vf[b, VF_POL, EGO] = p[P_V_LIMIT], p[P_EGO_T], 0.0
    vf[b, VF_SINCE_LC, EGO], vf[b, VF_AGE, EGO] = 0.0, 0.0
    wf[b, WF_AFTER_V0], wf[b, WF_AFTER_T], wf[b, WF_AFTER_POL] = (
        sched[b, stream, head, SC_V0],
        sched[b, stream, head, SC_T_HW],
        sched[b, stream, head, SC_POL],
    )
    vi[b, VI_LANE, EGO], vi[b, VI_ACTIVE, EGO], vi[b, VI_PROFILE, EGO] = RAMP, 1, NEUTRAL
    vi[b, VI_ID, EGO], vi[b, VI_FLAGS, EGO] = wi[b, WI_NEXT_ID], 0
    wi[b, WI_NEXT_ID] += 1
    wi[b, WI_N_ACTIVE] += 1
    wf[b, WF_EGO_T], wf[b, WF_EGO_STALL], wf[b, WF_EGO_IN_LANE] = 0.0, 0.0, 0.0
    wf[b, WF_EGO_CMD] = 0.0
    wi[b, WI_OUTCOME] = OUTCOME_NONE
    wi[b, WI_EGO_COUNT] += 1
    wi[b, WI_FILTER_COUNT] = 0
    neighbours(S, b, p)
    ego_gaps(S, b, p)
    if p[P_SENSE_ON] > 0.0:
        sense_fill(S, X, b, p)


@kernel
def remove_ego_world(S: tuple, b: int, p: np.ndarray) -> None:
    """Take the ramp vehicle (and any wreck it left) off the road: a traffic-only world."""
    vf, vi, wf, wi, lanes, sched = S
    _tow_wrecks(S, b)
    deactivate(S, b, EGO)
    vi[b, VI_COLLIDED, EGO] = 0
    wi[b, WI_OUTCOME] = OUTCOME_NONE
    neighbours(S, b, p)
    ego_gaps(S, b, p)


@kernel
def next_ego(
    S: tuple, X: tuple, p: np.ndarray, mask: np.ndarray, noise_need: np.ndarray, check: bool
) -> int:
    """`next_ego_world` for the worlds of `mask`, if each has a drawn departure, room for two
    more vehicles and at least `noise_need[b]` drawn measurement errors; otherwise nothing, the
    worlds short of them flagged `WI_NEED`, and -1 (the Python side draws ahead for them, then
    calls again with `check` false: no checks). Returns the worlds that overflowed."""
    vf, vi, wf, wi, lanes, sched = S
    n_slots = vi.shape[2]
    short = False
    for b in range(vf.shape[0]):
        if (
            check
            and mask[b]
            and (
                wi[b, WI_COUNT_EGO] < 1
                or wi[b, WI_N_ACTIVE] + 2 >= n_slots
                or wi[b, WI_NOISE_COUNT] < noise_need[b]
            )
        ):
            wi[b, WI_NEED] = 1
            short = True
    if short:
        return -1
    overflowed = 0
    for b in range(vf.shape[0]):
        if mask[b]:
            next_ego_world(S, X, b, p[b])
        overflowed += wi[b, WI_OVERFLOW]
    return overflowed


@kernel
def remove_ego(S: tuple, p: np.ndarray, mask: np.ndarray) -> None:
    """`remove_ego_world` for the worlds of `mask`."""
    for b in range(S[0].shape[0]):
        if mask[b]:
            remove_ego_world(S, b, p[b])


@kernel
def pick_roster(S: tuple, out: np.ndarray) -> None:
    """out [B, K]: the right-lane vehicles whose arrival time at the merge point (at current
    speeds, at least 1 m/s) is closest to the ego's, nearest first (ties: lower slot first);
    -1 where the lane holds fewer than K."""
    vf, vi, wf, wi, lanes, sched = S
    k = out.shape[1]
    for b in range(vf.shape[0]):
        t_e = -vf[b, VF_X, EGO] / max(vf[b, VF_V, EGO], 1.0)
        for j in range(k):
            best, best_d = -1, INF
            for i in range(wi[b, WI_N_RIGHT]):
                s = lanes[b, RIGHT, i]
                if s == EGO or _in(out, b, j, s):
                    continue
                d = abs(-vf[b, VF_X, s] / max(vf[b, VF_V, s], 1.0) - t_e)
                if d < best_d or (d == best_d and s < best):
                    best, best_d = s, d
            out[b, j] = best


@kernel
def _in(out: np.ndarray, b: int, j: int, s: int) -> bool:
    """s is among out[b, :j]."""
    for i in range(j):
        if out[b, i] == s:
            return True
    return False


@kernel
def _rebuild_ramp(S: tuple, b: int) -> int:
    """The ramp list of world `b` from scratch (ramp flow): every active vehicle on the ramp but
    the ego, downstream first. Returns how many."""
    vf, vi, wf, wi, lanes, sched = S
    n = 0
    for s in range(1, vi.shape[2]):
        if vi[b, VI_ACTIVE, s] == 1 and vi[b, VI_LANE, s] == RAMP:
            i = n
            while i > 0 and vf[b, VF_X, lanes[b, RAMP_LIST, i - 1]] < vf[b, VF_X, s]:
                lanes[b, RAMP_LIST, i] = lanes[b, RAMP_LIST, i - 1]
                i -= 1
            lanes[b, RAMP_LIST, i] = s
            n += 1
    for i in range(n, lanes.shape[2]):
        lanes[b, RAMP_LIST, i] = -1
    wi[b, WI_N_RAMP] = n
    return n


@kernel
def ramp_agents(S: tuple, X: tuple, p: np.ndarray, rows: np.ndarray, obs: np.ndarray) -> None:
    """Ramp flow: the first K vehicles of each world's ramp list (downstream first) as agents,
    rows [RO_ROWS, B, K] (slot, id, mask; -1 / 0 where the ramp holds fewer), and what each
    sees, obs [B, K, F] (`observe_agents`)."""
    vf, vi, wf, wi, lanes, sched = S
    for b in range(vf.shape[0]):
        for j in range(rows.shape[2]):
            rows[RO_EXITED, b, j] = 0
            if j >= wi[b, WI_N_RAMP]:
                rows[RO_SLOT, b, j], rows[RO_ID, b, j], rows[RO_MASK, b, j] = -1, -1, 0
            else:
                s = lanes[b, RAMP_LIST, j]
                rows[RO_SLOT, b, j], rows[RO_ID, b, j], rows[RO_MASK, b, j] = s, vi[b, VI_ID, s], 1
    observe_agents(S, X, p, rows, obs)


@kernel
def observe_agents(S: tuple, X: tuple, p: np.ndarray, rows: np.ndarray, obs: np.ndarray) -> None:
    """Ramp flow: what each masked agent of rows [RO_ROWS, B, K] sees, obs [B, K, F], in the
    ego's layout with perfect sensing: the paper's seven features with its gap vehicles as
    `gap_vehicles` finds them, the extended columns (`agent_extended`), then `on_ramp` with
    `ego.join = "chosen"` (zeros where masked; `marlmerge.sim.observation.ramp_agent_features`)."""
    vf, vi, wf, wi, lanes, sched = S
    for b in range(vf.shape[0]):
        pb = p[b]
        ss, ps, v_limit = pb[P_SPEED_SCALE], pb[P_POSITION_SCALE], pb[P_V_LIMIT]
        for j in range(rows.shape[2]):
            s = rows[RO_SLOT, b, j]
            if rows[RO_MASK, b, j] == 0 or s < 0 or vi[b, VI_ID, s] != rows[RO_ID, b, j]:
                for c in range(obs.shape[2]):
                    obs[b, j, c] = 0.0
                continue
            gap = gap_vehicles(S, b, pb, s)
            _, _, x_f, v_f, _, x_b, v_b, _ = gap
            obs[b, j, 0], obs[b, j, 1] = vf[b, VF_V, s] / ss, vf[b, VF_X, s] / ps
            obs[b, j, 2], obs[b, j, 3] = v_f / ss, x_f / ps
            obs[b, j, 4], obs[b, j, 5] = v_b / ss, x_b / ps
            obs[b, j, 6] = v_limit / ss
            if pb[P_OBS_EXTENDED] > 0.0:
                agent_extended(S, X, b, pb, obs[b], j, s, gap)
            if pb[P_OBS_ON_RAMP] > 0.0:  # ego.join = "chosen": on_ramp
                obs[b, j, int(pb[P_OBS_ON_RAMP])] = 1.0 if vi[b, VI_LANE, s] == RAMP else 0.0


@kernel
def rebuild_lanes(S: tuple, p: np.ndarray, mask: np.ndarray) -> None:
    """Lane lists of the worlds of `mask` from scratch (after placing vehicles directly): every
    active vehicle with a highway lane, downstream first (equal positions: lower slot first)."""
    vf, vi, wf, wi, lanes, sched = S
    for b in range(vf.shape[0]):
        if not mask[b]:
            continue
        n_active = 0
        for lane in range(2):
            n = 0
            for s in range(vi.shape[2]):
                if vi[b, VI_ACTIVE, s] == 1 and vi[b, VI_LANE, s] == lane:
                    lanes[b, lane, n] = s
                    n += 1
            wi[b, WI_N_RIGHT + lane] = n
            n_active += n
            for i in range(n, lanes.shape[2]):
                lanes[b, lane, i] = -1
            ll.resort(S, b, lane)  # stable: equal positions keep slot order
        if vi[b, VI_ACTIVE, EGO] == 1 and vi[b, VI_LANE, EGO] == RAMP:
            n_active += 1
        n_active += _rebuild_ramp(S, b)
        wi[b, WI_N_ACTIVE] = n_active
        neighbours(S, b, p[b])
        ego_gaps(S, b, p[b])
