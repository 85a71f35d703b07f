"""Ramp flow's agents, for every view of it: which ramp vehicle each agent column holds, and how
its merge ends.

`RampAgentTable(core, k, reuse)` keeps, for B worlds, K columns: column j of world b holds one
ramp vehicle (by its vehicle id) from the step it enters the ramp (or, at a reset, is on it)
until its own merge ends, as the ego's does:

- success: past `ego.success_distance_m`;
- collision: its vehicle collided in the step (or is gone: towed away);
- truncated: `ego.max_episode_s` after it became an agent, or slower than `ego.stall_speed_mps`
  for `ego.stall_time_s`.

With `reuse` (the torchrl view) a column takes the next vehicle once free; without (PettingZoo,
whose agents never come back) column j is the j-th ramp vehicle of the episode and vehicles
beyond K are not agents. Vehicles that find no column drive by IDM behind their ramp leader.
"""

from __future__ import annotations

import numpy as np

from marlmerge.sim import (
    OUTCOME_COLLISION,
    OUTCOME_NONE,
    OUTCOME_SUCCESS,
    OUTCOME_TRUNCATED,
    TrafficCore,
)
from marlmerge.sim import layout as L
from marlmerge.sim.state import Roster


class RampAgentTable:
    def __init__(self, core: TrafficCore, k: int, reuse: bool):
        if not core.cfg.ramp.flowing:
            raise ValueError("RampAgentTable needs ramp flow (ramp.flow_vph > 0)")
        self.core, self.k, self.reuse = core, k, reuse
        b = core.batch_size
        self.ids = np.full((b, k), -1, dtype=np.int64)
        """[B, K] vehicle id of each column's agent (-1: free)."""
        self.since_s = np.zeros((b, k))
        """[B, K] world time at which it became an agent."""
        self.stall_s = np.zeros((b, k))
        self.newest = np.full(b, -1, dtype=np.int64)
        """[B] the newest vehicle id given a column: ramp vehicles enter in id order."""
        self.used = np.zeros(b, dtype=np.int64)
        """[B] columns given out since the last `clear` (without `reuse`, the next free one)."""
        self.step_s = core.cfg.sim.dt_s * core.cfg.sim.action_repeat

    @property
    def live(self) -> np.ndarray:
        """[B, K] bool: the column holds an agent."""
        return self.ids >= 0

    def clear(self, worlds: np.ndarray | None = None) -> None:
        """Free every column of `worlds` (all if None); the ramp's vehicles get columns again."""
        rows = slice(None) if worlds is None else worlds
        self.ids[rows], self.since_s[rows], self.stall_s[rows] = -1, 0.0, 0.0
        self.newest[rows], self.used[rows] = -1, 0

    def slots(self) -> np.ndarray:
        """[B, K] the slot of each column's vehicle now, -1 if free or gone."""
        st = self.core.state
        match = (st.vehicle_id[:, None, :] == self.ids[:, :, None]) & st.active[:, None, :]
        found = match.any(axis=2)
        return np.where(found & self.live, match.argmax(axis=2), -1)

    def roster(self, slots: np.ndarray | None = None) -> Roster:
        """The agents as a `Roster` (`slots`: `slots()` if already at hand)."""
        return self.core.make_roster(self.slots() if slots is None else slots)

    def assign(self) -> np.ndarray:
        """Give the ramp vehicles that entered since the last call free columns (upstream last).
        Returns [B, K] bool: the columns filled now."""
        core, st = self.core, self.core.state
        new = np.zeros(self.ids.shape, dtype=bool)
        n_ramp = st.n_on_ramp
        for b in np.flatnonzero(n_ramp > 0):
            for s in core.lanes[b, L.RAMP_LIST, : int(n_ramp[b])][::-1]:
                vid = int(st.vehicle_id[b, s])
                if vid <= self.newest[b]:
                    continue
                free = np.flatnonzero(~self.live[b]) if self.reuse else np.array([self.used[b]])
                if free.size == 0 or free[0] >= self.k:
                    break
                j = int(free[0])
                self.ids[b, j], self.since_s[b, j], self.stall_s[b, j] = vid, st.t_s[b], 0.0
                self.newest[b], self.used[b] = vid, self.used[b] + 1
                new[b, j] = True
        return new

    def outcomes(self, slots: np.ndarray | None = None) -> np.ndarray:
        """[B, K] each live agent's outcome after a step (OUTCOME_NONE: still running; free
        columns too). Counts the stall clocks: call once per env step (`slots`: `slots()` after
        the step, if already at hand)."""
        core, st, e = self.core, self.core.state, self.core.cfg.ego
        slots = self.slots() if slots is None else slots
        b_idx = np.arange(core.batch_size)[:, None]
        s = np.maximum(slots, 0)
        gone = self.live & (slots < 0)
        hit = self.live & (slots >= 0) & ((core.vi[b_idx, L.VI_FLAGS, s] & L.EV_COLLIDED) != 0)
        x, v = st.x_m[b_idx, s], st.v_mps[b_idx, s]
        slow = self.live & (v < e.stall_speed_mps)
        self.stall_s = np.where(slow, self.stall_s + self.step_s, 0.0)
        age = st.t_s[:, None] - self.since_s
        out = np.full(self.ids.shape, OUTCOME_NONE, dtype=np.int64)
        late = (age >= e.max_episode_s - 1e-9) | (self.stall_s >= e.stall_time_s - 1e-9)
        out[self.live & late] = OUTCOME_TRUNCATED
        out[self.live & (x >= e.success_distance_m)] = OUTCOME_SUCCESS
        out[gone | hit] = OUTCOME_COLLISION
        return out

    def release(self, ended: np.ndarray) -> None:
        """Free the columns of `ended` [B, K] (their merges ended)."""
        self.ids[ended], self.since_s[ended], self.stall_s[ended] = -1, 0.0, 0.0

    def unnamed_on_ramp(self, slots: np.ndarray | None = None) -> np.ndarray:
        """[B] ramp vehicles on the ramp that hold no column (`slots`: `slots()` if at hand)."""
        st = self.core.state
        slots = self.slots() if slots is None else slots
        b_idx = np.arange(self.core.batch_size)[:, None]
        on_ramp = (slots >= 0) & (st.lane[b_idx, np.maximum(slots, 0)] == L.RAMP)
        return st.n_on_ramp - on_ramp.sum(axis=1)
