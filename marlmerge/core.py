"""The batched ramp-merge traffic simulator. NumPy only: no RL library is imported here.

All vehicles of `B` independent worlds live in arrays shaped `[B, N]`: fixed slots with an
`active` mask. A vehicle's position `x_m` is its front bumper; its body covers
`[x_m - length_m, x_m]`. Slot 0 of every world is the ramp vehicle (the ego); slots 1..N-1 are
mainline vehicles. One simulator step advances every world at once by `dt_s`.

Neighbours are found by one sort per step (key = lane, then position), never all pairs: a vehicle's
leader is the next entry of its lane in that order, and a position's neighbours in another lane come
from a binary search in the same order.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, fields

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.drivers import InteractionView, Profile, idm_accel, profile_accel

RAMP, RIGHT, LEFT = -1, 0, 1
"""Lane codes. The ego is on `RAMP` until it overlaps the right lane, then in `RIGHT`."""
EGO = 0
"""The ego's slot."""

_LANE_SPAN = 1.0e4  # sort key = lane * span + x; larger than any road length
_ROW_SPAN = 1.0e5  # row offset that makes every world's keys sort after the previous world's
_INACTIVE_KEY = 5.0e4  # beyond every active key in a row
_INACTIVE_LANE = 5  # lane code an inactive slot's sort key decodes to
MAX_ROAD_EXTENT_M = 4000.0  # |x| must stay below this for the sort keys to separate lanes

OUTCOME_NONE, OUTCOME_SUCCESS, OUTCOME_COLLISION, OUTCOME_TRUNCATED = 0, 1, 2, 3
OUTCOME_NAMES = {0: "running", 1: "success", 2: "collision", 3: "truncated"}


@dataclass
class TrafficState:
    """Every mutable quantity of B worlds. `[B, N]` per vehicle slot, `[B]` per world."""

    x_m: np.ndarray  # [B, N] position along the road, 0 at the merge point
    v_mps: np.ndarray  # [B, N] speed, >= 0
    a_mps2: np.ndarray  # [B, N] acceleration applied in the last step
    lane: np.ndarray  # [B, N] int: RAMP, RIGHT or LEFT
    active: np.ndarray  # [B, N] bool: the slot holds a vehicle
    v0_mps: np.ndarray  # [B, N] IDM desired speed
    headway_s: np.ndarray  # [B, N] IDM time headway
    politeness: np.ndarray  # [B, N] MOBIL politeness
    profile: np.ndarray  # [B, N] int: Profile code
    since_lane_change_s: np.ndarray  # [B, N] time since the last lane change
    vehicle_id: np.ndarray  # [B, N] int: unique per world, never reused
    collided: np.ndarray  # [B, N] bool: involved in a collision, awaiting removal
    t_s: np.ndarray  # [B] world time
    next_arrival_s: np.ndarray  # [B, 2] world time of the next arrival per lane (RIGHT, LEFT)
    next_entry_speed_mps: np.ndarray  # [B, 2] speed of that arrival
    next_id: np.ndarray  # [B] next vehicle id to hand out
    ego_time_s: np.ndarray  # [B] time since the current ego departed
    ego_stall_s: np.ndarray  # [B] time the current ego has been slower than the stall speed
    ego_outcome: np.ndarray  # [B] int: OUTCOME_* of the current ego
    ego_count: np.ndarray  # [B] egos departed so far
    background_collisions: np.ndarray  # [B] collisions between mainline vehicles (should stay 0)
    dropped_arrivals: np.ndarray  # [B] arrivals lost because every slot was taken

    @property
    def batch_size(self) -> int:
        return self.x_m.shape[0]

    def take(self, rows: np.ndarray) -> TrafficState:
        """A copy of the worlds `rows` (integer indices)."""
        return TrafficState(**{f.name: getattr(self, f.name)[rows].copy() for f in fields(self)})

    def put(self, rows: np.ndarray, other: TrafficState) -> None:
        """Write `other`'s worlds into rows `rows`."""
        for f in fields(self):
            getattr(self, f.name)[rows] = getattr(other, f.name)


def empty_state(batch_size: int, n_slots: int) -> TrafficState:
    b, n = batch_size, n_slots
    return TrafficState(
        x_m=np.zeros((b, n)),
        v_mps=np.zeros((b, n)),
        a_mps2=np.zeros((b, n)),
        lane=np.full((b, n), RIGHT, dtype=np.int64),
        active=np.zeros((b, n), dtype=bool),
        v0_mps=np.full((b, n), 30.0),
        headway_s=np.full((b, n), 1.5),
        politeness=np.zeros((b, n)),
        profile=np.zeros((b, n), dtype=np.int64),
        since_lane_change_s=np.zeros((b, n)),
        vehicle_id=np.full((b, n), -1, dtype=np.int64),
        collided=np.zeros((b, n), dtype=bool),
        t_s=np.zeros(b),
        next_arrival_s=np.zeros((b, 2)),
        next_entry_speed_mps=np.zeros((b, 2)),
        next_id=np.zeros(b, dtype=np.int64),
        ego_time_s=np.zeros(b),
        ego_stall_s=np.zeros(b),
        ego_outcome=np.zeros(b, dtype=np.int64),
        ego_count=np.zeros(b, dtype=np.int64),
        background_collisions=np.zeros(b, dtype=np.int64),
        dropped_arrivals=np.zeros(b, dtype=np.int64),
    )


@dataclass
class Neighbours:
    """Lane order of every world, from one sort. Indices are slots; -1 means none."""

    order: np.ndarray  # [B, N] slots sorted by (lane, x), inactive last
    sorted_keys: np.ndarray  # [B*N] flat sorted keys with row offsets, for binary search
    sorted_lane: np.ndarray  # [B, N] lane of each sorted entry (a sentinel for inactive)
    leader: np.ndarray  # [B, N] slot of the own-lane leader
    follower: np.ndarray  # [B, N] slot of the own-lane follower
    gap_m: np.ndarray  # [B, N] bumper gap to the leader (inf if none)
    v_lead_mps: np.ndarray  # [B, N] leader speed (own speed if none)
    v_mps: np.ndarray  # [B, N] speeds at the time of the sort

    @functools.cached_property
    def gap_back_m(self) -> np.ndarray:
        """[B, N] bumper gap to the follower (inf if none): the follower's gap to its leader."""
        has = self.follower >= 0
        return np.where(
            has, np.take_along_axis(self.gap_m, np.where(has, self.follower, 0), 1), np.inf
        )

    @functools.cached_property
    def v_follow_mps(self) -> np.ndarray:
        """[B, N] follower speed (own speed if none)."""
        has = self.follower >= 0
        return np.where(
            has, np.take_along_axis(self.v_mps, np.where(has, self.follower, 0), 1), self.v_mps
        )


@dataclass
class EgoGaps:
    """The ego's gap vehicles in the right lane at its (projected) position. `[B]` each."""

    front: np.ndarray  # slot of the gap-front vehicle, -1 if none within sensing range
    back: np.ndarray  # slot of the gap-back vehicle, -1 if none within sensing range
    d_front_m: np.ndarray  # bumper gap to the gap-front vehicle (sensing range if none)
    d_back_m: np.ndarray  # bumper gap to the gap-back vehicle (sensing range if none)
    x_front_m: np.ndarray  # position (x_ego + sensing range if none)
    x_back_m: np.ndarray  # position (x_ego - sensing range if none)
    v_front_mps: np.ndarray  # speed (speed limit if none)
    v_back_mps: np.ndarray  # speed (speed limit if none)


@dataclass
class StepEvents:
    """What happened in one simulator step."""

    ego_outcome: np.ndarray  # [B] OUTCOME_* reached this step (OUTCOME_NONE if still running)
    collided: np.ndarray  # [B, N] slots involved in a collision this step
    exited: np.ndarray  # [B, N] slots that left the road downstream this step (ego excluded)
    ego_partner: np.ndarray  # [B] slot the ego collided with this step, -1 if none
    ego_rear: np.ndarray  # [B] bool: in that collision the ego was the rear vehicle


class TrafficCore:
    """B worlds of the ramp-merge scenario, stepped together.

    Typical use:

        core = TrafficCore(cfg, batch_size=64, seed=0)
        while True:
            ev = core.step(ego_accel)            # ego_accel: [B] m/s^2, NaN = ego drives by IDM
            done = ev.ego_outcome != OUTCOME_NONE
            core.next_ego(done)                  # the next ramp vehicle departs in finished worlds
    """

    def __init__(self, cfg: ScenarioConfig, batch_size: int = 1, seed: int | None = None):
        self.cfg = cfg
        self.batch_size = batch_size
        self.n_slots = cfg.traffic.max_vehicles
        self.v_limit = cfg.road.speed_limit_mps
        self.length_m = cfg.vehicle.length_m
        self.x_overlap_m = cfg.x_overlap_m
        self._row_off = (np.arange(batch_size) * _ROW_SPAN)[:, None]  # [B, 1]
        self._row_base = (np.arange(batch_size) * self.n_slots)[:, None]  # [B, 1] flat row starts
        self._rows = np.arange(batch_size)
        self.rng = np.random.default_rng(seed)
        self.step_count = 0
        self._version = 0  # bumped whenever self.state changes; keys the ego-gap cache
        self._gaps_cache: tuple[int, EgoGaps] | None = None
        self.state = empty_state(batch_size, self.n_slots)
        self.nb = self._neighbours(self.state)
        self.reset(seed=seed)

    # ------------------------------------------------------------------ resets
    def reset(self, seed: int | None = None, mask: np.ndarray | None = None) -> None:
        """Build fresh roads in steady flow for the worlds in `mask` (all if None); send an ego.

        With `seed`, the generator is re-seeded first, so equal seeds give equal worlds.
        """
        if seed is not None:
            self.rng = np.random.default_rng(seed)
            self.step_count = 0
        rows = np.arange(self.batch_size) if mask is None else np.flatnonzero(mask)
        if rows.size == 0:
            return
        sub = empty_state(rows.size, self.n_slots)
        self._fill_road(sub)
        n_warm = int(round(self.cfg.traffic.warmup_s / self.cfg.sim.dt_s))
        nan = np.full(rows.size, np.nan)
        for i in range(n_warm):
            self._advance(sub, nan, None, i)
        if rows.size == self.batch_size:
            self.state = sub
        else:
            self.state.put(rows, sub)
        self.next_ego(np.isin(np.arange(self.batch_size), rows))

    def _fill_road(self, st: TrafficState) -> None:
        """Place mainline vehicles along both lanes as a stationary arrival stream."""
        cfg, rng = self.cfg, self.rng
        b = st.batch_size
        flow = cfg.traffic.flow_vph_per_lane
        mean_v, _ = cfg.traffic.entry_speed_mps
        road_len = cfg.road.x_exit_m - cfg.road.x_entrance_m
        per_lane = (self.n_slots - 1) // 2
        if flow > 0:
            mean_headway_s = 3600.0 / flow
            # spacing = speed x exponential headway, never closer than a safe following distance
            h = rng.exponential(mean_headway_s, size=(b, 2, per_lane))
            v = self._draw_entry_speed((b, 2, per_lane))
            min_space = self.length_m + cfg.driver.min_gap_m + v * cfg.driver.time_headway_s[1]
            space = np.maximum(v * h, min_space)
            first = rng.uniform(0.0, 1.0, size=(b, 2, 1)) * space[..., :1]
            dist = np.cumsum(space, axis=-1) - space[..., :1] + first  # from the exit upstream
            x = cfg.road.x_exit_m - dist
            keep = dist < road_len
        else:
            x = v = np.zeros((b, 2, per_lane))
            keep = np.zeros((b, 2, per_lane), dtype=bool)
        lane = np.broadcast_to(np.array([RIGHT, LEFT])[None, :, None], keep.shape)
        slot = 1
        for lane_i in range(2):
            for j in range(per_lane):
                m = keep[:, lane_i, j]
                self._spawn_into(
                    st,
                    np.flatnonzero(m),
                    np.full(m.sum(), slot),
                    x[m, lane_i, j],
                    v[m, lane_i, j],
                    lane[m, lane_i, j],
                )
                slot += 1
        if flow > 0:
            st.next_arrival_s[:] = rng.exponential(3600.0 / flow, size=(b, 2))
        else:
            st.next_arrival_s[:] = np.inf
        st.next_entry_speed_mps[:] = self._draw_entry_speed((b, 2))

    def _draw_entry_speed(self, shape: tuple[int, ...]) -> np.ndarray:
        mean, std = self.cfg.traffic.entry_speed_mps
        return np.clip(self.rng.normal(mean, std, size=shape), mean - 2 * std, mean + 2 * std)

    def _spawn_into(
        self,
        st: TrafficState,
        rows: np.ndarray,
        slots: np.ndarray,
        x: np.ndarray,
        v: np.ndarray,
        lane: np.ndarray,
    ) -> None:
        """Put new mainline vehicles with freshly drawn drivers into the given (row, slot) pairs."""
        n = rows.size
        if n == 0:
            return
        d = self.cfg.driver
        rng = self.rng
        st.x_m[rows, slots] = x
        st.v_mps[rows, slots] = v
        st.a_mps2[rows, slots] = 0.0
        st.lane[rows, slots] = lane
        st.active[rows, slots] = True
        st.v0_mps[rows, slots] = rng.uniform(*d.desired_speed_factor, size=n) * self.v_limit
        st.headway_s[rows, slots] = rng.uniform(*d.time_headway_s, size=n)
        st.politeness[rows, slots] = rng.uniform(*d.politeness, size=n)
        st.profile[rows, slots] = rng.choice(3, size=n, p=np.asarray(d.mix) / sum(d.mix))
        st.since_lane_change_s[rows, slots] = d.lane_change_cooldown_s
        st.vehicle_id[rows, slots] = st.next_id[rows]
        st.collided[rows, slots] = False
        np.add.at(st.next_id, rows, 1)

    def next_ego(self, mask: np.ndarray) -> None:
        """End the current ego in the worlds of `mask` and send the next one from the ramp start.

        A merged ego stays on the road as a neutral mainline vehicle; after a collision the ego and
        the vehicles it hit are towed away; a truncated ego is removed.
        """
        rows = np.flatnonzero(mask)
        if rows.size == 0:
            return
        st, cfg = self.state, self.cfg
        merged = rows[st.active[rows, EGO] & (st.ego_outcome[rows] == OUTCOME_SUCCESS)]
        if merged.size:
            free = ~st.active[merged]
            free[:, EGO] = False
            has = free.any(axis=1)
            slot = np.argmax(free, axis=1)
            keep_rows, keep_slots = merged[has], slot[has]
            self._spawn_into(
                st,
                keep_rows,
                keep_slots,
                st.x_m[keep_rows, EGO],
                st.v_mps[keep_rows, EGO],
                np.full(keep_rows.size, RIGHT),
            )
            st.profile[keep_rows, keep_slots] = Profile.NEUTRAL
        st.active[rows] &= ~st.collided[rows]
        st.collided[rows] = False
        st.x_m[rows, EGO] = cfg.road.x_ramp_start_m
        st.v_mps[rows, EGO] = self.rng.uniform(*cfg.ego.start_speed_mps, size=rows.size)
        st.a_mps2[rows, EGO] = 0.0
        st.lane[rows, EGO] = RAMP
        st.active[rows, EGO] = True
        st.v0_mps[rows, EGO] = self.v_limit
        st.headway_s[rows, EGO] = float(np.mean(cfg.driver.time_headway_s))
        st.profile[rows, EGO] = Profile.NEUTRAL
        st.vehicle_id[rows, EGO] = st.next_id[rows]
        st.next_id[rows] += 1
        st.ego_time_s[rows] = 0.0
        st.ego_stall_s[rows] = 0.0
        st.ego_outcome[rows] = OUTCOME_NONE
        st.ego_count[rows] += 1
        self.nb = self._neighbours(st)
        self._version += 1

    def remove_ego(self, mask: np.ndarray | None = None) -> None:
        """Take the ramp vehicle off the road in the worlds of `mask` (all if None): traffic-only
        worlds, until `next_ego` sends one again."""
        rows = np.arange(self.batch_size) if mask is None else np.flatnonzero(mask)
        self.state.active[rows, EGO] = False
        self.state.ego_outcome[rows] = OUTCOME_NONE
        self.nb = self._neighbours(self.state)
        self._version += 1

    def pick_roster(self, k: int) -> np.ndarray:
        """Slots of the mainline vehicles taking part in each world's current merge, [B, k] int:
        the right-lane vehicles whose arrival time at the merge point (at current speeds) is
        closest to the ego's, nearest in time first; -1 where the lane holds fewer than k."""
        st = self.state
        cand = st.active & (st.lane == RIGHT)  # [B, N]
        cand[:, EGO] = False
        t_arrive_s = -st.x_m / np.maximum(st.v_mps, 1.0)  # [B, N]
        dt_s = np.where(cand, np.abs(t_arrive_s - t_arrive_s[:, EGO : EGO + 1]), np.inf)
        order = np.argsort(dt_s, axis=1, kind="stable")[:, :k]
        return np.where(np.take_along_axis(cand, order, axis=1), order, -1)

    # ------------------------------------------------------------------ neighbours
    def _neighbours(self, st: TrafficState) -> Neighbours:
        b, n = st.x_m.shape
        keys = np.where(st.active, st.lane * _LANE_SPAN + st.x_m, _INACTIVE_KEY)
        order = np.argsort(keys, axis=1, kind="stable")
        sorted_keys = self._gather(keys, order)
        sorted_lane = np.rint(sorted_keys * (1.0 / _LANE_SPAN)).astype(np.int64)  # inactive: 5
        same_next = sorted_lane[:, 1:] == sorted_lane[:, :-1]
        same_next &= sorted_lane[:, :-1] != _INACTIVE_LANE
        lead_sorted = np.full((b, n), -1)
        lead_sorted[:, :-1] = np.where(same_next, order[:, 1:], -1)
        follow_sorted = np.full((b, n), -1)
        follow_sorted[:, 1:] = np.where(same_next, order[:, :-1], -1)
        flat_order = (
            order + self._row_base if b == self.batch_size else order + (np.arange(b) * n)[:, None]
        ).ravel()
        leader = np.empty(b * n, dtype=np.int64)
        follower = np.empty(b * n, dtype=np.int64)
        leader[flat_order] = lead_sorted.ravel()
        follower[flat_order] = follow_sorted.ravel()
        leader, follower = leader.reshape(b, n), follower.reshape(b, n)
        gap, v_lead = self._gap_to(st, leader, ahead=True)
        rows = self._row_offsets(b)
        return Neighbours(
            order,
            (sorted_keys + rows).ravel(),
            sorted_lane,
            leader,
            follower,
            gap,
            v_lead,
            st.v_mps,
        )

    def _gather(self, a: np.ndarray, idx: np.ndarray) -> np.ndarray:
        """`a[b, idx[b, j]]` for [B, N] `a` and [B, K] slots (faster than take_along_axis)."""
        b, n = a.shape
        base = self._row_base if b == self.batch_size else (np.arange(b) * n)[:, None]
        return a.ravel()[idx + base]

    def _row_offsets(self, b: int) -> np.ndarray:
        return self._row_off if b == self.batch_size else (np.arange(b) * _ROW_SPAN)[:, None]

    def _gap_to(
        self, st: TrafficState, other: np.ndarray, ahead: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """Bumper gap and speed of `other` ([B, N] slots, -1 = none): inf and own speed if none."""
        has = other >= 0
        idx = np.where(has, other, 0)
        x_o = self._gather(st.x_m, idx)
        v_o = self._gather(st.v_mps, idx)
        dist = (x_o - st.x_m) if ahead else (st.x_m - x_o)
        gap = np.where(has, dist - self.length_m, np.inf)
        return gap, np.where(has, v_o, st.v_mps)

    def _lane_neighbours_at(
        self, nb: Neighbours, lane: np.ndarray | int, x: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Slots of the first vehicle ahead of `x` and the last one behind it, in `lane`.

        `x` (and `lane` if an array): leading dim B, any trailing shape. The query position must not
        be a vehicle of `lane` itself. Returns slot arrays shaped like `x` (-1 = none).
        """
        b, n = nb.order.shape
        shape = x.shape
        q = (lane * _LANE_SPAN + x).reshape(b, -1) + self._row_offsets(b)
        pos = np.searchsorted(nb.sorted_keys, q.ravel()).reshape(q.shape)
        pos -= self._row_base if b == self.batch_size else (np.arange(b) * n)[:, None]
        lane_b = lane if isinstance(lane, int) else lane.reshape(b, -1)
        ahead_pos = np.minimum(pos, n - 1)
        back_pos = np.maximum(pos - 1, 0)
        ok_ahead = (pos < n) & (self._gather(nb.sorted_lane, ahead_pos) == lane_b)
        ok_back = (pos > 0) & (self._gather(nb.sorted_lane, back_pos) == lane_b)
        ahead = np.where(ok_ahead, self._gather(nb.order, ahead_pos), -1)
        back = np.where(ok_back, self._gather(nb.order, back_pos), -1)
        return ahead.reshape(shape), back.reshape(shape)

    # ------------------------------------------------------------------ views of the state
    def interaction_view(self, st: TrafficState | None = None) -> InteractionView:
        """The ramp vehicle as mainline drivers see it, broadcast over slots: `[B, 1]` arrays."""
        st = self.state if st is None else st
        x_e = st.x_m[:, EGO : EGO + 1]
        return InteractionView(
            ego_dx_m=x_e - st.x_m,
            ego_v_mps=st.v_mps[:, EGO : EGO + 1],
            ego_to_overlap_m=self.x_overlap_m - x_e,
            ego_pending=(st.active[:, EGO : EGO + 1] & (st.lane[:, EGO : EGO + 1] == RAMP)),
        )

    def ego_gaps(self) -> EgoGaps:
        """Gap-front and gap-back vehicles of the ego: its right-lane neighbours (projected while it
        is still on the ramp). Cached until the next step."""
        if self._gaps_cache is not None and self._gaps_cache[0] == self._version:
            return self._gaps_cache[1]
        st, nb = self.state, self.nb
        rng_m = self.cfg.ego.sensing_range_m
        x_e = st.x_m[:, EGO]
        in_lane = st.lane[:, EGO] == RIGHT
        front, back = nb.leader[:, EGO], nb.follower[:, EGO]
        if not in_lane.all():
            f_proj, b_proj = self._lane_neighbours_at(nb, RIGHT, x_e)
            front = np.where(in_lane, front, f_proj)
            back = np.where(in_lane, back, b_proj)
        rows = self._rows
        x_f = st.x_m[rows, front]  # index -1 reads the last slot; masked below
        x_b = st.x_m[rows, back]
        has_f = (front >= 0) & (x_f - x_e <= rng_m)
        has_b = (back >= 0) & (x_e - x_b <= rng_m)
        x_f = np.where(has_f, x_f, x_e + rng_m)
        x_b = np.where(has_b, x_b, x_e - rng_m)
        gaps = EgoGaps(
            front=np.where(has_f, front, -1),
            back=np.where(has_b, back, -1),
            d_front_m=x_f - x_e - np.where(has_f, self.length_m, 0.0),
            d_back_m=x_e - x_b - np.where(has_b, self.length_m, 0.0),
            x_front_m=x_f,
            x_back_m=x_b,
            v_front_mps=np.where(has_f, st.v_mps[rows, front], self.v_limit),
            v_back_mps=np.where(has_b, st.v_mps[rows, back], self.v_limit),
        )
        self._gaps_cache = (self._version, gaps)
        return gaps

    # ------------------------------------------------------------------ stepping
    def step(self, ego_accel: np.ndarray, highway_accel: np.ndarray | None = None) -> StepEvents:
        """Advance every world by one simulator step.

        ego_accel: [B] m/s^2, clipped to the ego bounds; NaN lets the ego drive by plain IDM
            (it then ignores the merge: a baseline).
        highway_accel: optional [B, N] m/s^2 for externally controlled mainline slots; NaN entries
            (and the ego column) are driven by their scripted profile. Controlled vehicles keep
            their lane and are clipped to the physical limits.
        """
        ev = self._advance(
            self.state, np.asarray(ego_accel, dtype=np.float64), highway_accel, self.step_count
        )
        self.step_count += 1
        self._version += 1
        return ev

    def _advance(
        self,
        st: TrafficState,
        ego_accel: np.ndarray,
        highway_accel: np.ndarray | None,
        step_index: int,
    ) -> StepEvents:
        cfg = self.cfg
        dt = cfg.sim.dt_s
        drv = cfg.driver
        nb = self.nb if st is self.state else self._neighbours(st)
        view = self.interaction_view(st)
        in_right = st.lane == RIGHT

        # ---- accelerations [B, N]
        accel, yielding = profile_accel(
            st.profile,
            st.v_mps,
            nb.gap_m,
            nb.v_lead_mps,
            st.v0_mps,
            st.headway_s,
            in_right,
            view,
            drv,
            cfg.vehicle,
            self.v_limit,
        )
        lo, hi = cfg.ego.accel_bounds_mps2
        ego_a = np.minimum(np.maximum(ego_accel, lo), hi)
        if np.isnan(ego_accel).any():
            ego_a = np.where(np.isnan(ego_accel), accel[:, EGO], ego_a)
        controlled = None
        if highway_accel is not None:
            controlled = ~np.isnan(highway_accel)
            controlled[:, EGO] = False
            accel = np.where(controlled, highway_accel, accel)
        accel = np.minimum(
            np.maximum(accel, -cfg.vehicle.max_brake_mps2), cfg.vehicle.max_accel_mps2
        )
        accel[:, EGO] = ego_a

        # ---- lane-change decisions on the pre-step state (MOBIL), applied after integration
        change = None
        if step_index % drv.lane_change_every_steps == 0:
            change = self._mobil(st, nb, yielding, controlled)

        # ---- integrate (ballistic; a vehicle that stops within the step stops where v reaches 0)
        v_old = st.v_mps
        v_new = np.maximum(v_old + accel * dt, 0.0)
        dx = (v_old + v_new) * (0.5 * dt)
        stopped = v_new == 0.0
        if stopped.any():
            dx = np.where(stopped, 0.5 * v_old * v_old / np.maximum(-accel, 1e-9), dx)
        st.x_m += dx
        st.a_mps2 = (v_new - v_old) * (1.0 / dt)
        st.v_mps = v_new
        st.t_s += dt
        st.since_lane_change_s += dt
        if change is not None:
            st.lane = np.where(change, 1 - st.lane, st.lane)
            st.since_lane_change_s = np.where(change, 0.0, st.since_lane_change_s)

        # ---- leave downstream, arrive upstream, ego joins the right lane
        exited = st.active & (st.x_m > cfg.road.x_exit_m)
        exited[:, EGO] = False
        st.active &= ~exited
        self._arrivals(st)
        ego_on = st.active[:, EGO]
        st.lane[:, EGO] = np.where(st.x_m[:, EGO] >= self.x_overlap_m, RIGHT, RAMP)

        # ---- new lane order, then collisions = overlaps of consecutive vehicles in a lane
        nb = self._neighbours(st)
        if st is self.state:
            self.nb = nb
        hit = st.active & (nb.gap_m < 0.0)  # [B, N] rear vehicle of an overlapping pair
        collided = np.zeros_like(hit)
        ego_hit = np.zeros(st.batch_size, dtype=bool)
        ego_partner = np.full(st.batch_size, -1, dtype=np.int64)
        ego_rear = np.zeros(st.batch_size, dtype=bool)
        if hit.any():
            rows, slots = np.nonzero(hit)
            partner = nb.leader[rows, slots]  # front vehicle of each overlapping pair
            collided[rows, slots] = True
            collided[rows, partner] = True
            with_ego = (slots == EGO) | (partner == EGO)
            ego_side = np.zeros_like(hit)
            ego_side[rows[with_ego], slots[with_ego]] = True
            ego_side[rows[with_ego], partner[with_ego]] = True
            ego_hit[rows[with_ego]] = True
            ego_hit &= ~st.collided[:, EGO]
            r, s, p = rows[with_ego], slots[with_ego], partner[with_ego]
            ego_partner[r] = np.where(s == EGO, p, s)
            ego_rear[r] = s == EGO
            ego_partner[~ego_hit] = -1
            ego_rear &= ego_hit
            np.add.at(st.background_collisions, rows[~with_ego], 1)
            # mainline wrecks are towed away at once; the ego's stay until its episode is closed
            st.active &= ~(collided & ~ego_side)
            st.collided |= ego_side

        # ---- ego episode end
        e = cfg.ego
        running = ego_on & (st.ego_outcome == OUTCOME_NONE)
        st.ego_time_s += running * dt
        slow = running & (st.v_mps[:, EGO] < e.stall_speed_mps)
        st.ego_stall_s = (st.ego_stall_s + dt) * slow
        outcome = np.zeros(st.batch_size, dtype=np.int64)
        outcome[
            (st.ego_time_s >= e.max_episode_s - 1e-9) | (st.ego_stall_s >= e.stall_time_s - 1e-9)
        ] = OUTCOME_TRUNCATED
        outcome[st.x_m[:, EGO] >= e.success_distance_m] = OUTCOME_SUCCESS
        outcome[ego_hit] = OUTCOME_COLLISION
        outcome[~running] = OUTCOME_NONE
        st.ego_outcome[running] = outcome[running]
        return StepEvents(
            ego_outcome=outcome,
            collided=collided,
            exited=exited,
            ego_partner=ego_partner,
            ego_rear=ego_rear,
        )

    def _mobil(
        self, st: TrafficState, nb: Neighbours, yielding: np.ndarray, controlled: np.ndarray | None
    ) -> np.ndarray:
        """MOBIL lane-change decisions for scripted mainline vehicles ([B, N] bool)."""
        drv = self.cfg.driver
        a, b, s0, delta = drv.accel_mps2, drv.comfort_brake_mps2, drv.min_gap_m, drv.delta
        L = self.length_m
        target = 1 - st.lane
        eligible = (
            st.active & (st.lane >= RIGHT) & (st.since_lane_change_s >= drv.lane_change_cooldown_s)
        )
        eligible[:, EGO] = False
        if controlled is not None:
            eligible &= ~controlled
        if not eligible.any():
            return eligible
        t_lead, t_follow = self._lane_neighbours_at(nb, target, st.x_m)
        v = st.v_mps
        gap_t, v_t = self._gap_to(st, t_lead, ahead=True)  # gap to the target-lane leader
        back_gap_t, v_nf = self._gap_to(st, t_follow, ahead=False)  # gap to the new follower
        nf = np.maximum(t_follow, 0)
        v0_nf = self._gather(st.v0_mps, nf)
        T_nf = self._gather(st.headway_s, nf)
        has_nf = t_follow >= 0
        # new follower: before (following the target leader) and after (following this vehicle)
        nf_gap_before = self._gather(nb.gap_m, nf)
        nf_vlead_before = self._gather(nb.v_lead_mps, nf)
        a_nf_before = idm_accel(v_nf, nf_gap_before, nf_vlead_before, v0_nf, T_nf, a, b, s0, delta)
        a_nf_after = idm_accel(v_nf, back_gap_t, v, v0_nf, T_nf, a, b, s0, delta)
        # old follower: before (following this vehicle) and after (following its leader)
        of = np.maximum(nb.follower, 0)
        has_of = nb.follower >= 0
        v_of = self._gather(v, of)
        v0_of = self._gather(st.v0_mps, of)
        T_of = self._gather(st.headway_s, of)
        a_of_before = idm_accel(v_of, nb.gap_back_m, v, v0_of, T_of, a, b, s0, delta)
        of_gap_after = nb.gap_back_m + L + nb.gap_m
        a_of_after = idm_accel(v_of, of_gap_after, nb.v_lead_mps, v0_of, T_of, a, b, s0, delta)
        # this vehicle, now and in the target lane
        a_now = idm_accel(v, nb.gap_m, nb.v_lead_mps, st.v0_mps, st.headway_s, a, b, s0, delta)
        a_tgt = idm_accel(v, gap_t, v_t, st.v0_mps, st.headway_s, a, b, s0, delta)
        others = np.where(has_nf, a_nf_after - a_nf_before, 0.0) + np.where(
            has_of, a_of_after - a_of_before, 0.0
        )
        incentive = a_tgt - a_now + st.politeness * others
        bias = np.where(target == LEFT, -drv.keep_right_bias_mps2, drv.keep_right_bias_mps2)
        bias = bias + np.where(yielding & (target == LEFT), drv.yield_lane_change_bonus_mps2, 0.0)
        safe = (~has_nf | (a_nf_after >= -drv.safe_brake_mps2)) & (gap_t > s0) & (back_gap_t > s0)
        return eligible & safe & (incentive + bias > drv.lane_change_threshold_mps2)

    def _arrivals(self, st: TrafficState) -> None:
        """Poisson arrivals at the entrance of each lane, delayed while the entrance is blocked.

        Each lane's next arrival time and speed are drawn when the previous vehicle enters. A due
        vehicle enters once the bumper gap to the last vehicle exceeds s0 + 0.5 s x its speed, no
        faster than that vehicle if closer than a safe headway; with every slot taken it is dropped.
        """
        due = st.next_arrival_s <= st.t_s[:, None]  # [B, 2]
        if not due.any():
            return
        cfg = self.cfg
        x0 = cfg.road.x_entrance_m
        s0 = cfg.driver.min_gap_m
        for lane_i, lane in enumerate((RIGHT, LEFT)):
            rows = np.flatnonzero(due[:, lane_i])
            if rows.size == 0:
                continue
            x_lane = np.where(st.active[rows] & (st.lane[rows] == lane), st.x_m[rows], np.inf)
            last = np.argmin(x_lane, axis=1)
            room = x_lane[np.arange(rows.size), last] - x0 - self.length_m  # inf if lane empty
            v = st.next_entry_speed_mps[rows, lane_i]
            clear = room > s0 + 0.5 * v
            if not clear.any():
                continue
            rows, last, room, v = rows[clear], last[clear], room[clear], v[clear]
            close = room < s0 + v * cfg.driver.time_headway_s[0]
            v = np.where(close, np.minimum(v, st.v_mps[rows, last]), v)
            free = ~st.active[rows]
            free[:, EGO] = False
            has_slot = free.any(axis=1)
            slot = np.argmax(free, axis=1)
            st.dropped_arrivals[rows[~has_slot]] += 1
            go = rows[has_slot]
            self._spawn_into(
                st, go, slot[has_slot], np.full(go.size, x0), v[has_slot], np.full(go.size, lane)
            )
            st.next_arrival_s[rows, lane_i] += self.rng.exponential(
                3600.0 / cfg.traffic.flow_vph_per_lane, size=rows.size
            )
            st.next_entry_speed_mps[rows, lane_i] = self._draw_entry_speed((rows.size,))
