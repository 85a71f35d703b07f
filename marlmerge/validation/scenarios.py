"""What the validation runs, and how marlmerge runs it.

Positions here are metres from the start of the road (SUMO's lane position), so both simulators
read the same numbers; marlmerge's axis (`x_m`, 0 at the merge point) is that minus the length
of the road upstream of the merge point.

- Car following (`CASES`): one IDM follower with fixed parameters behind a leader whose
  acceleration is prescribed (none, braking and recovering, standing still), on one lane.
- Flow sweep (`FLOWS_VPHPL`): the scenario's two mainline lanes without a ramp vehicle, fed by
  the scenario's random arrivals at each flow. Both simulators get the same drawn vehicles:
  arrival time, lane, entry speed, desired speed and headway (`drawn_arrivals`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.sim import LEFT, TrafficCore
from marlmerge.sim.layout import SC_T, SC_T_HW, SC_V, SC_V0
from marlmerge.sim.streams import (
    SCENARIO_STREAM,
    Streams,
    draw_world_scenario,
    world_seed_sequences,
)
from marlmerge.validation.measure import FlowSamples

FLOWS_VPHPL = (600.0, 1200.0, 1800.0, 2400.0)
"""Demand per lane of the flow sweep."""
CF_ROAD_M = 3900.0
"""Length of the single-lane road of the car-following cases."""


@dataclass(frozen=True)
class CarFollowingCase:
    """A leader with a prescribed acceleration profile and an IDM follower behind it."""

    name: str
    doc: str
    duration_s: float
    follower_pos_m: float
    follower_v_mps: float
    leader_pos_m: float | None = None  # None: no leader (free road)
    leader_v_mps: float = 0.0
    leader_accel: tuple[tuple[float, float, float], ...] = ()
    """(t_from_s, t_to_s, accel_mps2) pieces; zero elsewhere."""
    v0_mps: float = 30.0
    headway_s: float = 1.5

    def leader_accel_at(self, t_s: float) -> float:
        """The leader's acceleration over the step that starts at `t_s`."""
        for t0, t1, a in self.leader_accel:
            if t0 - 1e-9 <= t_s < t1 - 1e-9:
                return a
        return 0.0


CASES = (
    CarFollowingCase("free_road", "free road from 10 m/s to the desired 30 m/s", 60.0, 100.0, 10.0),
    CarFollowingCase(
        "leader_braking",
        "leader at 25 m/s brakes at 3 m/s^2 to 10 m/s, holds, accelerates back at 1 m/s^2",
        80.0,
        100.0,
        25.0,
        leader_pos_m=160.0,
        leader_v_mps=25.0,
        leader_accel=((10.0, 15.0, -3.0), (35.0, 50.0, 1.0)),
    ),
    CarFollowingCase(
        "approach_stopped",
        "approach at 25 m/s to a car standing 500 m ahead",
        60.0,
        100.0,
        25.0,
        leader_pos_m=600.0,
        leader_v_mps=0.0,
    ),
)


@dataclass
class Trajectories:
    """A car-following run sampled every step ([T+1] each, sample 0 at t = 0)."""

    t_s: np.ndarray
    follower_pos_m: np.ndarray
    follower_v_mps: np.ndarray
    leader_pos_m: np.ndarray  # nan without a leader
    leader_v_mps: np.ndarray


def car_following_config(cfg: ScenarioConfig) -> ScenarioConfig:
    """The scenario's drivers on a long empty road: no arrivals, no lane changes."""
    return cfg.replace(
        **{
            "road.highway_upstream_m": CF_ROAD_M - 100.0,
            "road.highway_downstream_m": 100.0,
            "traffic.flow_vph_per_lane": 0.0,
            "traffic.warmup_s": 0.0,
            "driver.lane_change_threshold_mps2": 1.0e6,
        }
    )


def run_car_following(case: CarFollowingCase, cfg: ScenarioConfig) -> Trajectories:
    """The case in marlmerge: the leader is a controlled highway agent."""
    cfg = car_following_config(cfg)
    x0 = cfg.road.x_entrance_m  # road position 0
    core = TrafficCore(cfg, batch_size=1, seed=0)
    core.clear_traffic()
    follower = core.add_vehicle(
        0, x0 + case.follower_pos_m, case.follower_v_mps, LEFT, case.v0_mps, case.headway_s
    )
    roster, cmd = None, None
    if case.leader_pos_m is not None:
        leader = core.add_vehicle(0, x0 + case.leader_pos_m, case.leader_v_mps, LEFT, 1.0e3, 1.0)
        roster = core.make_roster(np.array([[leader]]))
        cmd = np.zeros((1, 1))
    n = int(round(case.duration_s / cfg.sim.dt_s))
    rows = np.zeros((n + 1, 4))
    st = core.state

    def sample(i: int) -> None:
        rows[i, 0:2] = st.x_m[0, follower] - x0, st.v_mps[0, follower]
        if roster is not None:
            rows[i, 2:4] = st.x_m[0, leader] - x0, st.v_mps[0, leader]
        else:
            rows[i, 2:4] = np.nan

    sample(0)
    nan = np.full(1, np.nan)
    for i in range(n):
        if cmd is not None:
            cmd[0, 0] = case.leader_accel_at(i * cfg.sim.dt_s)
        core.step(nan, roster, cmd)
        sample(i + 1)
    return Trajectories(np.arange(n + 1) * cfg.sim.dt_s, *rows.T)


def flow_config(cfg: ScenarioConfig, flow_vphpl: float) -> ScenarioConfig:
    """The scenario at another mainline demand."""
    return cfg.replace(**{"traffic.flow_vph_per_lane": float(flow_vphpl)})


def _world_streams(cfg: ScenarioConfig, seed: int | np.random.SeedSequence) -> Streams:
    """The generators of one world seeded `seed` (with `[sample]`, in the traffic it draws at its
    first reset)."""
    streams = Streams(cfg, 1)
    streams.seed(np.array([0]), world_seed_sequences(1, [seed], np.array([0])))
    if cfg.sample.active:
        streams.cfgs[0] = draw_world_scenario(cfg, streams.gens[0][SCENARIO_STREAM])
    return streams


def _drawn_until(draw: Callable[[float], np.ndarray], duration_s: float) -> np.ndarray:
    """The chunks `draw(t_last)` gives, one after the other, up to `duration_s`: [n, 4] of
    (time s, speed m/s, desired speed m/s, time headway s)."""
    chunks, t_last = [], 0.0
    while t_last <= duration_s:
        c = draw(t_last)
        chunks.append(c)
        t_last = float(c[-1, SC_T])
    a = np.concatenate(chunks)
    return a[a[:, SC_T] <= duration_s][:, [SC_T, SC_V, SC_V0, SC_T_HW]]


def drawn_ramp_arrivals(
    cfg: ScenarioConfig, seed: int | np.random.SeedSequence, duration_s: float
) -> np.ndarray:
    """Ramp flow: the ramp vehicles a world seeded `seed` draws up to `duration_s`, [n, 4] of
    (time s, start speed m/s, desired speed m/s, time headway s)."""
    streams = _world_streams(cfg, seed)
    return _drawn_until(functools.partial(streams.ramp_arrivals, 0), duration_s)


def drawn_arrivals(
    cfg: ScenarioConfig, seed: int | np.random.SeedSequence, duration_s: float
) -> list[np.ndarray]:
    """The arrivals a world seeded `seed` draws for each lane up to `duration_s` (with `[sample]`,
    in the traffic it draws first): per lane an array [n, 4] of (time s, entry speed m/s, desired
    speed m/s, time headway s)."""
    streams = _world_streams(cfg, seed)
    return [
        _drawn_until(functools.partial(streams.arrivals, 0, lane), duration_s) for lane in range(2)
    ]


def run_flow(cfg: ScenarioConfig, seed: int, duration_s: float) -> FlowSamples:
    """The mainline alone in marlmerge (a world seeded `seed`, its ramp vehicle removed), every
    vehicle sampled every step. The road starts filled in steady flow, as marlmerge's roads do;
    measurements skip the first minutes in both simulators."""
    cfg = cfg.replace(**{"traffic.warmup_s": 0.0})
    core = TrafficCore(cfg, batch_size=1, seed=[seed])
    core.remove_ego()
    st = core.state
    x0 = cfg.road.x_entrance_m
    parts: list[tuple[np.ndarray, ...]] = []
    nan = np.full(1, np.nan)
    for i in range(int(round(duration_s / cfg.sim.dt_s))):
        core.step(nan)
        on = st.active[0]
        t = np.full(int(on.sum()), (i + 1) * cfg.sim.dt_s)
        parts.append((t, st.vehicle_id[0][on], st.lane[0][on], st.x_m[0][on] - x0, st.v_mps[0][on]))
    return FlowSamples(*(np.concatenate([p[j] for p in parts]) for j in range(5)))
