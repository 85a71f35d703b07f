"""Attention lapses of mainline drivers (`driver.lapse_rate_per_h`, `driver.lapse_s`), compiled.

In each simulator step an attentive scripted mainline driver begins a lapse with probability
p = 1 - exp(-rate dt) (`layout.lapse_step_probability`); a lapsing driver holds its speed (no
acceleration, no braking, no lane change) for `lapse_s`, whatever is ahead of it. The draw is
counter-based (`lapse_uniform`: a hash of the world's lapse key, the step and the vehicle id),
so a world with lapses off draws nothing and its numbers are those of a core without them.

Importance sampling (`marlmerge.sim.proposal`): while the ego runs in the merge zone, the
driver behind its gap (`WI_BACK`) begins a lapse with the proposal's probability q_c of its
class c instead of p (`P_LAPSE_Q + c`; `lapse_class`: how soon such a lapse could close its gap
to the ego; lapses that could not are drawn naturally and collisions come from the others),
until one such lapse has begun since the world's reset (the
estimate runs one ego per world): later draws are natural, so a collision is not paid for with
a second, needless lapse. The world keeps the exact log p/q_c of each tilted draw
(`WF_LAPSE_LOGW`: log p/q_c for a lapse begun, log (1-p)/(1-q_c) for none; a ratio that
depends on the past draws only is still exact) with the per-class counts q_c is refitted from
(`WF_LAPSE_STEPS + c`, `WF_LAPSE_N + c`). Without a proposal q_c = p and every ratio is
exactly 1.

Splitting (`marlmerge.evaluation.splitting`, `P_LAPSE_SPLIT`): the same critical steps become
branch points instead of tilted draws. In the **trunk** (`P_LAPSE_FORCE` = -1) the driver behind
the ego's gap never begins a lapse at a critical step (weight 1 - p each); a critical step of
class c is a **branch point** when a second hash of the same key, step and vehicle falls below
r_c (`P_LAPSE_R + c`), and `WF_LAPSE_N + c` counts the branch points passed. **Branch** j
(`P_LAPSE_FORCE` = j) replays the same world, seeded alike, so it passes the same steps; at its
j-th branch point the driver begins the lapse, with weight p / r_c, and every draw after that is
natural. Summed over the trunk and its branches, the weighted outcomes have the natural rate as
their expectation: each lapse the trunk leaves out is run in a branch with probability r_c and
counted 1 / r_c times. `WF_LAPSE_STEPS + c` counts the critical steps, `WF_LAPSE_LOGW` keeps
the weight's log as above.
"""

from __future__ import annotations

import math

import numpy as np

from marlmerge.sim.jit import kernel
from marlmerge.sim.layout import (
    EGO,
    N_LAPSE_CLASSES,
    OUTCOME_NONE,
    P_DT,
    P_LAPSE_FORCE,
    P_LAPSE_P,
    P_LAPSE_Q,
    P_LAPSE_R,
    P_LAPSE_SPLIT,
    P_LAPSE_STEPS,
    P_LEN,
    P_X_ZONE_START,
    VF_LAPSE,
    VF_V,
    VF_X,
    VI_ACTIVE,
    VI_ID,
    WF_LAPSE_LOGW,
    WF_LAPSE_N,
    WF_LAPSE_STEPS,
    WI_BACK,
    WI_LAPSE_KEY,
    WI_OUTCOME,
    WI_STEPS,
)

_MASK32 = 0xFFFFFFFF


@kernel(inline=True)
def _mix32(x: int) -> int:
    """A 32-bit integer hash (xor-shift-multiply rounds); every product stays below 2^63, so
    compiled int64 and plain Python integers give the same value."""
    x = (x ^ (x >> 16)) & _MASK32
    x = (x * 0x7FEB352D) & _MASK32
    x = (x ^ (x >> 15)) & _MASK32
    x = (x * 0x2C1B3C6D) & _MASK32
    return (x ^ (x >> 16)) & _MASK32


@kernel(inline=True)
def lapse_uniform(key: int, step: int, vehicle_id: int) -> float:
    """The uniform in (0, 1) that decides whether vehicle `vehicle_id` begins a lapse in
    simulator step `step` of a world whose lapse key (drawn from its seed at each reset) is
    `key`: the same seed gives the same lapses in any batch, order or backend."""
    h = _mix32((key & _MASK32) ^ 0x5BD1E995)
    h = _mix32(h ^ (step & _MASK32))
    h = _mix32(h ^ (vehicle_id & _MASK32))
    return (h + 0.5) * (1.0 / 4294967296.0)


@kernel(inline=True)
def critical_slot(S: tuple, b: int, p: np.ndarray) -> int:
    """The driver whose lapses the proposal tilts in this step: the ego's gap-back vehicle
    while the ego runs in the merge zone or after joining (-1: none)."""
    vf, vi, wf, wi, lanes, sched = S
    if vi[b, VI_ACTIVE, EGO] == 0 or wi[b, WI_OUTCOME] != OUTCOME_NONE:
        return -1
    if vf[b, VF_X, EGO] < p[P_X_ZONE_START]:
        return -1
    return wi[b, WI_BACK]


MIN_CLOSING_MPS = 1.5
"""A driver closing in on the ego more slowly than this reaches as far as one this fast would:
the ego may slow down to join while the lapse lasts (without this floor, about 4 % of the
collisions came from lapses begun out of reach, 7-13 m behind and closing at 0.5-1.2 m/s)."""
CLASS_EDGES = (0.5, 1.0, 1.5, 2.5, 5.0)
"""Bounds on reach ratios (gap / reach, `lapse_class`): class 0 from the first to the second,
1 to the third, 2 to the fourth; class 3 below the first or from the fourth to the fifth.

Measured with gap acceptance on `lapses` at ten times its lapse rate (the first such lapse of
466,186 episodes, 841 of them ending in the ego's collision with the lapsing driver), the share
of lapses that end in a collision by reach ratio: 0.2 % below 0.5 (the ego does not join in
front of so close a driver), 44 % in [0.5, 1), 9 % in [1, 1.5), 2.3 % in [1.5, 2.5), 0.2 % in
[2.5, 5), under 0.01 % beyond. Classes with alike collision shares let the proposal give each
its own lapse probability."""


@kernel(inline=True)
def lapse_class(S: tuple, b: int, p: np.ndarray, s: int) -> int:
    """How soon a lapse of the driver in slot `s`, beginning now, could close its bumper gap to
    the ego (projected onto the road) at today's speeds: the reach ratio gap / reach, reach =
    the closing speed (at least `MIN_CLOSING_MPS`) times the lapse's length, binned by
    `CLASS_EDGES` (-1: not closing in, or out of reach: not tilted)."""
    vf, vi, wf, wi, lanes, sched = S
    closing_mps = vf[b, VF_V, s] - vf[b, VF_V, EGO]
    if closing_mps <= 0.0:
        return -1
    reach_m = max(closing_mps, MIN_CLOSING_MPS) * p[P_LAPSE_STEPS] * p[P_DT]
    ratio = (vf[b, VF_X, EGO] - p[P_LEN] - vf[b, VF_X, s]) / reach_m
    if ratio < CLASS_EDGES[0]:
        return 3
    for c in range(3):
        if ratio < CLASS_EDGES[c + 1]:
            return c
    return 3 if ratio < CLASS_EDGES[4] else -1


@kernel(inline=True)
def _tilted_lapse_begun(wf: np.ndarray, b: int) -> bool:
    for c in range(N_LAPSE_CLASSES):
        if wf[b, WF_LAPSE_N + c] > 0.0:
            return True
    return False


BRANCH_SALT = 0x2545F491
"""Mixed into the lapse key for the branch-point draw: independent of the lapse draws."""


@kernel(inline=True)
def _branch_points(wf: np.ndarray, b: int) -> float:
    n = 0.0
    for c in range(N_LAPSE_CLASSES):
        n += wf[b, WF_LAPSE_N + c]
    return n


@kernel(inline=True)
def _split_lapse_begun(wf: np.ndarray, b: int, p: np.ndarray) -> bool:
    """A branch has begun its forced lapse (the trunk never does)."""
    force = p[P_LAPSE_FORCE]
    return force >= 0.0 and _branch_points(wf, b) > force


@kernel(inline=True)
def _split_draw(S: tuple, b: int, p: np.ndarray, s: int, c: int) -> bool:
    """A critical step of class `c` under splitting (see the module docstring): the lapse
    begins only at a branch's own branch point."""
    vf, vi, wf, wi, lanes, sched = S
    p_nat = p[P_LAPSE_P]
    wf[b, WF_LAPSE_STEPS + c] += 1.0
    r = p[P_LAPSE_R + c]
    u = lapse_uniform(wi[b, WI_LAPSE_KEY] ^ BRANCH_SALT, wi[b, WI_STEPS], vi[b, VI_ID, s])
    if u < r:
        here = _branch_points(wf, b)  # the branch points passed before this one
        wf[b, WF_LAPSE_N + c] += 1.0
        if here == p[P_LAPSE_FORCE]:
            wf[b, WF_LAPSE_LOGW] += math.log(p_nat / r)
            return True
    wf[b, WF_LAPSE_LOGW] += math.log1p(-p_nat)
    return False


@kernel(inline=True)
def _tilted_draw(S: tuple, b: int, p: np.ndarray, s: int, c: int) -> bool:
    """A lapse drawn with the proposal's probability of class `c`, its weight kept (c = -1:
    the natural probability, nothing kept)."""
    vf, vi, wf, wi, lanes, sched = S
    p_nat = p[P_LAPSE_P]
    q = p[P_LAPSE_Q + c] if c >= 0 else p_nat
    lapse = lapse_uniform(wi[b, WI_LAPSE_KEY], wi[b, WI_STEPS], vi[b, VI_ID, s]) < q
    if c >= 0:
        wf[b, WF_LAPSE_STEPS + c] += 1.0
        if lapse:
            wf[b, WF_LAPSE_N + c] += 1.0
            wf[b, WF_LAPSE_LOGW] += math.log(p_nat / q)
        else:
            wf[b, WF_LAPSE_LOGW] += math.log1p(-p_nat) - math.log1p(-q)
    return lapse


@kernel(inline=True)
def lapsing(S: tuple, b: int, p: np.ndarray, s: int, critical: bool) -> bool:
    """Whether the driver in slot `s` lapses in this step (beginning one, or going on with
    one), with the draw's weight kept when `critical` (see the module docstring)."""
    vf, vi, wf, wi, lanes, sched = S
    left = vf[b, VF_LAPSE, s]
    if left > 0.0:
        vf[b, VF_LAPSE, s] = left - 1.0
        return True
    split = p[P_LAPSE_SPLIT] > 0.0
    begun = _split_lapse_begun(wf, b, p) if split else _tilted_lapse_begun(wf, b)
    c = lapse_class(S, b, p, s) if critical and not begun else -1
    lapse = _split_draw(S, b, p, s, c) if split and c >= 0 else _tilted_draw(S, b, p, s, c)
    if lapse:
        vf[b, VF_LAPSE, s] = p[P_LAPSE_STEPS] - 1.0
    return lapse
