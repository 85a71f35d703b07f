"""Where the mainline changes lanes and how hard it brakes, tallied while a ramp-flow run drives.

Two of the merge's costs that merged flow and ramp delay do not show:

- **Lane changes** of mainline vehicles (a ramp vehicle's join is not one), located where they
  happened (the position at the sample less the distance driven since the change) and counted
  per road section (`SECTIONS`): the first `ENTRANCE_M` after the entrance (a vehicle that enters
  a lane only to leave it), the rest of the upstream, beside the ramp, beside the merge zone, and
  downstream of the merge point.
- **Braking** of mainline vehicles around the merge (from `BRAKING_MARGIN_M` before the merge
  zone to `BRAKING_MARGIN_M` past the merge point), from the acceleration each realised over the
  last simulator step of every control step: the share of these samples braking harder than the
  drivers' comfortable deceleration b (IDM's `driver.comfort_brake_mps2`) and than
  `HARD_BRAKE_MPS2`, and the hardest braking seen.
- **Braking after a vehicle moves in ahead**: a mainline vehicle (that has not just changed
  lanes itself) whose new leader changed lanes into its lane in the last `RECENT_MOVE_S` (a
  cut-in, which MOBIL's `driver.safe_brake_mps2` bounds) or joined from the ramp (a join) is
  followed for `CUT_IN_WINDOW_S`: per kind, the events, those after which it braked harder than
  b, and the hardest braking.

`marlmerge.evaluation.ramp_flow` reports them with the merge's flows (`RampFlowResult`);
`marlmerge.validation.sumo` measures SUMO's mainline the same way.
"""

from __future__ import annotations

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.sim.core import TrafficCore
from marlmerge.sim.state import TrafficState

ENTRANCE_M = 50.0
BRAKING_MARGIN_M = 100.0
HARD_BRAKE_MPS2 = 4.0
SECTIONS = ("entrance", "upstream", "beside_ramp", "merge_zone", "downstream")
"""Road sections of the lane-change tally, upstream to downstream."""
UNSEEN = -2
"""`MergeTally.lane_of` of a vehicle id not seen yet."""
CUT_IN_WINDOW_S = 3.0
"""How long braking counts against a vehicle that moved in ahead (s)."""
RECENT_MOVE_S = 1.0
"""A new leader that changed lanes this recently has moved in ahead (s)."""
MOVES = ("cut_in", "join")
"""What moved in ahead: a mainline lane change, a ramp vehicle's join."""


def section_edges_m(cfg: ScenarioConfig) -> np.ndarray:
    """Upper ends (m) of the first four `SECTIONS`: a position x is in section
    `np.searchsorted(edges, x, side="right")`."""
    r = cfg.road
    return np.array([r.x_entrance_m + ENTRANCE_M, r.x_ramp_start_m, r.x_zone_start_m, 0.0])


def braking_window_m(cfg: ScenarioConfig) -> tuple[float, float]:
    """Where the mainline's braking is sampled (m)."""
    return (cfg.road.x_zone_start_m - BRAKING_MARGIN_M, BRAKING_MARGIN_M)


class MergeTally:
    """Lane changes per section and braking samples of B worlds, from the samples `add` takes
    after each control step (a vehicle's first sample only records its lane)."""

    def __init__(self, cfg: ScenarioConfig, worlds: int):
        self.edges_m = section_edges_m(cfg)
        self.braking_window_m = braking_window_m(cfg)
        self.comfort_brake_mps2 = cfg.driver.comfort_brake_mps2
        self.lane_of = np.full((worlds, 1024), UNSEEN, dtype=np.int64)
        """[B, ids] each vehicle's lane at the last sample, by its id."""
        self.leader_of = np.full((worlds, 1024), UNSEEN, dtype=np.int64)
        """[B, ids] its leader's id at the last sample (-1: none)."""
        self.moved_t = np.full((worlds, 1024), -np.inf)
        """[B, ids] when a vehicle last moved in ahead of it (s)."""
        self.moved_kind = np.zeros((worlds, 1024), dtype=np.int64)
        """[B, ids] what moved in (index in `MOVES`)."""
        self.braked = np.zeros((worlds, 1024), dtype=bool)
        """[B, ids] it has braked harder than b since."""
        self.moves = np.zeros(len(MOVES), dtype=np.int64)
        self.moves_braked = np.zeros(len(MOVES), dtype=np.int64)
        self.hardest_after = np.zeros(len(MOVES))
        self.lane_changes = np.zeros((worlds, len(SECTIONS)), dtype=np.int64)
        self.brake_samples = np.zeros(worlds, dtype=np.int64)
        self.over_comfort = np.zeros(worlds, dtype=np.int64)
        self.over_hard = np.zeros(worlds, dtype=np.int64)
        self.hardest_mps2 = 0.0

    def shares(self) -> dict[str, float | None]:
        """Each section's share of all lane changes (None: there were none)."""
        total = int(self.lane_changes.sum())
        per = self.lane_changes.sum(axis=0)
        return {
            k: (float(n) / total if total else None) for k, n in zip(SECTIONS, per, strict=True)
        }

    def braking(self) -> dict[str, float]:
        """Shares of the braking samples above b and `HARD_BRAKE_MPS2`, and the hardest (m/s^2)."""
        n = max(int(self.brake_samples.sum()), 1)
        return {
            "braking_over_b_share": float(self.over_comfort.sum()) / n,
            "braking_over_4_share": float(self.over_hard.sum()) / n,
            "hardest_braking_mps2": self.hardest_mps2,
            **{f"{k}s": int(self.moves[i]) for i, k in enumerate(MOVES)},
            **{f"{k}s_braking_over_b": int(self.moves_braked[i]) for i, k in enumerate(MOVES)},
            **{
                f"hardest_braking_after_{k}_mps2": float(self.hardest_after[i])
                for i, k in enumerate(MOVES)
            },
        }

    def add(self, core: TrafficCore) -> None:
        """Tally the samples of the state after a control step."""
        st = core.state
        main = st.active & (st.lane >= 0) & ~st.from_ramp  # [B, N] mainline vehicles
        self._grow(int(st.vehicle_id.max()) + 1)
        self._lane_changes(st, main)
        self._moves(st, main)
        lo, hi = self.braking_window_m
        near = main & (st.x_m >= lo) & (st.x_m < hi)
        decel = -st.a_mps2[near]
        self.brake_samples += near.sum(axis=1)
        per_world = np.zeros(near.shape)
        per_world[near] = decel
        self.over_comfort += (per_world > self.comfort_brake_mps2).sum(axis=1)
        self.over_hard += (per_world > HARD_BRAKE_MPS2).sum(axis=1)
        if decel.size:
            self.hardest_mps2 = max(self.hardest_mps2, float(decel.max()))

    def _grow(self, top: int) -> None:
        """Room for vehicle ids below `top` in the per-id arrays."""
        n = self.lane_of.shape[1]
        if top <= n:
            return
        for name, fill in (
            ("lane_of", UNSEEN),
            ("leader_of", UNSEEN),
            ("moved_t", -np.inf),
            ("moved_kind", 0),
            ("braked", False),
        ):
            old = getattr(self, name)
            grown = np.full((old.shape[0], 2 * top), fill, dtype=old.dtype)
            grown[:, :n] = old
            setattr(self, name, grown)

    def _moves(self, st: TrafficState, main: np.ndarray) -> None:
        """Vehicles moving in ahead, and the braking of their new followers within the window."""
        lo, hi = self.braking_window_m
        for b in range(main.shape[0]):
            s = np.flatnonzero(main[b])
            ids = st.vehicle_id[b, s]
            lead = st.leader[b, s]
            lead_id = np.where(lead >= 0, st.vehicle_id[b, np.maximum(lead, 0)], -1)
            before = self.leader_of[b, ids]
            new = (before != UNSEEN) & (lead >= 0) & (lead_id != before)
            ls = np.maximum(lead, 0)
            joined = st.from_ramp[b, ls]
            moved = (
                new
                & (st.since_lane_change_s[b, ls] <= RECENT_MOVE_S)  # the leader just moved in
                & (st.since_lane_change_s[b, s] > RECENT_MOVE_S)  # not the follower moving
            )
            if moved.any():
                kind = joined[moved].astype(np.int64)  # MOVES order: cut_in 0, join 1
                self.moved_t[b, ids[moved]] = st.t_s[b]
                self.moved_kind[b, ids[moved]] = kind
                self.braked[b, ids[moved]] = False
                np.add.at(self.moves, kind, 1)
            self.leader_of[b, ids] = lead_id
            within = (st.t_s[b] - self.moved_t[b, ids] <= CUT_IN_WINDOW_S) & (
                (st.x_m[b, s] >= lo) & (st.x_m[b, s] < hi)
            )
            if not within.any():
                continue
            w_ids = ids[within]
            decel = -st.a_mps2[b, s[within]]
            kind = self.moved_kind[b, w_ids]
            np.maximum.at(self.hardest_after, kind, decel)
            first = (decel > self.comfort_brake_mps2) & ~self.braked[b, w_ids]
            np.add.at(self.moves_braked, kind[first], 1)
            self.braked[b, w_ids[first]] = True

    def _lane_changes(self, st: TrafficState, main: np.ndarray) -> None:
        ids, lanes = st.vehicle_id, st.lane
        for b in range(main.shape[0]):
            s = np.flatnonzero(main[b])
            before = self.lane_of[b, ids[b, s]]
            moved = (before >= 0) & (before != lanes[b, s])
            if moved.any():
                m = s[moved]
                x = st.x_m[b, m] - st.v_mps[b, m] * st.since_lane_change_s[b, m]
                section = np.searchsorted(self.edges_m, x, side="right")
                np.add.at(self.lane_changes[b], section, 1)
            self.lane_of[b, ids[b, s]] = lanes[b, s]
