"""The validation scenarios in SUMO (the optional `[sumo]` extra: eclipse-sumo, libsumo, sumolib).

The networks are built from the `ScenarioConfig` with netconvert, on the same axis: a road whose
lane positions are marlmerge's road positions (0 at the entrance). Drivers use SUMO's IDM
(`carFollowModel="IDM"`, ballistic update) with marlmerge's parameters: accel = a, decel = b,
minGap = s0, tau = T, delta, emergencyDecel = the vehicle's braking limit, length; the desired
speed v0 is the lane speed times a per-vehicle `speedFactor`. Lane changes use SUMO's own
model (LC2013). A SUMO vehicle inserted at time 0 stands at its start position after the first
step; samples are aligned so that sample 0 is that start in both simulators.
"""

from __future__ import annotations

import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.validation.measure import FlowSamples
from marlmerge.validation.scenarios import (
    CF_ROAD_M,
    CarFollowingCase,
    Trajectories,
    drawn_arrivals,
    drawn_ramp_arrivals,
)


def available() -> bool:
    """True when libsumo and sumolib can be imported (the `[sumo]` extra is installed)."""
    try:
        import libsumo  # noqa: F401
        import sumolib  # noqa: F401
    except ImportError:
        return False
    return True


def sumo_version() -> str:
    import libsumo

    return str(libsumo.getVersion()[1]).replace("SUMO ", "")


def _netconvert(
    folder: Path, length_m: float, n_lanes: int, speed_mps: float, width_m: float
) -> Path:
    import sumolib

    (folder / "road.nod.xml").write_text(
        f'<nodes><node id="a" x="0" y="0"/><node id="b" x="{length_m}" y="0"/></nodes>'
    )
    (folder / "road.edg.xml").write_text(
        f'<edges><edge id="road" from="a" to="b" numLanes="{n_lanes}" speed="{speed_mps}" '
        f'width="{width_m}"/></edges>'
    )
    net = folder / "road.net.xml"
    subprocess.run(
        [
            sumolib.checkBinary("netconvert"),
            "-n", str(folder / "road.nod.xml"), "-e", str(folder / "road.edg.xml"),
            "-o", str(net), "--no-turnarounds",
        ],
        check=True,
        capture_output=True,
    )  # fmt: skip
    return net


def _vtype(cfg: ScenarioConfig, vid: str, speed_factor: float, tau_s: float) -> str:
    d, v = cfg.driver, cfg.vehicle
    return (
        f'<vType id="{vid}" carFollowModel="IDM" accel="{d.accel_mps2}" '
        f'decel="{d.comfort_brake_mps2}" emergencyDecel="{v.max_brake_mps2}" '
        f'minGap="{d.min_gap_m}" tau="{float(tau_s)!r}" delta="{d.delta}" length="{v.length_m}" '
        f'width="{v.width_m}" maxSpeed="100" speedFactor="{float(speed_factor)!r}" speedDev="0" '
        f'sigma="0"/>'
    )


def _start(net: Path, routes: Path, dt_s: float, seed: int) -> None:
    import libsumo

    libsumo.start(
        [
            "sumo", "-n", str(net), "-r", str(routes), "--step-length", str(dt_s),
            "--step-method.ballistic", "--no-step-log", "--no-warnings", "--seed", str(seed),
            "--collision.action", "warn",
        ]
    )  # fmt: skip


def run_car_following(case: CarFollowingCase, cfg: ScenarioConfig) -> Trajectories:
    """The case in SUMO: the leader's speed is set every step (checks off), the follower
    drives by SUMO's IDM."""
    import libsumo as traci

    dt = cfg.sim.dt_s
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        net = _netconvert(folder, CF_ROAD_M, 1, 100.0, cfg.road.lane_width_m)
        lines = ['<routes><route id="r" edges="road"/>']
        lines.append(_vtype(cfg, "follower_t", case.v0_mps / 100.0, case.headway_s))
        if case.leader_pos_m is not None:
            lines.append(_vtype(cfg, "leader_t", 1.0, 1.0))
            lines.append(
                f'<vehicle id="leader" type="leader_t" route="r" depart="0" '
                f'departPos="{case.leader_pos_m}" departSpeed="{case.leader_v_mps}"/>'
            )
        lines.append(
            f'<vehicle id="follower" type="follower_t" route="r" depart="0" '
            f'departPos="{case.follower_pos_m}" departSpeed="{case.follower_v_mps}"/>'
        )
        lines.append("</routes>")
        routes = folder / "cf.rou.xml"
        routes.write_text("\n".join(lines))
        _start(net, routes, dt, 0)
        try:
            traci.simulationStep()  # inserts the vehicles at their start
            n = int(round(case.duration_s / dt))
            rows = np.full((n + 1, 4), np.nan)
            has_leader = case.leader_pos_m is not None
            if has_leader:
                traci.vehicle.setSpeedMode("leader", 0)
            for i in range(n + 1):
                rows[i, 0] = traci.vehicle.getLanePosition("follower")
                rows[i, 1] = traci.vehicle.getSpeed("follower")
                if has_leader:
                    v = traci.vehicle.getSpeed("leader")
                    rows[i, 2:4] = traci.vehicle.getLanePosition("leader"), v
                    target = max(v + case.leader_accel_at(i * dt) * dt, 0.0)
                    traci.vehicle.setSpeed("leader", target)
                if i < n:
                    traci.simulationStep()
        finally:
            traci.close()
    return Trajectories(np.arange(n + 1) * dt, *rows.T)


def _drawn_vehicles(
    cfg: ScenarioConfig,
    rows: list[tuple],
    vehicle: str,
    vtype: str,
    route: str,
    lane_rule: str = "drawn",
) -> tuple[list[str], list[tuple[float, str]]]:
    """vTypes and (departure s, vehicle line) of drawn vehicles `rows` (time, lane, speed,
    desired speed, headway), named `{vehicle}{i}` of type `{vtype}{i}`: each departs at its
    drawn time in its lane (`lane_rule` "drawn") or in SUMO's best lane (`"best"`,
    `departLane="best"`, as `traffic.entrance_lane = "best"`), at its drawn speed
    (`departSpeed`: SUMO delays the insertion until that speed is safe), with its drawn desired
    speed and headway."""
    v_limit = cfg.road.speed_limit_mps
    types = [_vtype(cfg, f"{vtype}{i}", v0 / v_limit, hw) for i, (*_, v0, hw) in enumerate(rows)]
    vehicles = []
    for i, (t, lane, v, v0, _) in enumerate(rows):
        v = float(min(v, v0 * (1 - 1e-12)))  # <= v0 also after rounding
        depart = f"{t:.1f}"
        vehicles.append(
            (
                float(depart),
                f'<vehicle id="{vehicle}{i}" type="{vtype}{i}" route="{route}" depart="{depart}" '
                f'departLane="{lane if lane_rule == "drawn" else lane_rule}" departPos="0" '
                f'departSpeed="{v!r}"/>',
            )
        )
    return types, vehicles


def _mainline_vehicles(
    cfg: ScenarioConfig, seed: int | np.random.SeedSequence, duration_s: float, route: str
) -> tuple[list[str], list[tuple[float, str]]]:
    """`_drawn_vehicles` of the arrivals marlmerge draws for a world seeded `seed`, in time
    order, entering as `traffic.entrance_lane` says."""
    arrivals = drawn_arrivals(cfg, seed, duration_s)
    rows = sorted((t, lane, v, v0, hw) for lane, a in enumerate(arrivals) for t, v, v0, hw in a)
    return _drawn_vehicles(cfg, rows, "v", "t", route, cfg.traffic.entrance_lane)


def _mainline_routes(
    cfg: ScenarioConfig, seed: int | np.random.SeedSequence, duration_s: float, route: str
) -> list[str]:
    """vTypes and vehicles of the arrivals marlmerge draws for a world seeded `seed`."""
    types, vehicles = _mainline_vehicles(cfg, seed, duration_s, route)
    return types + [line for _, line in vehicles]


def run_flow(cfg: ScenarioConfig, seed: int, duration_s: float) -> FlowSamples:
    """The mainline alone in SUMO, fed the arrivals marlmerge draws for a world seeded `seed`
    (`_mainline_routes`), every vehicle sampled every step."""
    import libsumo as traci

    dt = cfg.sim.dt_s
    road = cfg.road
    length = road.x_exit_m - road.x_entrance_m
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        net = _netconvert(folder, length, 2, road.speed_limit_mps, road.lane_width_m)
        lines = ['<routes><route id="r" edges="road"/>']
        lines += _mainline_routes(cfg, seed, duration_s, "r")
        lines.append("</routes>")
        routes = folder / "flow.rou.xml"
        routes.write_text("\n".join(lines))
        _start(net, routes, dt, seed)
        parts = []
        try:
            for i in range(int(round(duration_s / dt))):
                traci.simulationStep()
                ids = traci.vehicle.getIDList()
                if not ids:
                    continue
                t = np.full(len(ids), (i + 1) * dt)
                vid = np.array([int(v[1:]) for v in ids])
                lane = np.array([traci.vehicle.getLaneIndex(v) for v in ids])
                pos = np.array([traci.vehicle.getLanePosition(v) for v in ids])
                speed = np.array([traci.vehicle.getSpeed(v) for v in ids])
                parts.append((t, vid, lane, pos, speed))
        finally:
            traci.close()
    return FlowSamples(*(np.concatenate([p[j] for p in parts]) for j in range(5)))


def ramp_network(folder: Path, cfg: ScenarioConfig) -> Path:
    """The scenario's road with its ramp as a SUMO network in `folder`: the two mainline lanes
    (edge `up`), the merge zone with the acceleration lane as its lane 0 (edge `zone`, from
    x = -merge_zone_m to the merge point x = 0), the road downstream (`down`) and the ramp
    (`ramp`, from the ramp start), all on marlmerge's x axis."""
    import sumolib

    road = cfg.road
    x0, zone, v = road.x_entrance_m, road.x_zone_start_m, road.speed_limit_mps
    y_ramp = -road.ramp_offset_m * 2
    (folder / "n.nod.xml").write_text(
        f'<nodes><node id="in" x="{x0}" y="0"/><node id="zone" x="{zone}" y="0"/>'
        f'<node id="merge" x="0" y="0"/><node id="out" x="{road.x_exit_m}" y="0"/>'
        f'<node id="ramp" x="{road.x_ramp_start_m}" y="{y_ramp}"/></nodes>'
    )
    (folder / "n.edg.xml").write_text(
        f'<edges><edge id="up" from="in" to="zone" numLanes="2" speed="{v}"/>'
        f'<edge id="zone" from="zone" to="merge" numLanes="3" speed="{v}"/>'
        f'<edge id="down" from="merge" to="out" numLanes="2" speed="{v}"/>'
        f'<edge id="ramp" from="ramp" to="zone" numLanes="1" speed="{v}" '
        f'width="{road.ramp_width_m}"/></edges>'
    )
    (folder / "n.con.xml").write_text(
        '<connections><connection from="up" to="zone" fromLane="0" toLane="1"/>'
        '<connection from="up" to="zone" fromLane="1" toLane="2"/>'
        '<connection from="ramp" to="zone" fromLane="0" toLane="0"/>'
        '<connection from="zone" to="down" fromLane="1" toLane="0"/>'
        '<connection from="zone" to="down" fromLane="2" toLane="1"/></connections>'
    )
    net = folder / "n.net.xml"
    subprocess.run(
        [
            sumolib.checkBinary("netconvert"), "-n", str(folder / "n.nod.xml"),
            "-e", str(folder / "n.edg.xml"), "-x", str(folder / "n.con.xml"),
            "-o", str(net), "--no-turnarounds", "--default.lanewidth",
            str(road.lane_width_m),
        ],
        check=True,
        capture_output=True,
    )  # fmt: skip
    return net


class RampRoad:
    """The scenario's road with its ramp in SUMO, for speed comparisons: the two mainline lanes
    fed by marlmerge's drawn arrivals, and a ramp vehicle sent whenever the previous one has
    left the ramp and the merge zone (one merging vehicle at a time, as in marlmerge).

        with RampRoad(cfg, duration_s=3600) as road:
            road.step()              # one simulator step, the ramp bookkeeping included
    """

    def __init__(self, cfg: ScenarioConfig, duration_s: float, seed: int = 0):
        self.cfg, self.duration_s, self.seed = cfg, duration_s, seed
        self._tmp: tempfile.TemporaryDirectory | None = None
        self.egos = 0

    def __enter__(self) -> RampRoad:
        import libsumo as traci

        cfg = self.cfg
        self._tmp = tempfile.TemporaryDirectory()
        folder = Path(self._tmp.name)
        net = ramp_network(folder, cfg)
        lines = ['<routes><route id="main" edges="up zone down"/>']
        lines.append('<route id="ramp" edges="ramp zone down"/>')
        lines.append(_vtype(cfg, "ego_t", 1.0, float(np.mean(cfg.driver.time_headway_s))))
        lines += _mainline_routes(cfg, self.seed, self.duration_s, "main")
        lines.append("</routes>")
        routes = folder / "n.rou.xml"
        routes.write_text("\n".join(lines))
        _start(net, routes, cfg.sim.dt_s, self.seed)
        self._traci = traci
        self._ego: str | None = None
        return self

    def step(self) -> None:
        traci = self._traci
        if self._ego is not None:
            on = traci.vehicle.getRoadID(self._ego)  # "" while waiting to depart or when gone
            if on:
                self._on_road = True
            done = self._on_road and on not in ("ramp", "zone")
        if self._ego is None or done:
            self._ego, self._on_road = f"ego{self.egos}", False
            self.egos += 1
            traci.vehicle.add(self._ego, "ramp", typeID="ego_t", departSpeed="21")
        traci.simulationStep()

    def vehicle_count(self) -> int:
        return self._traci.vehicle.getIDCount()

    def __exit__(self, *exc: object) -> None:
        self._traci.close()
        if self._tmp is not None:
            self._tmp.cleanup()


def _ramp_routes(
    cfg: ScenarioConfig, seed: int | np.random.SeedSequence, duration_s: float
) -> list[str]:
    """The mainline's drawn arrivals (`_mainline_vehicles`) and the ramp's (`drawn_ramp_arrivals`,
    vehicles `r{i}` on route `ramp`) for a world seeded `seed`, vehicles sorted by departure."""
    types, vehicles = _mainline_vehicles(cfg, seed, duration_s, "main")
    ramp = [(t, 0, v, v0, hw) for t, v, v0, hw in drawn_ramp_arrivals(cfg, seed, duration_s)]
    ramp_types, ramp_vehicles = _drawn_vehicles(cfg, ramp, "r", "rt", "ramp")
    ordered = sorted(vehicles + ramp_vehicles, key=lambda tv: tv[0])  # stable: mainline first
    return types + ramp_types + [line for _, line in ordered]


def run_merge(
    cfg: ScenarioConfig,
    seed: int | np.random.SeedSequence,
    duration_s: float,
    skip_s: float,
    sumo_seed: int = 0,
) -> dict[str, float]:
    """Ramp flow in SUMO: the road of `ramp_network` fed the mainline and ramp arrivals that a
    marlmerge world seeded `seed` draws (`ramp.flow_vph > 0`), SUMO's LC2013 merging from the
    acceleration lane (a vehicle that finds no gap stops at its end). Counted in the window
    [skip_s, duration_s]: ramp vehicles that entered and passed the merge point (entering
    `down`), their summed travel times from their drawn arrival and entrance waits, collisions
    and teleports, and the mainline's summed speeds and samples in the merge zone and upstream of
    the ramp start (every 4 steps)."""
    import libsumo as traci

    from marlmerge.evaluation.ramp_flow import UPSTREAM_WINDOW_M

    dt, road = cfg.sim.dt_s, cfg.road
    drawn = {f"r{i}": row[0] for i, row in enumerate(drawn_ramp_arrivals(cfg, seed, duration_s))}
    up_lo = road.x_ramp_start_m - UPSTREAM_WINDOW_M - road.x_entrance_m  # lane positions on `up`
    up_hi = road.x_ramp_start_m - road.x_entrance_m
    out = dict.fromkeys(("entered", "passed", "travel_s", "wait_s", "collisions", "teleports"), 0.0)
    speeds = np.zeros(4)
    mainline = _MainlineTally(cfg)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        net = ramp_network(folder, cfg)
        routes = folder / "merge.rou.xml"
        lines = ['<routes><route id="main" edges="up zone down"/>']
        lines.append('<route id="ramp" edges="ramp zone down"/>')
        routes.write_text("\n".join(lines + _ramp_routes(cfg, seed, duration_s) + ["</routes>"]))
        _start(net, routes, dt, sumo_seed)
        on_ramp: dict[str, float] = {}
        try:
            for i in range(int(round(duration_s / dt))):
                traci.simulationStep()
                t = (i + 1) * dt
                counting = t >= skip_s - 1e-9
                for vid in traci.simulation.getDepartedIDList():
                    if vid in drawn:
                        on_ramp[vid] = drawn[vid]
                        if counting:
                            out["entered"] += 1
                            out["wait_s"] += t - drawn[vid]
                for vid in [v for v in on_ramp if traci.vehicle.getRoadID(v) == "down"]:
                    if counting:
                        out["passed"] += 1
                        out["travel_s"] += t - on_ramp[vid]
                    del on_ramp[vid]
                if counting:
                    out["collisions"] += sum(
                        1 for v in traci.simulation.getCollidingVehiclesIDList() if v in drawn
                    )
                    out["teleports"] += len(traci.simulation.getStartingTeleportIDList())
                if counting and i % 4 == 3:
                    mainline.sample(traci, drawn)
                    for lane in ("zone_1", "zone_2"):
                        n = traci.lane.getLastStepVehicleNumber(lane)
                        speeds[0] += traci.lane.getLastStepMeanSpeed(lane) * n
                        speeds[1] += n
                    for lane in ("up_0", "up_1"):
                        for v in traci.lane.getLastStepVehicleIDs(lane):
                            if up_lo <= traci.vehicle.getLanePosition(v) < up_hi:
                                speeds[2] += traci.vehicle.getSpeed(v)
                                speeds[3] += 1
        finally:
            traci.close()
    names = ("speed_merge_sum", "speed_merge_n", "speed_up_sum", "speed_up_n")
    out.update(zip(names, speeds.tolist(), strict=True))
    return out | mainline.counts()


class _MainlineTally:
    """SUMO's mainline measured as `marlmerge.evaluation.merge_metrics` measures marlmerge's:
    lane changes per road section and braking around the merge, sampled every control step (a
    lane change is placed half a sample's drive before where it is first seen). Mainline:
    every vehicle but ramp vehicles before the merge point."""

    def __init__(self, cfg: ScenarioConfig):
        from marlmerge.evaluation.merge_metrics import (
            HARD_BRAKE_MPS2,
            SECTIONS,
            braking_window_m,
            section_edges_m,
        )

        road = cfg.road
        self.edges_m, self.window_m = section_edges_m(cfg), braking_window_m(cfg)
        self.hard, self.b = HARD_BRAKE_MPS2, cfg.driver.comfort_brake_mps2
        self.half_sample_s = 2 * cfg.sim.dt_s
        # edge -> (x of its start, marlmerge lane of each SUMO lane index; -1: not mainline)
        self.edges = {
            "up": (road.x_entrance_m, (0, 1)),
            "zone": (road.x_zone_start_m, (-1, 0, 1)),
            "down": (0.0, (0, 1)),
        }
        self.lane_of: dict[str, int] = {}
        self.lane_changes = np.zeros(len(SECTIONS))
        self.brake = np.zeros(3)  # samples, harder than b, harder than HARD_BRAKE_MPS2
        self.hardest = 0.0

    def sample(self, traci: Any, ramp_ids: dict[str, float]) -> None:
        for vid in traci.vehicle.getIDList():
            edge = traci.vehicle.getRoadID(vid)
            if edge not in self.edges or (vid in ramp_ids and edge != "down"):
                continue
            x0, lanes = self.edges[edge]
            lane = lanes[traci.vehicle.getLaneIndex(vid)]
            if lane < 0:
                continue
            x = x0 + traci.vehicle.getLanePosition(vid)
            before = self.lane_of.get(vid, lane)
            self.lane_of[vid] = lane
            if before != lane:
                at = x - traci.vehicle.getSpeed(vid) * self.half_sample_s
                self.lane_changes[int(np.searchsorted(self.edges_m, at, side="right"))] += 1
            if self.window_m[0] <= x < self.window_m[1]:
                decel = -traci.vehicle.getAcceleration(vid)
                self.brake += (1.0, decel > self.b, decel > self.hard)
                self.hardest = max(self.hardest, decel)

    def counts(self) -> dict[str, float]:
        from marlmerge.evaluation.merge_metrics import SECTIONS

        out = {
            f"lane_changes_{k}": float(n) for k, n in zip(SECTIONS, self.lane_changes, strict=True)
        }
        names = ("brake_samples", "brake_over_b", "brake_over_4")
        return (
            out
            | dict(zip(names, self.brake.tolist(), strict=True))
            | {"hardest_braking_mps2": self.hardest}
        )
