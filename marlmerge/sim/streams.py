"""Every random draw of the simulator, made with seeded NumPy generators outside the kernels
(attention lapses are drawn inside them, from a key drawn here: `marlmerge.sim.lapses`).

Each world has four generators, spawned from one `numpy.random.SeedSequence`: the arrivals of
the right lane, of the left lane, the ego departures, and the road filled at a reset; with sensor
noise on (`[sensing]`) a fifth, the ego sensor's measurement errors (spawning a fifth child leaves
the first four as they were); with `[sample]` a sixth, its drawn traffic; with attention lapses
(`driver.lapse_rate_per_h`) a seventh, the key of each road's lapse draws. Arrivals and
departures are drawn ahead in fixed chunks (`CHUNK` vehicles: time, speed and the driver's
parameters) into the world's `sched` ring, measurement errors in chunks of `CHUNK` measurements
into its noise ring, which the kernels consume. The arrivals and departures are drawn by
`marlmerge.sim.draws` in one compiled call, from the same generators and bit for bit as
`arrivals`, `ramp_arrivals` and `departures` below draw them. The stream of numbers a world sees is
fixed by its seed alone, whatever the batch it runs in, the action repeat, or when the chunks
happen to be drawn. One exception: a reset without a seed (a new road mid-run, as `[sample]`'s
`resample_every_egos` makes) throws away what its world had drawn ahead, and it draws ahead
in every world of its draw group (`marlmerge.sim.core.draw_groups`), so with such resets a
world's later numbers depend on its group's other worlds; never on another group's.

Seeds: `seed=s` for a batch of B worlds gives world i the sequence `SeedSequence(s,
spawn_key=(i,))`; an explicit per-world seed s_i gives `SeedSequence(s_i, spawn_key=(0,))`, the
same world as world 0 of a core seeded s_i (so B single worlds can reproduce one batch); a
per-world `SeedSequence` is used as it is (the grid keys its roads that way).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from marlmerge.config import MPH_TO_MPS, ScenarioConfig, to_dict
from marlmerge.sim import draws as dr
from marlmerge.sim.drivers import entry_speed
from marlmerge.sim.layout import (
    EGO_STREAM,
    LEFT,
    NEUTRAL,
    NZ_COLS,
    RIGHT,
    SC_COLS,
    SC_POL,
    SC_PROFILE,
    SC_T,
    SC_T_HW,
    SC_V,
    SC_V0,
)
from marlmerge.sim.proposal import (
    TILTED_DEPARTURES,
    Proposal,
    TiltedDraws,
    natural_profiles,
)

CHUNK = dr.CHUNK
"""Vehicles (or measurements) drawn per stream at a time."""
FILL_STREAM = 3
N_STREAMS = 4
NOISE_STREAM = 4
"""The sensor's stream, spawned only when its noise is on."""
SCENARIO_STREAM = 5
"""The stream of a world's drawn traffic (`[sample]`), spawned only when sampling is on."""
LAPSE_STREAM = 6
"""The stream of a world's attention-lapse keys, spawned only when drivers lapse."""
ROAD_SEED_KEY = 11
"""spawn_key of a road chosen by its seed (`Streams.seed_road`), apart from every world's."""
START_SPEED_HALF_WIDTH_MPS = 3.0
"""A world's ramp vehicles start within +- this of its drawn centre, m/s
(`sample.ego_start_speed_mps`)."""


WorldSeed = int | np.random.SeedSequence


def is_seed(value: object) -> bool:
    """A non-negative integer (Python or NumPy; not a bool, not a float such as 1.0)."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool) and value >= 0


def check_seed(seed: object, batch_size: int | None = None) -> None:
    """`seed` is None, a non-negative integer, or (with `batch_size`) a list of one such
    integer or `SeedSequence` per world; anything else is a `ValueError` naming the value."""
    if seed is None or is_seed(seed):
        return
    per_world = batch_size is not None and isinstance(seed, list | tuple | np.ndarray)
    if not per_world:
        raise ValueError(
            f"seed must be None or a non-negative integer, got {seed!r} ({type(seed).__name__})"
        )
    seeds = list(seed)  # type: ignore[call-overload]
    if len(seeds) != batch_size:
        raise ValueError(f"seed: need one seed per world ({batch_size}), got {len(seeds)}")
    bad = [s for s in seeds if not (is_seed(s) or isinstance(s, np.random.SeedSequence))]
    if bad:
        raise ValueError(
            "seed: per-world seeds must be non-negative integers or SeedSequences, got "
            f"{bad[0]!r} ({type(bad[0]).__name__})"
        )


def world_seed_sequences(
    batch_size: int, seed: int | Sequence[WorldSeed] | None, rows: np.ndarray
) -> list[np.random.SeedSequence]:
    """The seed sequence of each world in `rows` (see the module docstring)."""
    check_seed(seed, batch_size)
    if seed is None:
        return [np.random.SeedSequence() for _ in rows]
    if is_seed(seed):
        return [np.random.SeedSequence(int(seed), spawn_key=(int(i),)) for i in rows]
    seeds = list(seed)  # type: ignore[arg-type]
    return [
        seeds[i]
        if isinstance(seeds[i], np.random.SeedSequence)
        else np.random.SeedSequence(int(seeds[i]), spawn_key=(0,))
        for i in rows
    ]


@functools.lru_cache(maxsize=256)
def _mix_cdf(mix: tuple[float, float, float]) -> np.ndarray:
    """The normalised cumulative profile mix, as `Generator.choice` computes it (read only)."""
    p = np.asarray(mix, dtype=np.float64)
    cdf = (p / p.sum()).cumsum()
    cdf /= cdf[-1]
    cdf.flags.writeable = False
    return cdf


def draw_params(cfg: ScenarioConfig) -> np.ndarray:
    """[DP_COLS] a scenario's parameters of `arrivals`, `departures` and `ramp_arrivals`, as
    `marlmerge.sim.draws` reads them (the same numbers those methods compute)."""
    d, flow, ramp_flow = cfg.driver, cfg.traffic.flow_vph_per_lane, cfg.ramp.flow_vph
    mean, std = cfg.traffic.entry_speed_mps
    row = np.zeros(dr.DP_COLS)
    row[dr.DP_FLOW_ON] = 1.0 if flow > 0 else 0.0
    row[dr.DP_MEAN_GAP_S] = 3600.0 / flow if flow > 0 else 0.0
    row[[dr.DP_ENTRY_MEAN, dr.DP_ENTRY_STD]] = mean, std
    row[[dr.DP_ENTRY_LO, dr.DP_ENTRY_HI]] = mean - 2 * std, mean + 2 * std
    row[[dr.DP_V0_LO, dr.DP_V0_HI]] = d.desired_speed_factor
    row[dr.DP_V_LIMIT] = cfg.road.speed_limit_mps
    row[[dr.DP_HW_LO, dr.DP_HW_HI]] = d.time_headway_s
    row[[dr.DP_POL_LO, dr.DP_POL_HI]] = d.politeness
    row[dr.DP_CDF0 : dr.DP_CDF2 + 1] = _mix_cdf(d.mix)
    row[[dr.DP_START_LO, dr.DP_START_HI]] = cfg.ego.start_speed_mps
    row[dr.DP_RAMP_GAP_S] = 3600.0 / ramp_flow if ramp_flow > 0 else 0.0
    return row


class Streams:
    """The generators of B worlds and what they draw."""

    def __init__(self, cfg: ScenarioConfig, batch_size: int, proposal: Proposal | None = None):
        self.cfgs = [cfg] * batch_size
        """Each world's scenario: `cfg`, or the traffic it drew (`[sample]`)."""
        self.gens: list[list[np.random.Generator]] = [[] for _ in range(batch_size)]
        self.n_streams = N_STREAMS + 1 if cfg.sensing.noisy else N_STREAMS
        if cfg.sample.active:
            self.n_streams = SCENARIO_STREAM + 1
        if cfg.driver.lapse_rate_per_h > 0.0:
            self.n_streams = LAPSE_STREAM + 1
        if proposal is not None:
            proposal.check(cfg)
        self.tilted = None if proposal is None else TiltedDraws(proposal, batch_size)
        """With a proposal: its draws, log-likelihood ratios and statistics per world."""
        self._states = np.zeros((batch_size, EGO_STREAM + 1), dtype=np.uint64)
        self._states_of: list[Any] = [None] * batch_size
        self._params = np.zeros((batch_size, dr.DP_COLS))
        self._params_of: list[Any] = [None] * batch_size

    def seed(self, rows: np.ndarray, sequences: list[np.random.SeedSequence]) -> None:
        for b, seq in zip(rows, sequences, strict=True):
            # spawn from a copy: spawning advances a SeedSequence, and equal seeds must give equal
            # worlds every time
            fresh = np.random.SeedSequence(seq.entropy, spawn_key=seq.spawn_key)
            self.gens[b] = [np.random.default_rng(c) for c in fresh.spawn(self.n_streams)]

    def seed_road(self, b: int, road_seed: int) -> None:
        """World `b`'s generators start again from `road_seed`, all but its scenario stream,
        which goes on: the road a scenario source chose by its seed (`ScenarioSource.road`),
        the same fill, arrivals and departures every time it is chosen."""
        seq = np.random.SeedSequence(road_seed, spawn_key=(ROAD_SEED_KEY,))
        gens = [np.random.default_rng(c) for c in seq.spawn(self.n_streams)]
        gens[SCENARIO_STREAM] = self.gens[b][SCENARIO_STREAM]
        self.gens[b] = gens

    def __getstate__(self) -> dict[str, Any]:
        """A copy (pickle, deepcopy) has generators of its own: their state addresses are
        taken again on its first draws, never carried over from this object's."""
        state = self.__dict__.copy()
        state["_states_of"] = [None] * len(self._states_of)
        return state

    def compiled_inputs(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """What `marlmerge.sim.draws.draw_ahead` reads: the state addresses of the lanes' and
        the ego stream's generators [B, 3] and each world's draw parameters [B, DP_COLS],
        brought up to date for the worlds `rows` (a world's generators are replaced when it is
        seeded, its scenario when it draws one)."""
        for b in rows.tolist():
            gens, cfg = self.gens[b], self.cfgs[b]
            if self._states_of[b] is not gens:
                self._states[b] = [dr.state_address(g) for g in gens[: EGO_STREAM + 1]]
                self._states_of[b] = gens
            if self._params_of[b] is not cfg:
                self._params[b] = draw_params(cfg)
                self._params_of[b] = cfg
        return self._states, self._params

    # ------------------------------------------------------------------ drawn vehicles
    def _drivers(
        self, cfg: ScenarioConfig, g: np.random.Generator, n: int
    ) -> tuple[np.ndarray, ...]:
        d = cfg.driver
        v0 = g.uniform(*d.desired_speed_factor, size=n) * cfg.road.speed_limit_mps
        headway = g.uniform(*d.time_headway_s, size=n)
        politeness = g.uniform(*d.politeness, size=n)
        return v0, headway, politeness

    def _entry_speed(self, cfg: ScenarioConfig, g: np.random.Generator, n: int) -> np.ndarray:
        mean, std = cfg.traffic.entry_speed_mps
        v = g.normal(mean, std, size=n)  # clipped to mean +- 2 std (np.clip's wrapper is slow)
        return np.minimum(np.maximum(v, mean - 2 * std, out=v), mean + 2 * std, out=v)

    def _profiles(self, cfg: ScenarioConfig, g: np.random.Generator, n: int) -> np.ndarray:
        """`g.choice(3, size=n, p=mix / mix.sum())` drawn as `Generator.choice` draws it (n
        uniforms searched in the normalised cumulative mix) without its per-call checks, a
        third of an arrival chunk's cost: the same values and the same stream after
        (`tests/test_sampling.py`)."""
        return _mix_cdf(cfg.driver.mix).searchsorted(g.random(n), side="right").astype(np.float64)

    def arrivals(self, b: int, lane: int, t_last_s: float) -> np.ndarray:
        """The next `CHUNK` arrivals of `lane` after `t_last_s`, [CHUNK, SC_COLS]. The entry speed
        is drawn from `traffic.entry_speed_mps` and capped at the driver's desired speed."""
        if self.tilted is not None:
            return self._tilted_arrivals(b, lane, t_last_s)
        g, cfg = self.gens[b][lane], self.cfgs[b]
        flow = cfg.traffic.flow_vph_per_lane
        out = np.empty((CHUNK, SC_COLS))
        if flow > 0:
            out[:, SC_T] = t_last_s + np.cumsum(g.exponential(3600.0 / flow, size=CHUNK))
        else:
            out[:, SC_T] = np.inf
        out[:, SC_V] = self._entry_speed(cfg, g, CHUNK)
        out[:, SC_V0], out[:, SC_T_HW], out[:, SC_POL] = self._drivers(cfg, g, CHUNK)
        out[:, SC_PROFILE] = self._profiles(cfg, g, CHUNK)
        out[:, SC_V] = np.minimum(out[:, SC_V], out[:, SC_V0])  # nobody enters above its v0
        return out

    def _tilted_arrivals(self, b: int, lane: int, t_last_s: float) -> np.ndarray:
        """`arrivals` under the proposal (`marlmerge.sim.proposal`): the same columns, the
        vehicles entering inside its window drawn from it, their weights kept."""
        g, cfg, tw = self.gens[b][lane], self.cfgs[b], self.tilted
        assert tw is not None
        flow, d = cfg.traffic.flow_vph_per_lane, cfg.driver
        out = np.empty((CHUNK, SC_COLS))
        if flow > 0:
            out[:, SC_T] = tw.gaps(b, lane, g, 3600.0 / flow, t_last_s, CHUNK)
        else:
            out[:, SC_T] = np.inf
        tilt = tw.in_window(out[:, SC_T])
        out[:, SC_V] = self._entry_speed(cfg, g, CHUNK)
        speed_factor = tw.band(b, 0, g, d.desired_speed_factor, tilt)
        out[:, SC_V0] = speed_factor * cfg.road.speed_limit_mps
        out[:, SC_T_HW] = tw.band(b, 1, g, d.time_headway_s, tilt)
        out[:, SC_POL] = tw.band(b, 2, g, d.politeness, tilt)
        natural = np.asarray(natural_profiles(cfg))
        out[:, SC_PROFILE] = tw.profiles(b, lane, g, natural, tilt)
        out[:, SC_V] = np.minimum(out[:, SC_V], out[:, SC_V0])
        return out

    def departures(self, b: int) -> np.ndarray:
        """The next `CHUNK` egos: start speed and the driver they become once merged."""
        g, cfg = self.gens[b][EGO_STREAM], self.cfgs[b]
        out = np.zeros((CHUNK, SC_COLS))
        if self.tilted is not None:  # the first egos after a reset start at a tilted speed
            first = np.zeros(CHUNK, dtype=bool)
            first[:TILTED_DEPARTURES] = self.tilted.first_ego[b]
            self.tilted.first_ego[b] = False
            out[:, SC_V] = self.tilted.band(b, 3, g, cfg.ego.start_speed_mps, first)
        else:
            out[:, SC_V] = g.uniform(*cfg.ego.start_speed_mps, size=CHUNK)
        out[:, SC_V0], out[:, SC_T_HW], out[:, SC_POL] = self._drivers(cfg, g, CHUNK)
        out[:, SC_PROFILE] = NEUTRAL
        return out

    def ramp_arrivals(self, b: int, t_last_s: float) -> np.ndarray:
        """Ramp flow (`ramp.flow_vph > 0`): the next `CHUNK` ramp vehicles after `t_last_s`,
        [CHUNK, SC_COLS], from the ego departures' generator (ramp flow sends no ego): Poisson
        arrival times, a start speed from `ego.start_speed_mps` (at most the driver's desired
        speed) and the driver they are, neutral once merged."""
        g, cfg = self.gens[b][EGO_STREAM], self.cfgs[b]
        out = np.zeros((CHUNK, SC_COLS))
        out[:, SC_T] = t_last_s + np.cumsum(g.exponential(3600.0 / cfg.ramp.flow_vph, size=CHUNK))
        out[:, SC_V] = g.uniform(*cfg.ego.start_speed_mps, size=CHUNK)
        out[:, SC_V0], out[:, SC_T_HW], out[:, SC_POL] = self._drivers(cfg, g, CHUNK)
        out[:, SC_PROFILE] = NEUTRAL
        out[:, SC_V] = np.minimum(out[:, SC_V], out[:, SC_V0])
        return out

    def lapse_key(self, b: int) -> int:
        """The key of world `b`'s attention-lapse draws for its next road
        (`marlmerge.sim.lapses.lapse_uniform`)."""
        return int(self.gens[b][LAPSE_STREAM].integers(0, 2**31))

    def noise(self, b: int) -> np.ndarray:
        """Standard-normal errors of the next `CHUNK` measurements of world `b`'s ego sensor,
        [CHUNK, NZ_COLS] (columns `NZ_*`; the core scales them by the configured stds)."""
        return self.gens[b][NOISE_STREAM].standard_normal((CHUNK, NZ_COLS))

    def fill(self, b: int) -> dict[str, np.ndarray]:
        """Mainline vehicles for a fresh road in steady flow: each lane filled from the exit
        upstream with spacing speed x an exponential headway, at least a safe following distance
        (jam gap + the longest desired headway), each at a speed `entry_speed` allows behind its
        leader. Arrays of the kept vehicles, downstream first
        per lane: x_m, v_mps, lane, v0_mps, headway_s, politeness, profile."""
        cfg = self.cfgs[b]
        g = self.gens[b][FILL_STREAM]
        flow = cfg.traffic.flow_vph_per_lane
        length, s0 = cfg.vehicle.length_m, cfg.driver.min_gap_m
        road_len = cfg.road.x_exit_m - cfg.road.x_entrance_m
        per_lane = int(np.ceil(road_len / (length + s0))) + 1
        cols: dict[str, list[np.ndarray]] = {k: [] for k in _FILL_KEYS}
        for lane in (RIGHT, LEFT):
            h = g.exponential(3600.0 / flow, size=per_lane) if flow > 0 else np.zeros(per_lane)
            v = self._entry_speed(cfg, g, per_lane)
            v0, headway, politeness = self._drivers(cfg, g, per_lane)
            v = np.minimum(v, v0)
            profile = self._profiles(cfg, g, per_lane)
            first = g.uniform()
            if flow <= 0:
                continue
            space = np.maximum(v * h, length + s0 + v * cfg.driver.time_headway_s[1])
            dist = np.cumsum(space) - space[0] + first * space[0]  # front bumpers from the exit
            kept: list[int] = []
            speeds: list[float] = []
            for i in np.flatnonzero(dist < road_len):
                v_i = v[i]
                if kept:  # enter at a speed the vehicle's IDM can hold behind its leader
                    j = kept[-1]
                    gap = dist[i] - dist[j] - length
                    v_i = entry_speed(v[i], gap, speeds[-1], headway[i], *_idm(cfg))
                if v_i >= 0.0:
                    kept.append(int(i))
                    speeds.append(float(v_i))
            idx = np.array(kept, dtype=np.int64)
            cols["x_m"].append(cfg.road.x_exit_m - dist[idx])
            cols["v_mps"].append(np.array(speeds))
            cols["lane"].append(np.full(idx.size, lane, dtype=np.float64))
            cols["v0_mps"].append(v0[idx])
            cols["headway_s"].append(headway[idx])
            cols["politeness"].append(politeness[idx])
            cols["profile"].append(profile[idx])
        return {k: np.concatenate(v) if v else np.zeros(0) for k, v in cols.items()}


WORLD_KEYS = frozenset(
    {
        "name",
        "traffic.flow_vph_per_lane",
        "traffic.entry_speed_mps",
        "road.speed_limit_mph",
        "road.ramp_length_m",
        "road.merge_zone_m",
        "driver.mix_neutral",
        "driver.mix_cooperative",
        "driver.mix_adversarial",
        "driver.desired_speed_factor",
        "driver.time_headway_s",
        "driver.politeness",
        "driver.yield_max_brake_mps2",
        "driver.adversarial_time_headway_s",
        "driver.adversarial_speed_factor",
        "driver.adversarial_accel_mps2",
        "ego.start_speed_mps",
        "ego.sensing_range_m",
    }
)
"""The keys in which one world's scenario may differ from its batch's: what `[sample]` draws."""


def _leaves(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in data.items():
        out.update(_leaves(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k: v})
    return out


def check_world_scenarios(
    cfg: ScenarioConfig, batch_size: int, scenarios: Sequence[ScenarioConfig] | None
) -> None:
    """`scenarios` (one per world, or None) may differ from `cfg` only in `WORLD_KEYS`, and a
    batch that draws its traffic (`[sample]`) takes none; a `ValueError` names the world and key."""
    if scenarios is None:
        return
    if cfg.sample.active:
        raise ValueError("scenarios: a batch that draws its traffic ([sample]) takes no scenarios")
    if len(scenarios) != batch_size:
        raise ValueError(f"scenarios: one per world ({batch_size}), got {len(scenarios)}")
    base = _leaves(to_dict(cfg))
    checked: set[int] = set()
    for b, world in enumerate(scenarios):
        if id(world) in checked:  # a scenario given to many worlds is checked once
            continue
        checked.add(id(world))
        if not isinstance(world, ScenarioConfig):
            raise ValueError(f"scenarios[{b}] must be a ScenarioConfig, got {type(world).__name__}")
        own = _leaves(to_dict(world))
        for key in sorted(k for k in own if own[k] != base[k] and k not in WORLD_KEYS):
            raise ValueError(
                f"scenarios[{b}]: {key} = {own[key]!r} differs from the batch's ({base[key]!r}); "
                "a world may differ only in what [sample] draws (marlmerge.sim.streams.WORLD_KEYS)"
            )


DRAWN_BEFORE_MIX = (
    "flow_vph_per_lane",
    "speed_limit_mph",
    "entry_speed_fraction",
    "adversarial_share",
    "cooperative_share",
    "adversarial_time_headway_s",
    "adversarial_speed_factor",
    "ego_start_speed_mps",
)
DRAWN_AFTER_MIX = (
    "sensing_range_m",
    "desired_speed_factor",
    "time_headway_s",
    "politeness",
    "yield_max_brake_mps2",
    "adversarial_accel_mps2",
    "ramp_length_m",
    "merge_zone_m",
)
"""The `[sample]` keys in the order a world draws them (the one-profile draw in between)."""
PURE_MIXES = ("mix_neutral", "mix_cooperative", "mix_adversarial")


WorldDraw = tuple[dict[str, float | None], str | None]
"""What a world draws from `[sample]`: each key's value (None: not sampled) and the pure
driver mix (None: the drawn or configured mix)."""


def draw_world_values(base: ScenarioConfig, g: np.random.Generator) -> WorldDraw:
    """A world's draw from `base.sample` (see `marlmerge.config.SampleConfig`): every range
    drawn in a fixed order, so a world's draws depend on its seed alone."""
    smp = base.sample

    def draw(key: str) -> float | None:
        rng = getattr(smp, key)
        return None if rng is None else float(g.uniform(*rng))

    values = {key: draw(key) for key in DRAWN_BEFORE_MIX}
    pure = None
    if smp.pure_mix_fraction > 0.0 and g.uniform() < smp.pure_mix_fraction:
        pure = PURE_MIXES[int(g.integers(3))]
    values |= {key: draw(key) for key in DRAWN_AFTER_MIX}
    return values, pure


class ScenarioSource(Protocol):
    """Chooses the traffic of a world's next road in place of its own `[sample]` draw (e.g. a
    training run replaying the conditions where its ego failed). It must draw only from `g`
    (the world's scenario stream), so runs stay reproducible."""

    def draw(
        self, base: ScenarioConfig, world: int, g: np.random.Generator
    ) -> tuple[ScenarioConfig, int]:
        """The scenario world `world` runs next (differing from `base` only in `WORLD_KEYS`)
        and a tag for it (>= 0; the core reports it, `TrafficCore.world_tag`)."""
        ...

    def road(self, world: int, tag: int) -> int | None:
        """The seed of the road the level `tag`, just drawn for `world`, runs on (its fill,
        arrivals and departures: `Streams.seed_road`), or None: the world's own generators go
        on."""
        ...


def draw_world_scenario(base: ScenarioConfig, g: np.random.Generator) -> ScenarioConfig:
    """A world's traffic drawn from `base.sample` (`draw_world_values`)."""
    return base.replace(**world_changes(base, *draw_world_values(base, g)))


def world_changes(
    base: ScenarioConfig, values: dict[str, float | None], pure: str | None = None
) -> dict[str, object]:
    """The dotted-key changes to `base` of the `[sample]` keys' `values` (None or left out: kept)
    and, with `pure`, drivers all of that profile."""
    v, d = values.get, base.driver
    limit, frac = v("speed_limit_mph"), v("entry_speed_fraction")
    changes: dict[str, object] = {
        "traffic.flow_vph_per_lane": v("flow_vph_per_lane"),
        "road.speed_limit_mph": limit,
        "driver.adversarial_time_headway_s": v("adversarial_time_headway_s"),
        "driver.adversarial_speed_factor": v("adversarial_speed_factor"),
    }
    if frac is not None:
        limit_mps = (base.road.speed_limit_mph if limit is None else limit) * MPH_TO_MPS
        changes["traffic.entry_speed_mps"] = [frac * limit_mps, base.traffic.entry_speed_mps[1]]
    adv, coop_share = v("adversarial_share"), v("cooperative_share")
    if adv is not None or coop_share is not None:
        adv = d.mix_adversarial / sum(d.mix) if adv is None else adv
        if coop_share is None:
            coop_share = d.mix_cooperative / max(d.mix_cooperative + d.mix_neutral, 1e-12)
        changes["driver.mix_adversarial"] = adv
        changes["driver.mix_cooperative"] = (1.0 - adv) * coop_share
        changes["driver.mix_neutral"] = (1.0 - adv) * (1.0 - coop_share)
    start = v("ego_start_speed_mps")
    if start is not None:
        half = START_SPEED_HALF_WIDTH_MPS
        changes["ego.start_speed_mps"] = [max(start - half, 0.0), start + half]
    if pure is not None:
        for key in PURE_MIXES:
            changes[f"driver.{key}"] = 1.0 if key == pure else 0.0
    changes["ego.sensing_range_m"] = v("sensing_range_m")
    for key in ("desired_speed_factor", "time_headway_s", "politeness"):
        changes[f"driver.{key}"] = _centred(getattr(d, key), v(key))
    for key in ("yield_max_brake_mps2", "adversarial_accel_mps2"):
        changes[f"driver.{key}"] = v(key)
    for key in ("ramp_length_m", "merge_zone_m"):
        changes[f"road.{key}"] = v(key)
    return {k: c for k, c in changes.items() if c is not None}


def _centred(band: tuple[float, float], centre: float | None) -> list[float] | None:
    """`band` moved to centre on `centre` (its width kept, its low end at least 0); None: kept."""
    if centre is None:
        return None
    half = (band[1] - band[0]) / 2
    return [max(centre - half, 0.0), centre + half]


_FILL_KEYS = ("x_m", "v_mps", "lane", "v0_mps", "headway_s", "politeness", "profile")


def _idm(cfg: ScenarioConfig) -> tuple[float, float, float]:
    d = cfg.driver
    return d.accel_mps2, d.comfort_brake_mps2, d.min_gap_m
