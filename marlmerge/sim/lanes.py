"""The lane lists: each highway lane's vehicles in road order, kept up to date step by step.

`lanes[b, lane, :n]` holds the slots of lane `lane` (RIGHT = 0, LEFT = 1) of world `b`, sorted by
position, downstream first; `n = wi[b, WI_N_RIGHT + lane]`. A vehicle's leader is the entry
before it, its follower the entry after it, and a position's neighbours in a lane come from a
binary search: no all-pairs search, no sort from scratch. Vehicles enter at the tail, leave at
the head, and change lanes by a removal and an insertion; the order within a lane only changes
when vehicles overlap (a collision), which one insertion-sort pass repairs.
"""

from __future__ import annotations

from marlmerge.sim.jit import kernel
from marlmerge.sim.layout import RAMP_LIST, VF_X, WI_N_RAMP, WI_N_RIGHT


@kernel(inline=True)
def count_ahead(S: tuple, b: int, lane: int, x: float) -> int:
    """How many vehicles of `lane` are at or ahead of position `x`: the insertion index of `x`.

    The first of them (index - 1) is the nearest vehicle at or ahead of `x`, the entry at the
    index the nearest one behind it."""
    vf, vi, wf, wi, lanes, sched = S
    lo, hi = 0, wi[b, WI_N_RIGHT + lane]
    while lo < hi:
        mid = (lo + hi) // 2
        if vf[b, VF_X, lanes[b, lane, mid]] >= x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@kernel(inline=True)
def neighbours_at(S: tuple, b: int, lane: int, x: float) -> tuple[int, int]:
    """Slots of the nearest vehicle at or ahead of `x` and the nearest behind it in `lane`
    (-1 = none). `x` must not be the position of a vehicle of `lane` looked up for itself."""
    vf, vi, wf, wi, lanes, sched = S
    i = count_ahead(S, b, lane, x)
    n = wi[b, WI_N_RIGHT + lane]
    ahead = lanes[b, lane, i - 1] if i > 0 else -1
    behind = lanes[b, lane, i] if i < n else -1
    return ahead, behind


@kernel(inline=True)
def insert(S: tuple, b: int, lane: int, slot: int) -> None:
    """Put `slot` into `lane` at its position (behind vehicles at the same position)."""
    vf, vi, wf, wi, lanes, sched = S
    i = count_ahead(S, b, lane, vf[b, VF_X, slot])
    n = wi[b, WI_N_RIGHT + lane]
    for j in range(n, i, -1):
        lanes[b, lane, j] = lanes[b, lane, j - 1]
    lanes[b, lane, i] = slot
    wi[b, WI_N_RIGHT + lane] = n + 1


@kernel(inline=True)
def remove(S: tuple, b: int, lane: int, slot: int) -> bool:
    """Take `slot` out of `lane`; False if it was not there."""
    vf, vi, wf, wi, lanes, sched = S
    n = wi[b, WI_N_RIGHT + lane]
    for i in range(n):
        if lanes[b, lane, i] == slot:
            for j in range(i, n - 1):
                lanes[b, lane, j] = lanes[b, lane, j + 1]
            lanes[b, lane, n - 1] = -1
            wi[b, WI_N_RIGHT + lane] = n - 1
            return True
    return False


@kernel
def replace(S: tuple, b: int, lane: int, old: int, new: int) -> None:
    """Let `new` take `old`'s place in `lane` (a merged ego handing its place to its successor
    slot)."""
    vf, vi, wf, wi, lanes, sched = S
    for i in range(wi[b, WI_N_RIGHT + lane]):
        if lanes[b, lane, i] == old:
            lanes[b, lane, i] = new
            return


@kernel(inline=True)
def resort(S: tuple, b: int, lane: int) -> None:
    """Restore downstream-first order after a step (insertion sort: one pass when in order)."""
    vf, vi, wf, wi, lanes, sched = S
    n = wi[b, WI_N_RIGHT + lane]
    for i in range(1, n):
        s = lanes[b, lane, i]
        x = vf[b, VF_X, s]
        j = i - 1
        while j >= 0 and vf[b, VF_X, lanes[b, lane, j]] < x:
            lanes[b, lane, j + 1] = lanes[b, lane, j]
            j -= 1
        lanes[b, lane, j + 1] = s


# ---- the ramp list (ramp flow): `lanes[b, RAMP_LIST, :WI_N_RAMP]`, downstream first. Vehicles
# enter at its tail and leave it when they join the right lane (or are towed away); they follow
# each other, so its order never changes.


@kernel(inline=True)
def ramp_append(S: tuple, b: int, slot: int) -> None:
    """Put `slot` at the tail of the ramp list (the ramp's most upstream vehicle)."""
    vf, vi, wf, wi, lanes, sched = S
    n = wi[b, WI_N_RAMP]
    lanes[b, RAMP_LIST, n] = slot
    wi[b, WI_N_RAMP] = n + 1


@kernel(inline=True)
def ramp_remove(S: tuple, b: int, slot: int) -> bool:
    """Take `slot` out of the ramp list; False if it was not there."""
    vf, vi, wf, wi, lanes, sched = S
    n = wi[b, WI_N_RAMP]
    for i in range(n):
        if lanes[b, RAMP_LIST, i] == slot:
            for j in range(i, n - 1):
                lanes[b, RAMP_LIST, j] = lanes[b, RAMP_LIST, j + 1]
            lanes[b, RAMP_LIST, n - 1] = -1
            wi[b, WI_N_RAMP] = n - 1
            return True
    return False
