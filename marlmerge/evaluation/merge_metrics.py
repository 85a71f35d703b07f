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

import math
from typing import Any

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


def ratio_interval(num: np.ndarray, den: np.ndarray) -> tuple[float, float]:
    """95 % interval of the pooled share sum(num) / sum(den) of samples counted per world [B],
    the worlds taken as independent clusters (the samples of one world are not: a vehicle
    brakes over several control steps): the ratio estimator's linearised variance, normal
    quantile, clipped to [0, 1]; (NaN, NaN) from fewer than two worlds or without samples."""
    n, total = num.size, float(den.sum())
    if n < 2 or total <= 0.0:
        return (math.nan, math.nan)
    share = float(num.sum()) / total
    resid = num - share * den  # [B]
    half = 1.96 * math.sqrt(n / (n - 1) * float((resid * resid).sum())) / total
    return (max(share - half, 0.0), min(share + half, 1.0))


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

    def shares_ci95(self) -> dict[str, tuple[float, float]]:
        """95 % intervals over worlds of `shares` (`ratio_interval`)."""
        total = self.lane_changes.sum(axis=1)  # [B]
        return {k: ratio_interval(self.lane_changes[:, i], total) for i, k in enumerate(SECTIONS)}

    def braking(self) -> dict[str, Any]:
        """Shares of the braking samples above b and `HARD_BRAKE_MPS2` with their 95 % intervals
        over worlds, the hardest (m/s^2), and the braking after vehicles moved in ahead."""
        n = max(int(self.brake_samples.sum()), 1)
        return {
            "braking_over_b_share": float(self.over_comfort.sum()) / n,
            "braking_over_b_share_ci95": ratio_interval(self.over_comfort, self.brake_samples),
            "braking_over_4_share": float(self.over_hard.sum()) / n,
            "braking_over_4_share_ci95": ratio_interval(self.over_hard, self.brake_samples),
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
        b, s = np.nonzero(main)  # [M] each: world and slot of every mainline vehicle
        ids = st.vehicle_id[b, s]
        self._lane_changes(st, b, s, ids)
        self._moves(st, b, s, ids)
        lo, hi = self.braking_window_m
        near = main & (st.x_m >= lo) & (st.x_m < hi)  # [B, N] sampled for braking
        decel = np.where(near, -st.a_mps2, 0.0)  # [B, N] m/s^2, 0 where not sampled
        self.brake_samples += near.sum(axis=1)
        self.over_comfort += (decel > self.comfort_brake_mps2).sum(axis=1)
        self.over_hard += (decel > HARD_BRAKE_MPS2).sum(axis=1)
        self.hardest_mps2 = max(self.hardest_mps2, float(decel.max(initial=0.0)))

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

    def _moves(self, st: TrafficState, b: np.ndarray, s: np.ndarray, ids: np.ndarray) -> None:
        """Vehicles moving in ahead of the mainline vehicles (b, s) (ids `ids`), and the braking
        of their followers within the window."""
        since = st.since_lane_change_s
        lead = st.leader[b, s]
        ls = np.maximum(lead, 0)
        lead_id = np.where(lead >= 0, st.vehicle_id[b, ls], -1)
        before = self.leader_of[b, ids]
        moved = (
            (before != UNSEEN)
            & (lead >= 0)
            & (lead_id != before)
            & (since[b, ls] <= RECENT_MOVE_S)  # the leader just moved in
            & (since[b, s] > RECENT_MOVE_S)  # not the follower moving
        )
        t = st.t_s[b]
        if moved.any():
            kind = st.from_ramp[b[moved], ls[moved]].astype(np.int64)  # MOVES: cut_in, join
            self.moved_t[b[moved], ids[moved]] = t[moved]
            self.moved_kind[b[moved], ids[moved]] = kind
            self.braked[b[moved], ids[moved]] = False
            np.add.at(self.moves, kind, 1)
        self.leader_of[b, ids] = lead_id
        lo, hi = self.braking_window_m
        x = st.x_m[b, s]
        within = (t - self.moved_t[b, ids] <= CUT_IN_WINDOW_S) & (x >= lo) & (x < hi)
        if not within.any():
            return
        wb, w_ids = b[within], ids[within]
        decel = -st.a_mps2[wb, s[within]]
        kind = self.moved_kind[wb, w_ids]
        np.maximum.at(self.hardest_after, kind, decel)
        first = (decel > self.comfort_brake_mps2) & ~self.braked[wb, w_ids]
        np.add.at(self.moves_braked, kind[first], 1)
        self.braked[wb[first], w_ids[first]] = True

    def _lane_changes(
        self, st: TrafficState, b: np.ndarray, s: np.ndarray, ids: np.ndarray
    ) -> None:
        """Lane changes of the mainline vehicles (b, s) since their last sample."""
        lanes = st.lane[b, s]
        before = self.lane_of[b, ids]
        moved = (before >= 0) & (before != lanes)
        if moved.any():
            mb, ms = b[moved], s[moved]
            x = st.x_m[mb, ms] - st.v_mps[mb, ms] * st.since_lane_change_s[mb, ms]
            section = np.searchsorted(self.edges_m, x, side="right")
            np.add.at(self.lane_changes, (mb, section), 1)
        self.lane_of[b, ids] = lanes
