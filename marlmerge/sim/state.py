"""Named, read-only views of the core's packed arrays, and what one call of the core returns.

`TrafficState` is how everything outside the core reads the simulation: `core.state.x_m` is a
`[B, N]` view of the positions that cannot be written to. The core alone changes its state.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from marlmerge.sim import layout as L

if TYPE_CHECKING:
    from marlmerge.sim.core import TrafficCore


class _Row:
    """A read-only row of one of the core's packed arrays, as a named attribute."""

    def __init__(self, array: str, row: int | slice, doc: str, as_bool: bool = False):
        self.array, self.row, self.as_bool = array, row, as_bool
        self.__doc__ = doc

    def __get__(self, obj: TrafficState | None, owner: type) -> np.ndarray:
        if obj is None:
            return self  # type: ignore[return-value]
        a = getattr(obj._core, self.array)[:, self.row]
        if self.as_bool:
            return a != 0
        v = a.view()
        v.flags.writeable = False
        return v


class TrafficState:
    """The state of B worlds: `[B, N]` per vehicle slot (slot 0 is the ego), `[B]` per world."""

    def __init__(self, core: TrafficCore):
        self._core = core

    @property
    def batch_size(self) -> int:
        return self._core.batch_size

    # per vehicle slot [B, N]
    x_m = _Row("vf", L.VF_X, "position along the road (front bumper), 0 at the merge point")
    v_mps = _Row("vf", L.VF_V, "speed, >= 0")
    a_mps2 = _Row("vf", L.VF_A, "acceleration realised over the last step")
    v0_mps = _Row("vf", L.VF_V0, "IDM desired speed")
    headway_s = _Row("vf", L.VF_T, "IDM time headway")
    politeness = _Row("vf", L.VF_POL, "MOBIL politeness")
    since_lane_change_s = _Row("vf", L.VF_SINCE_LC, "time since the last lane change")
    age_s = _Row("vf", L.VF_AGE, "time since the vehicle entered the road (the ego: departed)")
    gap_m = _Row("vf", L.VF_GAP, "bumper gap to the own-lane leader (inf if none)")
    v_lead_mps = _Row("vf", L.VF_VLEAD, "speed of the own-lane leader (own speed if none)")
    lane = _Row("vi", L.VI_LANE, "RAMP, RIGHT or LEFT")
    active = _Row("vi", L.VI_ACTIVE, "the slot holds a vehicle", as_bool=True)
    profile = _Row("vi", L.VI_PROFILE, "driver profile code")
    vehicle_id = _Row("vi", L.VI_ID, "unique per world, never reused")
    collided = _Row("vi", L.VI_COLLIDED, "in a collision, awaiting removal", as_bool=True)
    leader = _Row("vi", L.VI_LEADER, "slot of the own-lane leader (-1 none)")
    follower = _Row("vi", L.VI_FOLLOWER, "slot of the own-lane follower (-1 none)")
    from_ramp = _Row(
        "vi", L.VI_RAMP, "ramp flow: came by the ramp, not yet past the merge point", as_bool=True
    )
    # per world [B]
    t_s = _Row("wf", L.WF_T, "world time")
    ego_time_s = _Row("wf", L.WF_EGO_T, "time since the current ego departed")
    ego_stall_s = _Row("wf", L.WF_EGO_STALL, "time the ego has been slower than the stall speed")
    ego_in_lane_s = _Row("wf", L.WF_EGO_IN_LANE, "time since the ego joined the right lane")
    entry_delay_s = _Row("wf", L.WF_DELAY_SUM, "summed entrance delay of the entered vehicles")
    ego_outcome = _Row("wi", L.WI_OUTCOME, "OUTCOME_* of the current ego")
    ego_count = _Row("wi", L.WI_EGO_COUNT, "egos departed so far")
    background_collisions = _Row(
        "wi", L.WI_BG_COLLISIONS, "collisions between mainline vehicles (should stay 0)"
    )
    entered = _Row("wi", L.WI_ENTERED, "mainline vehicles that entered the road since reset")
    exited = _Row("wi", L.WI_EXITED, "mainline vehicles that left downstream since reset")
    queue = _Row("wi", slice(L.WI_QUEUE_RIGHT, L.WI_QUEUE_LEFT + 1), "[B, 2] entrance queues")
    max_queue = _Row("wi", L.WI_QUEUE_MAX, "longest entrance queue since reset")
    n_active = _Row("wi", L.WI_N_ACTIVE, "vehicles on the road, the ego included")
    filter_interventions = _Row(
        "wi",
        L.WI_FILTER_COUNT,
        "simulator steps of the current ego's episode whose command the safety filter overrode",
    )
    steps = _Row("wi", L.WI_STEPS, "simulator steps since reset")
    vehicle_steps = _Row("wi", L.WI_VEH_STEPS, "vehicle-steps simulated since reset")
    # ramp flow, per world [B] (since reset)
    ramp_entered = _Row("wi", L.WI_RAMP_ENTERED, "ramp vehicles that entered the ramp")
    ramp_joined = _Row("wi", L.WI_RAMP_JOINED, "ramp vehicles that joined the right lane")
    ramp_passed = _Row("wi", L.WI_RAMP_PASSED, "ramp vehicles that passed the merge point x = 0")
    ramp_collisions = _Row(
        "wi", L.WI_RAMP_COLLISIONS, "collisions a ramp vehicle was in before the merge point"
    )
    ramp_towed = _Row(
        "wi", L.WI_RAMP_TOWED, "ramp vehicles towed away after a collision before x = 0"
    )
    ramp_queue = _Row("wi", L.WI_RAMP_QUEUE, "ramp vehicles waiting at the ramp's entrance")
    ramp_max_queue = _Row("wi", L.WI_RAMP_QUEUE_MAX, "longest ramp entrance queue")
    n_on_ramp = _Row("wi", L.WI_N_RAMP, "vehicles on the ramp (not yet joined)")
    ramp_travel_s = _Row(
        "wf",
        L.WF_RAMP_TRAVEL_SUM,
        "summed travel times (drawn arrival at the ramp start to x = 0) of the passed ones",
    )
    ramp_wait_s = _Row("wf", L.WF_RAMP_WAIT_SUM, "summed entrance waits of the entered ones")


@dataclass(frozen=True)
class EgoGaps:
    """The ego's gap vehicles in the right lane at its (projected) position, `[B]` each."""

    front: np.ndarray  # slot of the gap-front vehicle, -1 if none within sensing range
    back: np.ndarray  # slot of the gap-back vehicle, -1 if none within sensing range
    d_front_m: np.ndarray  # bumper gap to the gap-front vehicle (sensing range if none)
    d_back_m: np.ndarray  # bumper gap to the gap-back vehicle (sensing range if none)
    x_front_m: np.ndarray  # position (x_ego + sensing range if none)
    x_back_m: np.ndarray  # position (x_ego - sensing range if none)
    v_front_mps: np.ndarray  # speed (speed limit if none)
    v_back_mps: np.ndarray  # speed (speed limit if none)


@dataclass(slots=True)
class StepEvents:
    """What happened in one call of the core (one simulator step for `TrafficCore.step`)."""

    ego_outcome: np.ndarray  # [B] OUTCOME_* reached (OUTCOME_NONE if still running)
    collided: np.ndarray  # [B, N] slots involved in a collision
    exited: np.ndarray  # [B, N] slots that left the road downstream (never the ego)
    ego_partner: np.ndarray  # [B] slot the ego collided with, -1 if none
    ego_rear: np.ndarray  # [B] bool: in that collision the ego was the rear vehicle


@dataclass(frozen=True)
class Roster:
    """Highway agents of B worlds: `rows` [RO_ROWS, B, K] int64 (slot, vehicle id, mask,
    exited). The core updates mask and exited in every call."""

    rows: np.ndarray

    @property
    def slots(self) -> np.ndarray:
        """[B, K] slot of each agent (-1 none)."""
        return self.rows[L.RO_SLOT]

    @property
    def ids(self) -> np.ndarray:
        """[B, K] vehicle id of each agent (-1 none)."""
        return self.rows[L.RO_ID]

    @property
    def mask(self) -> np.ndarray:
        """[B, K] bool: the agent is on the road and counting."""
        return self.rows[L.RO_MASK] != 0

    @property
    def exited(self) -> np.ndarray:
        """[B, K] bool: the agent left by the road's downstream end in the last call."""
        return self.rows[L.RO_EXITED] != 0

    @property
    def n_agents(self) -> int:
        return self.rows.shape[2]


@dataclass(slots=True)
class Rollout:
    """One call of `TrafficCore.rollout`: up to k simulator steps of every world.

    A world whose ego was running stops within the call at the step its ego's episode ends."""

    substeps: np.ndarray  # [B] simulator steps run
    ego_steps: np.ndarray  # [B] ... of them with the ego running (trace rows of its episode)
    ego_outcome: np.ndarray  # [B] OUTCOME_* reached in this call (OUTCOME_NONE if none)
    ego_terms: np.ndarray  # [B, len(EGO_TERMS)] summed over the steps the ego ran
    trace: np.ndarray  # [B, k, TR_COLS] the ego after each step (rows < substeps are valid)
    ego_obs: np.ndarray  # [B, obs size of ego.observation] float32, what the ego sees after it
    hw_terms: np.ndarray  # [B, K, len(LEARNED_HIGHWAY_TERMS)] summed while counting (ramp flow:
    # the ramp agents' EGO_TERMS)
    hw_obs: np.ndarray  # [B, K, len(HIGHWAY_FEATURES)] float32 (zeros where masked)
    left_road: np.ndarray  # [B, K] bool: counting at the start, gone at the end
    exited: np.ndarray  # [B, K] bool: ... by the road's downstream end
    ego_partner: np.ndarray  # [B] slot the ego collided with in this call, -1 if none
    ego_rear: np.ndarray  # [B] bool: the ego was the rear vehicle of that collision
    filter_interventions: np.ndarray | None = None  # [B] the safety filter's overrides in the
    # current (or just ended) ego episode, in simulator steps; None with the filter off
