"""The batched ramp-merge traffic simulator: B worlds in packed arrays, stepped by compiled kernels.

`TrafficCore` owns its state: the packed arrays of `marlmerge.sim.layout`, the lane lists, the
drawn arrivals and the per-world generators (`marlmerge.sim.streams`). It imports no RL library.
Every view (PettingZoo, torchrl, Gymnasium) calls `rollout` (or `step`, one simulator step) and
only reshapes its outputs; checkpoints go through `state_dict` / `load_state_dict`.

Slot capacity follows the traffic: it starts from the expected number of vehicles on the road
and grows (doubling) before a call could run out, so no arrival is ever dropped; the kernels
only visit vehicles on the road, so unused slots cost nothing per step.
"""

from __future__ import annotations

import math
import sys
import threading
from collections.abc import Sequence
from typing import Any

import numba
import numpy as np

from marlmerge.config import ScenarioConfig, check_count, from_dict, latency_steps, to_dict
from marlmerge.sim import draws, kernels
from marlmerge.sim import layout as L
from marlmerge.sim.layout import EGO, EGO_STREAM, OUTCOME_NONE, RAMP
from marlmerge.sim.observation import (
    HIGHWAY_FEATURES,
    ego_features,
    ramp_agent_features,
)
from marlmerge.sim.proposal import Proposal
from marlmerge.sim.reward import EGO_TERMS, LEARNED_HIGHWAY_TERMS
from marlmerge.sim.state import EgoGaps, Rollout, Roster, StepEvents, TrafficState
from marlmerge.sim.streams import (
    CHUNK,
    SCENARIO_STREAM,
    ScenarioSource,
    Streams,
    check_world_scenarios,
    draw_world_scenario,
    world_seed_sequences,
)

PARALLEL_MIN_WORLDS = 64
"""From this many worlds on, `rollout` runs worlds in parallel threads (same results)."""
WARMUP_CHUNK_STEPS = 10
"""Warm-up runs in calls of this many steps (each call reserves slots for its arrivals)."""
STATE_DICT_VERSION = 5
"""2: the sensor's arrays and the `wi` rows of sensing and the safety filter; 3: ramp flow; 4:
attention lapses; 5: four lapse classes. Older states still load."""
_ARRAYS = ("vf", "vi", "wf", "wi", "lanes", "sched", "ring", "noise")
_ARRAYS_V1 = _ARRAYS[:6]
_NO_AGENTS = np.zeros((1 << 16, 0), dtype=bool)
_NO_AGENTS.flags.writeable = False
_BITGEN_FUNCTIONS = draws.bitgen_functions()
"""The C functions of NumPy's PCG64 that the compiled draws call (`marlmerge.sim.draws`)."""

_announced: set[str] = set()
_said = threading.Event()


def _announce_compilation(what: str) -> threading.Timer | None:
    """Say so when a first call takes long: the kernels are being compiled (then cached on
    disk, so later processes load them). Said once per process."""
    if what in _announced or _said.is_set():
        return None
    _announced.add(what)

    def say() -> None:
        if not _said.is_set():
            _said.set()
            print(
                "marlmerge: compiling the simulator kernels (first run only; cached on disk)...",
                file=sys.stderr,
                flush=True,
            )

    timer = threading.Timer(1.0, say)
    timer.daemon = True
    timer.start()
    return timer


def draw_groups(
    batch_size: int, world_groups: Sequence[int] | np.ndarray | None
) -> np.ndarray | None:
    """[B] each world's group numbered 0 .. G - 1 (in order of first appearance), or None for
    one group. A group is the unit the core draws ahead for: a world's random numbers are drawn
    in chunks, ahead of need (`marlmerge.sim.streams`), and a reset discards what its world
    drew for the old road, so each reset (and each call of another step count) draws ahead in
    every world of its group and in no other. The worlds of a group then run bit for bit as a
    core of those worlds alone (`marlmerge train --seeds`: one group per seed)."""
    if world_groups is None:
        return None
    g = np.asarray(world_groups)
    if g.shape != (batch_size,) or not np.issubdtype(g.dtype, np.integer) or np.any(g < 0):
        raise ValueError(
            f"world_groups: one non-negative integer per world ({batch_size}), got {world_groups!r}"
        )
    _, first, dense = np.unique(g, return_index=True, return_inverse=True)
    if first.size == 1:
        return None
    order = np.argsort(np.argsort(first))  # number the groups in order of first appearance
    return order[dense].astype(np.int64)


def initial_slots(cfg: ScenarioConfig) -> int:
    """Slots per world to start with: the ego plus twice the vehicles expected on both lanes at
    the configured flow and a slow speed, and room for a few calls' arrivals."""
    road_len = cfg.road.x_exit_m - cfg.road.x_entrance_m
    mean_v, std_v = cfg.traffic.entry_speed_mps
    slow = max(mean_v - 2 * std_v, 5.0)
    expected = 2 * road_len * cfg.traffic.flow_vph_per_lane / 3600.0 / slow
    return 1 + 2 * math.ceil(expected) + 16


class TrafficCore:
    """B worlds of the ramp-merge scenario, stepped together.

    Typical use:

        core = TrafficCore(cfg, batch_size=64, seed=0)
        while True:
            out = core.rollout(ego_accel)        # ego_accel: [B] m/s^2 (NaN: the ego drives by
                                                 # IDM), held for sim.action_repeat steps
            done = out.ego_outcome != OUTCOME_NONE
            core.next_ego(done)                  # the next ramp vehicle departs in finished worlds
    """

    compiled_draws = True
    """Draw arrivals and departures ahead in compiled code (`marlmerge.sim.draws`); False: through
    the streams' NumPy calls, the same numbers (the reference `tests/test_draws.py` compares)."""

    def __init__(
        self,
        cfg: ScenarioConfig,
        batch_size: int = 1,
        seed: int | Sequence[int] | None = None,
        parallel: bool | None = None,
        scenarios: Sequence[ScenarioConfig] | None = None,
        scenario_source: ScenarioSource | None = None,
        proposal: Proposal | None = None,
        world_groups: Sequence[int] | np.ndarray | None = None,
    ):
        """scenarios: one per world, the traffic and road world b runs (each may differ from
        `cfg` only in what `[sample]` draws, `WORLD_KEYS`); None: every world runs `cfg`.
        scenario_source: with `[sample]`, chooses each new road's traffic in place of the
        world's own draw (`ScenarioSource`); `world_tag` [B] holds the tag of its choice.
        proposal: draw the traffic the first ego of each reset meets from this proposal
        (`marlmerge.sim.proposal`); `streams.tilted.log_w` [B] holds each world's exact
        log-likelihood ratio. None (default): the scenario's own draws, bit for bit.
        world_groups: [B] a group number per world (`draw_groups`): the worlds of each group run
        exactly as a core of that group's worlds alone would (S seeds in one core); None: one
        group."""
        batch_size = check_count("batch_size", batch_size)
        check_world_scenarios(cfg, batch_size, scenarios)
        self.cfg = cfg
        self.fixed_scenarios = scenarios is not None
        """Every world runs a scenario it was given (`scenarios`)."""
        if proposal is not None and not isinstance(proposal, Proposal):
            raise ValueError(
                f"proposal must be None or a marlmerge.sim.proposal.Proposal, got {proposal!r}"
            )
        if proposal is not None and cfg.ramp.flowing:
            raise ValueError(
                f"proposal: ramp.flow_vph = {cfg.ramp.flow_vph} runs ramp flow, which has no ego "
                "to estimate rates for"
            )
        if scenario_source is not None and not cfg.sample.active:
            raise ValueError("scenario_source needs a scenario with [sample] ranges to replace")
        self.scenario_source = scenario_source
        self.world_tag = np.full(batch_size, -1, dtype=np.int64)
        """[B] the tag `scenario_source` gave each world's current traffic (-1: none)."""
        self.batch_size = batch_size
        self.proposal = proposal
        self.params = np.tile(self._pack(cfg), (batch_size, 1))  # [B, P]: each world's parameters
        self.v_limit = cfg.road.speed_limit_mps
        self.ego_features = ego_features(cfg)
        """The ego's observation layout (`ego.observation`)."""
        self.obs_size = len(self.ego_features)
        self.agent_features = ramp_agent_features(cfg)
        """What a ramp-flow agent sees (`ramp_agents`)."""
        self._ring_len = latency_steps(cfg) + 1 if cfg.sensing.active else 0
        self.parallel = batch_size >= PARALLEL_MIN_WORLDS if parallel is None else bool(parallel)
        self.streams = Streams(cfg, batch_size, proposal)
        for b, world in enumerate(scenarios or ()):
            self._set_world_scenario(b, world)
        self._allocate(initial_slots(cfg), 2 * CHUNK)
        self._no_roster = Roster(np.zeros((L.RO_ROWS, batch_size, 0), dtype=np.int64))
        self._no_cmd = np.zeros((batch_size, 0, 2))
        self._all_worlds = np.ones(batch_size, dtype=bool)
        if self.parallel:  # a few chunks of worlds per thread
            self._kernel = kernels.rollout_parallel
            self._worlds: tuple[int, ...] = (min(batch_size, 8 * numba.get_num_threads()),)
        else:
            self._kernel, self._worlds = kernels.rollout, (0, batch_size)
        self._called = False
        self._group_of = draw_groups(batch_size, world_groups)
        """[B] each world's group (0 .. G - 1), or None: one group."""
        self._all_rows = np.arange(batch_size)
        n_groups = 0 if self._group_of is None else int(self._group_of.max()) + 1
        self._group_slots = np.full(n_groups, self.n_slots, dtype=np.int64)
        """[G] the slots each draw group would have alone (`_reserve_slots`)."""
        self._no_noise_need = np.zeros(batch_size, dtype=np.int64)
        self._served_k = np.full(batch_size, -1, dtype=np.int64)
        """[B] the step count each world was last drawn ahead for (equal within a group)."""
        self._resampling = cfg.sample.active  # (config properties cost a call each time)
        self._noisy = cfg.sensing.noisy
        self.state = TrafficState(self)
        timer = _announce_compilation("core")
        self.reset(seed=seed)
        if timer is not None:
            timer.cancel()

    # ------------------------------------------------------------------ storage
    def _allocate(self, n_slots: int, q_len: int) -> None:
        b = self.batch_size
        self.vf = np.zeros((b, L.VF_ROWS, n_slots))
        self.vi = np.zeros((b, L.VI_ROWS, n_slots), dtype=np.int64)
        self.vi[:, L.VI_LANE] = RAMP
        self.vi[:, L.VI_ID] = -1
        self.wf = np.zeros((b, L.WF_ROWS))
        self.wi = np.zeros((b, L.WI_ROWS), dtype=np.int64)
        self.lanes = np.full((b, 3, n_slots), -1, dtype=np.int64)
        self.sched = np.zeros((b, 3, q_len, L.SC_COLS))
        self._allocate_sensor()

    def _allocate_sensor(self) -> None:
        """The sensor's ring and drawn errors (empty when sensing is perfect / noise-free)."""
        b = self.batch_size
        self.ring = np.zeros((b * self._ring_len, self.obs_size))
        noise_len = 2 * CHUNK if self.cfg.sensing.noisy else 0
        self.noise = np.zeros((b, noise_len, L.NZ_COLS))

    @property
    def arrays(self) -> tuple[np.ndarray, ...]:
        """(vf, vi, wf, wi, lanes, sched): the state the kernels take as one argument."""
        return (self.vf, self.vi, self.wf, self.wi, self.lanes, self.sched)

    @property
    def sensor(self) -> tuple[np.ndarray, np.ndarray]:
        """(ring, noise): the ego sensor's state the kernels take as one argument."""
        return (self.ring, self.noise)

    @property
    def n_slots(self) -> int:
        """Vehicle slots per world (grows with the traffic)."""
        return self.vf.shape[2]

    def _grow_slots(self, n_slots: int) -> None:
        pad = n_slots - self.n_slots
        self.vf = np.concatenate([self.vf, np.zeros(self.vf.shape[:2] + (pad,))], axis=2)
        new_vi = np.zeros(self.vi.shape[:2] + (pad,), dtype=np.int64)
        new_vi[:, L.VI_LANE], new_vi[:, L.VI_ID] = RAMP, -1
        self.vi = np.concatenate([self.vi, new_vi], axis=2)
        self.lanes = np.concatenate(
            [self.lanes, np.full(self.lanes.shape[:2] + (pad,), -1, dtype=np.int64)], axis=2
        )

    def _reserve_slots(self, rows: np.ndarray, need: np.ndarray) -> None:
        """At least `need` [len(rows)] slots for the worlds `rows`, doubling the slots when
        short. With draw groups each group counts its own slots, as a core of its worlds alone
        would, and the arrays hold the most any group has (`draw_groups`)."""
        if self._group_of is None:
            top = int(need.max())
            if top > self.n_slots:
                self._grow_slots(max(top, 2 * self.n_slots))
            return
        groups = self._group_of[rows]
        for g in np.unique(groups).tolist():
            top = int(need[groups == g].max())
            if top > self._group_slots[g]:
                self._group_slots[g] = max(top, 2 * int(self._group_slots[g]))
        if int(self._group_slots.max()) > self.n_slots:
            self._grow_slots(int(self._group_slots.max()))

    def _grow_rings(self, q_len: int) -> None:
        """Longer arrival rings, each unrolled so that its head is at index 0."""
        old_q = self.sched.shape[2]
        new = np.zeros(self.sched.shape[:2] + (q_len, L.SC_COLS))
        for stream in range(3):
            heads = self.wi[:, L.WI_HEAD_RIGHT + stream]
            idx = (heads[:, None] + np.arange(old_q)[None, :]) % old_q  # [B, old_q]
            new[:, stream, :old_q] = np.take_along_axis(
                self.sched[:, stream], idx[:, :, None], axis=1
            )
            self.wi[:, L.WI_HEAD_RIGHT + stream] = 0
        self.sched = new

    # ------------------------------------------------------------------ drawn arrivals
    def _push(self, b: int, stream: int, rows: np.ndarray) -> None:
        q_len, n = self.sched.shape[2], rows.shape[0]
        count = int(self.wi[b, L.WI_COUNT_RIGHT + stream])
        start = (int(self.wi[b, L.WI_HEAD_RIGHT + stream]) + count) % q_len
        if start + n <= q_len:  # one slice (most pushes), else around the ring's end
            self.sched[b, stream, start : start + n] = rows
        else:
            self.sched[b, stream, (start + np.arange(n)) % q_len] = rows
        self.wi[b, L.WI_COUNT_RIGHT + stream] = count + n

    def _last_time(self, b: int, stream: int) -> float:
        """Drawn time of the last arrival of `stream` in world `b` (-inf when none is left)."""
        count = self.wi[b, L.WI_COUNT_RIGHT + stream]
        if count == 0:
            return -np.inf
        last = (self.wi[b, L.WI_HEAD_RIGHT + stream] + count - 1) % self.sched.shape[2]
        return float(self.sched[b, stream, last, L.SC_T])

    def _serve(self, k: int, rows: np.ndarray | None = None) -> None:
        """Make room and draw ahead so that a call of `k` steps, after at most one `next_ego`,
        never runs short, in the worlds `rows` (indices; all if None)."""
        rows = np.arange(self.batch_size) if rows is None else rows
        if rows.size:
            self._reserve_slots(rows, self._slots_needed(rows, k))
        if self.streams.tilted is None and self.compiled_draws:
            self._draw_ahead(k, rows)
        else:
            self._draw_ahead_numpy(k, rows)
        if self._noisy:
            for b in rows.tolist():
                self._top_up_noise(b, k + 2)
        self._served_k[self._group_rows(rows)] = k

    def _draw_ahead(self, k: int, rows: np.ndarray) -> None:
        """`_serve`'s draws of arrivals and departures in one compiled call
        (`marlmerge.sim.draws`), growing the rings when one is full."""
        states, params = self.streams.compiled_inputs(rows)
        flowing, start = bool(self.cfg.ramp.flowing), 0
        while True:
            start = draws.draw_ahead(
                self.wf, self.wi, self.sched, rows, start, k, self.cfg.sim.dt_s, flowing,
                states, _BITGEN_FUNCTIONS, params,
            )  # fmt: skip
            if start < 0:
                return
            self._grow_rings(2 * self.sched.shape[2])

    def _draw_ahead_numpy(self, k: int, rows: np.ndarray) -> None:
        """`_draw_ahead` through the streams' NumPy calls: under a proposal (its tilted draws),
        and the reference the compiled draws are tested against (`compiled_draws = False`)."""
        dt = self.cfg.sim.dt_s
        for b in rows.tolist():
            horizon = self.wf[b, L.WF_T] + (k + 1) * dt
            for stream in range(2):
                while (
                    self.wi[b, L.WI_COUNT_RIGHT + stream] < 2
                    or self._last_time(b, stream) <= horizon
                ):
                    self._reserve_ring(b, stream)
                    t_last = max(self._last_time(b, stream), 0.0)
                    self._push(b, stream, self.streams.arrivals(b, stream, t_last))
            if self.cfg.ramp.flowing:  # the ramp's arrivals, drawn ahead as the lanes' are
                while (
                    self.wi[b, L.WI_COUNT_RIGHT + EGO_STREAM] < 2
                    or self._last_time(b, EGO_STREAM) <= horizon
                ):
                    self._reserve_ring(b, EGO_STREAM)
                    t_last = max(self._last_time(b, EGO_STREAM), 0.0)
                    self._push(b, EGO_STREAM, self.streams.ramp_arrivals(b, t_last))
            while self.wi[b, L.WI_COUNT_RIGHT + EGO_STREAM] < 2:
                self._reserve_ring(b, EGO_STREAM)
                self._push(b, EGO_STREAM, self.streams.departures(b))
            self.wi[b, L.WI_NEED] = 0

    def _slots_needed(self, rows: np.ndarray | slice, k: int) -> np.ndarray:
        """Slots the worlds `rows` need before a call of `k` steps: their vehicles, the most
        arrivals k steps bring (two a step, three with ramp flow) and one `next_ego` (the
        kernels' `_short` asks the same)."""
        per_step = 3 if self.cfg.ramp.flowing else 2
        return self.wi[rows, L.WI_N_ACTIVE] + per_step * k + 3

    def _group_rows(self, rows: np.ndarray) -> np.ndarray:
        """The worlds of every group that holds one of `rows` (all worlds with one group)."""
        if self._group_of is None:
            return self._all_rows
        return np.flatnonzero(np.isin(self._group_of, self._group_of[rows]))

    def _top_up_noise(self, b: int, need: int) -> None:
        """At least `need` drawn measurement errors in world `b`'s noise ring (noise on)."""
        if not self.cfg.sensing.noisy:
            return
        q_len = self.noise.shape[1]
        while self.wi[b, L.WI_NOISE_COUNT] < need:
            count = int(self.wi[b, L.WI_NOISE_COUNT])
            if count + CHUNK > q_len:
                self._grow_noise(2 * q_len)
                q_len = self.noise.shape[1]
            head = int(self.wi[b, L.WI_NOISE_HEAD])
            idx = (head + count + np.arange(CHUNK)) % q_len
            self.noise[b, idx] = self.streams.noise(b)
            self.wi[b, L.WI_NOISE_COUNT] = count + CHUNK

    def _grow_noise(self, q_len: int) -> None:
        """A longer noise ring, each world's unrolled so that its head is at index 0."""
        old_q = self.noise.shape[1]
        idx = (self.wi[:, L.WI_NOISE_HEAD][:, None] + np.arange(old_q)[None, :]) % old_q
        new = np.zeros((self.batch_size, q_len, L.NZ_COLS))
        new[:, :old_q] = np.take_along_axis(self.noise, idx[:, :, None], axis=1)
        self.noise = new
        self.wi[:, L.WI_NOISE_HEAD] = 0

    def _reserve_ring(self, b: int, stream: int) -> None:
        if self.wi[b, L.WI_COUNT_RIGHT + stream] + CHUNK + 1 > self.sched.shape[2]:
            self._grow_rings(2 * self.sched.shape[2])

    # ------------------------------------------------------------------ resets
    def reset(
        self, seed: int | Sequence[int] | None = None, mask: np.ndarray | None = None
    ) -> None:
        """Fresh roads in steady flow for the worlds in `mask` (all if None), each warmed up for
        `traffic.warmup_s`, then an ego departs (with ramp flow: the ramp's vehicles arrive
        from the start of the warm-up, and no ego departs).

        seed: an int seeds world i with `SeedSequence(seed, spawn_key=(i,))`; a sequence gives
        each world its own seed (`marlmerge.sim.streams`). Without a seed a world's generators
        go on where they were (a first reset without a seed draws fresh entropy)."""
        rows = np.arange(self.batch_size) if mask is None else np.flatnonzero(mask)
        if rows.size == 0:
            return
        fresh = [b for b in rows if not self.streams.gens[b]]
        if seed is not None:
            self.streams.seed(rows, world_seed_sequences(self.batch_size, seed, rows))
        elif fresh:
            self.streams.seed(np.array(fresh), world_seed_sequences(1, None, np.array(fresh)))
        if self.streams.tilted is not None:
            self.streams.tilted.restart(rows)
        sel = np.zeros(self.batch_size, dtype=bool)
        sel[rows] = True
        self._clear(rows)
        # the cleared worlds hold nothing drawn: the next call draws ahead in their groups
        self._served_k[self._group_rows(rows)] = -1
        for b in rows:
            if self.cfg.sample.active:
                self._draw_scenario(b)
            if self.params[b, L.P_LAPSE_P] > 0.0:
                self.wi[b, L.WI_LAPSE_KEY] = self.streams.lapse_key(b)
            self._place(b, self.streams.fill(b))
        kernels.rebuild_lanes(self.arrays, self.params, sel)
        n_warm = int(round(self.cfg.traffic.warmup_s / self.cfg.sim.dt_s))
        nan = np.full((self.batch_size, 2), np.nan)
        done = 0
        while done < n_warm:
            k = min(WARMUP_CHUNK_STEPS, n_warm - done)
            self._call(nan, k, self._no_roster, self._no_cmd, sel)
            done += k
        if not self.cfg.ramp.flowing:
            self.next_ego(sel)

    def _draw_scenario(self, b: int) -> None:
        """World `b` draws its traffic (`[sample]`) for the road it is about to get, and with a
        scenario source that names the road's seed, starts its other generators from it."""
        g = self.streams.gens[b][SCENARIO_STREAM]
        if self.scenario_source is None:
            cfg = draw_world_scenario(self.cfg, g)
        else:
            cfg, self.world_tag[b] = self.scenario_source.draw(self.cfg, b, g)
            road_seed = self.scenario_source.road(b, int(self.world_tag[b]))
            if road_seed is not None:
                self.streams.seed_road(b, road_seed)
        self._set_world_scenario(b, cfg)

    def _set_world_scenario(self, b: int, cfg: ScenarioConfig) -> None:
        self.streams.cfgs[b] = cfg
        branch = self.params[b, L.P_LAPSE_FORCE]  # the world's own, not the scenario's
        self.params[b] = self._pack(cfg)
        self.params[b, L.P_LAPSE_FORCE] = branch

    def set_lapse_branches(self, branch: Sequence[int] | np.ndarray) -> None:
        """With lapse splitting: world b runs branch `branch[b]` of its road from now on (-1:
        the trunk, j >= 0: the lapse begins at the j-th branch point; `marlmerge.sim.lapses`),
        kept in its parameters (`P_LAPSE_FORCE`) across resets.
        Set it before the ego reaches the merge zone; the branch replays the road of the same
        seed."""
        if self.proposal is None or self.proposal.lapse_split is None:
            raise ValueError("set_lapse_branches: the core has no proposal with lapse_split")
        branch = np.asarray(branch)
        if branch.shape != (self.batch_size,) or not np.issubdtype(branch.dtype, np.integer):
            raise ValueError(
                f"set_lapse_branches: one integer per world ({self.batch_size}), got {branch!r}"
            )
        if np.any(branch < -1):
            raise ValueError(f"set_lapse_branches: branches are -1 or >= 0, got {branch.min()}")
        self.params[:, L.P_LAPSE_FORCE] = branch

    def _pack(self, cfg: ScenarioConfig) -> np.ndarray:
        """A world's parameters (`layout.pack_params`), with the proposal's lapse probability
        for the drivers whose lapses it tilts (`marlmerge.sim.lapses`)."""
        row = L.pack_params(cfg)
        if self.proposal is not None and self.proposal.lapse_p is not None:
            row[L.P_LAPSE_Q : L.P_LAPSE_Q + L.N_LAPSE_CLASSES] = self.proposal.lapse_p
        if self.proposal is not None and self.proposal.lapse_split is not None:
            row[L.P_LAPSE_SPLIT] = 1.0
            row[L.P_LAPSE_R : L.P_LAPSE_R + L.N_LAPSE_CLASSES] = self.proposal.lapse_split
        return row

    def world_scenario(self, b: int) -> ScenarioConfig:
        """The scenario world `b` runs now: the core's, or the traffic it drew (`[sample]`)."""
        return self.streams.cfgs[b]

    def _clear(self, rows: np.ndarray) -> None:
        self.vf[rows] = 0.0
        self.vi[rows] = 0
        self.vi[rows, L.VI_LANE] = RAMP
        self.vi[rows, L.VI_ID] = -1
        self.wf[rows] = 0.0
        self.wi[rows] = 0
        self.lanes[rows] = -1
        self.sched[rows] = 0.0
        self.wi[rows, L.WI_FRONT] = self.wi[rows, L.WI_BACK] = -1

    def _place(self, b: int, vehicles: dict[str, np.ndarray]) -> None:
        """Put filled-in mainline vehicles into slots 1.. of world `b` (lanes rebuilt after)."""
        n = vehicles["x_m"].size
        self._reserve_slots(np.array([b]), np.array([n + 1 + 2 * WARMUP_CHUNK_STEPS + 2]))
        s = np.arange(1, n + 1)
        for row, key in (
            (L.VF_X, "x_m"),
            (L.VF_V, "v_mps"),
            (L.VF_V0, "v0_mps"),
            (L.VF_T, "headway_s"),
            (L.VF_POL, "politeness"),
        ):
            self.vf[b, row, s] = vehicles[key]
        self.vf[b, L.VF_SINCE_LC, s] = self.cfg.driver.lane_change_cooldown_s
        self.vi[b, L.VI_LANE, s] = vehicles["lane"].astype(np.int64)
        self.vi[b, L.VI_PROFILE, s] = vehicles["profile"].astype(np.int64)
        self.vi[b, L.VI_ACTIVE, s] = 1
        self.vi[b, L.VI_ID, s] = s - 1
        self.wi[b, L.WI_NEXT_ID] = n

    def next_ego(self, mask: np.ndarray) -> None:
        """End the current ego in the worlds of `mask` and send the next one from the ramp start.

        A merged ego stays on the road as a neutral mainline vehicle; after a collision the ego and
        the vehicles it hit are towed away; a truncated ego is removed."""
        if self.cfg.ramp.flowing:
            raise ValueError(
                f"next_ego: ramp.flow_vph = {self.cfg.ramp.flow_vph} runs ramp flow, which has "
                "no ego (its ramp vehicles are agents: marlmerge.evaluation.ramp_flow)"
            )
        sel = self._mask(mask)
        if self._resampling:  # worlds that drew their traffic long enough get new traffic
            redraw = sel & (self.wi[:, L.WI_EGO_COUNT] >= self.cfg.sample.resample_every_egos)
            if redraw.any():
                self.reset(mask=redraw)
                sel = sel & ~redraw
        # a departure measures once (noise on); the next call needs k + 2
        noise_need = np.maximum(self._served_k, 1) + 3 if self._noisy else self._no_noise_need
        status = kernels.next_ego(self.arrays, self.sensor, self.params, sel, noise_need, True)
        if status < 0:  # only after direct set-ups: every call leaves room for one next_ego
            short = np.flatnonzero(sel & (self.wi[:, L.WI_NEED] != 0))  # flagged by the kernel
            for k in np.unique(self._served_k[short]).tolist():  # one k with one group
                self._serve(max(k, 1), short[self._served_k[short] == k])
            status = kernels.next_ego(self.arrays, self.sensor, self.params, sel, noise_need, False)
        if status:
            self._check_overflow()

    def remove_ego(self, mask: np.ndarray | None = None) -> None:
        """Take the ramp vehicle off the road in the worlds of `mask` (all if None): traffic-only
        worlds, until `next_ego` sends one again."""
        sel = self._mask(mask)
        kernels.remove_ego(self.arrays, self.params, sel)

    def _mask(self, mask: np.ndarray | None) -> np.ndarray:
        if mask is None:
            return np.ones(self.batch_size, dtype=bool)
        m = np.asarray(mask, dtype=bool).reshape(-1)
        if m.shape != (self.batch_size,):
            raise ValueError(f"mask must have shape ({self.batch_size},), got {m.shape}")
        return m

    # ------------------------------------------------------------------ stepping
    def rollout(
        self,
        ego_accel: np.ndarray,
        k: int | None = None,
        roster: Roster | None = None,
        roster_accel: np.ndarray | None = None,
        worlds: np.ndarray | None = None,
        ego_join: np.ndarray | None = None,
        roster_join: np.ndarray | None = None,
    ) -> Rollout:
        """Hold `ego_accel` ([B] m/s^2, clipped to the ego bounds; NaN: the ego drives by plain
        IDM and ignores the merge) for `k` simulator steps (default `sim.action_repeat`) in every
        world (or in the worlds of the mask `worlds` [B]; the others stand still and only report
        their observations). `roster` names highway agents whose terms and observations are
        computed, and `roster_accel` [B, K] (NaN: scripted) drives them. A world whose ego was
        running stops at the step its episode ends. With `ego.join = "chosen"`, `ego_join` [B]
        and `roster_join` [B, K] are the join commands (> 0: join now, inside the merge zone;
        NaN, the default: joined as without a choice, `marlmerge.sim.step.joins_now`)."""
        k = self.cfg.sim.action_repeat if k is None else int(k)
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        b = self.batch_size
        roster = self._no_roster if roster is None else roster
        ego_cmd = np.full((b, 2), np.nan)
        ego_cmd[:, 0] = self._per_world("ego_accel", ego_accel)
        if ego_join is not None:
            ego_cmd[:, 1] = self._per_world("ego_join", ego_join)
        if roster.n_agents == 0:
            roster_cmd = self._no_cmd
        else:
            roster_cmd = np.full((b, roster.n_agents, 2), np.nan)
            for c, value in enumerate((roster_accel, roster_join)):
                if value is None:
                    continue
                value = np.asarray(value, dtype=np.float64)
                if value.shape != (b, roster.n_agents):
                    raise ValueError(
                        f"roster commands of shape {value.shape} do not fit {b} worlds and "
                        f"{roster.n_agents} agents"
                    )
                roster_cmd[:, :, c] = value
        step_mask = None if worlds is None else self._mask(worlds)
        return self._call(ego_cmd, k, roster, roster_cmd, step_mask)

    def _per_world(self, name: str, value: np.ndarray | float) -> np.ndarray:
        """`value` as [B] float64: one number per world (a scalar only with one world)."""
        out = np.asarray(value, dtype=np.float64)
        if out.size != self.batch_size:
            raise ValueError(
                f"{name} of shape {out.shape} does not fit {self.batch_size} worlds "
                "(one command per world)"
            )
        return out.reshape(self.batch_size)

    def step(
        self,
        ego_accel: np.ndarray,
        roster: Roster | None = None,
        roster_accel: np.ndarray | None = None,
        ego_join: np.ndarray | None = None,
    ) -> StepEvents:
        """Advance every world by one simulator step (see `rollout`)."""
        out = self.rollout(ego_accel, 1, roster, roster_accel, ego_join=ego_join)
        flags = self.vi[:, L.VI_FLAGS]
        return StepEvents(
            ego_outcome=out.ego_outcome,
            collided=(flags & L.EV_COLLIDED) != 0,
            exited=(flags & L.EV_EXITED) != 0,
            ego_partner=out.ego_partner,
            ego_rear=out.ego_rear,
        )

    def _call(
        self,
        ego_cmd: np.ndarray,
        k: int,
        roster: Roster,
        roster_cmd: np.ndarray,
        step_mask: np.ndarray | None = None,
    ) -> Rollout:
        b, n_agents = self.batch_size, roster.n_agents  # ego_cmd [B, 2], roster_cmd [B, K, 2]
        if roster.rows.shape != (L.RO_ROWS, b, n_agents):
            raise ValueError(f"roster of shape {roster.rows.shape} does not fit {b} worlds")
        active = self._ready_for(k, step_mask)
        mask_before = roster.rows[L.RO_MASK].copy() if n_agents else None
        ego_terms = np.empty((b, len(EGO_TERMS)))
        hw_terms = np.empty((b, n_agents, len(LEARNED_HIGHWAY_TERMS)))
        trace = np.empty((b, k, L.TR_COLS))
        ego_obs = np.empty((b, self.obs_size), dtype=np.float32)
        hw_obs = np.empty((b, n_agents, len(HIGHWAY_FEATURES)), dtype=np.float32)
        call = np.empty((L.WI_CALL.stop - L.WI_CALL.start, b), dtype=np.int64)  # [5, B]
        timer = None if self._called else _announce_compilation(repr(self._kernel))
        status = self._kernel(
            self.arrays, self.sensor, *self._worlds, self.params, k,
            self._all_worlds if step_mask is None else step_mask,
            ego_cmd, roster.rows, roster_cmd,
            ego_terms, hw_terms, trace, ego_obs, hw_obs, call,
        )  # fmt: skip
        if timer is not None:
            timer.cancel()
        self._called = True
        if status >= kernels.OVERFLOW:
            self._check_overflow()
        if status or self._group_of is not None:
            self._serve_needs(k, active)
        no_agents = _NO_AGENTS[:b]
        return Rollout(
            substeps=call[L.WI_SUBSTEPS - L.WI_STEP_OUTCOME],
            ego_steps=call[L.WI_EGO_STEPS - L.WI_STEP_OUTCOME],
            ego_outcome=call[0],
            ego_terms=ego_terms,
            trace=trace,
            ego_obs=ego_obs,
            hw_terms=hw_terms,
            hw_obs=hw_obs,
            left_road=(mask_before != 0) & ~roster.mask if n_agents else no_agents,
            exited=roster.exited if n_agents else no_agents,
            ego_partner=call[L.WI_EGO_PARTNER - L.WI_STEP_OUTCOME],
            ego_rear=call[L.WI_EGO_REAR - L.WI_STEP_OUTCOME] != 0,
            filter_interventions=self._interventions(),
        )

    def _ready_for(self, k: int, step_mask: np.ndarray | None) -> np.ndarray:
        """Before a call of `k` steps: draw ahead where the worlds were drawn ahead for another
        step count (after a reset, or a call of another k). Returns the worlds of the groups
        that step (all of them with one group), whose needs the call then serves."""
        if self._group_of is None:  # one group: every world was drawn ahead for the same k
            if self._served_k[0] != k:
                self._serve(k)
            return self._all_rows
        if step_mask is None:  # every group steps
            active = self._all_rows
        else:
            active = self._group_rows(np.flatnonzero(step_mask))
        stale = active[self._served_k[active] != k]  # whole groups
        if stale.size:
            self._serve(k, stale)
        return active

    def _serve_needs(self, k: int, active: np.ndarray) -> None:
        """After a call of `k` steps: draw ahead and make room where the kernels flagged a need
        (`WI_NEED`). With draw groups, only in the groups that stepped (`active`; the others
        were judged against this call's k, not their own), and a world is short of slots
        against its group's count (`_reserve_slots`), not the arrays' (`draw_groups`)."""
        need = self.wi[:, L.WI_NEED] != 0
        if self._group_of is not None:
            need |= self._slots_needed(slice(None), k) > self._group_slots[self._group_of]
            idle = np.ones(self.batch_size, dtype=bool)
            idle[active] = False
            need &= ~idle
            self.wi[idle, L.WI_NEED] = 0
        if need.any():
            self._serve(k, np.flatnonzero(need))

    def _interventions(self) -> np.ndarray | None:
        """[B] the safety filter's overrides in each world's current (or just ended) episode;
        None with the filter off."""
        if not self.cfg.ego.safety_filter:
            return None
        return self.wi[:, L.WI_FILTER_COUNT].copy()

    def _check_overflow(self) -> None:
        bad = np.flatnonzero(self.wi[:, L.WI_OVERFLOW])
        if bad.size:
            raise RuntimeError(
                f"simulator ran out of vehicle slots or drawn vehicles in world {int(bad[0])} "
                "(a bug: the core reserves room before every call)"
            )

    # ------------------------------------------------------------------ agents and views
    def pick_roster(self, k: int) -> np.ndarray:
        """Slots of the mainline vehicles taking part in each world's current merge, [B, k]: the
        right-lane vehicles whose arrival time at the merge point (at current speeds) is closest
        to the ego's, nearest in time first; -1 where the lane holds fewer than k."""
        out = np.full((self.batch_size, k), -1, dtype=np.int64)
        if k > 0:
            kernels.pick_roster(self.arrays, out)
        return out

    def make_roster(self, slots: np.ndarray) -> Roster:
        """A roster of the vehicles now in `slots` ([B, K], -1 none)."""
        slots = np.asarray(slots, dtype=np.int64)
        rows = np.zeros((L.RO_ROWS,) + slots.shape, dtype=np.int64)
        safe = np.maximum(slots, 0)
        present = (slots > EGO) & (np.take_along_axis(self.vi[:, L.VI_ACTIVE], safe, axis=1) == 1)
        rows[L.RO_SLOT] = np.where(present, slots, -1)
        rows[L.RO_ID] = np.where(present, np.take_along_axis(self.vi[:, L.VI_ID], safe, axis=1), -1)
        rows[L.RO_MASK] = present
        return Roster(rows)

    def observe(self, roster: Roster | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The current observations: ego [B, obs_size] (the sensor's latest output; no new
        measurement) and the roster's [B, K, 12] float32."""
        roster = self._no_roster if roster is None else roster
        ego_obs = np.empty((self.batch_size, self.obs_size), dtype=np.float32)
        hw_obs = np.empty((self.batch_size, roster.n_agents, len(HIGHWAY_FEATURES)), np.float32)
        kernels.observe(self.arrays, self.sensor, self.params, roster.rows, ego_obs, hw_obs)
        return ego_obs, hw_obs

    def ramp_agents(self, k: int) -> tuple[Roster, np.ndarray]:
        """Ramp flow: the first `k` vehicles on each world's ramp (downstream first) as agents
        (a `Roster`: pass it to `rollout` with their commands as `roster_accel`) and what each
        sees, [B, k, F] float64 (`agent_features`: the ego's layout, scaled, measured from the
        agent with perfect sensing; zeros where the ramp holds fewer; `roster.mask`)."""
        if not self.cfg.ramp.flowing:
            raise ValueError("ramp_agents needs ramp flow (ramp.flow_vph > 0)")
        rows = np.zeros((L.RO_ROWS, self.batch_size, k), dtype=np.int64)
        obs = np.zeros((self.batch_size, k, len(self.agent_features)))
        kernels.ramp_agents(self.arrays, self.sensor, self.params, rows, obs)
        return Roster(rows), obs

    def observe_agents(self, roster: Roster) -> np.ndarray:
        """Ramp flow: what each agent of `roster` sees now, [B, K, F] float64 (`ramp_agents`;
        an agent that has joined the right lane sees its leader and follower)."""
        if not self.cfg.ramp.flowing:
            raise ValueError("observe_agents needs ramp flow (ramp.flow_vph > 0)")
        obs = np.zeros((self.batch_size, roster.n_agents, len(self.agent_features)))
        kernels.observe_agents(self.arrays, self.sensor, self.params, roster.rows, obs)
        return obs

    def ego_gaps(self) -> EgoGaps:
        """Gap-front and gap-back vehicles of the ego after the last call (computed there)."""
        wf, wi = self.wf, self.wi
        return EgoGaps(
            front=wi[:, L.WI_FRONT].copy(),
            back=wi[:, L.WI_BACK].copy(),
            d_front_m=wf[:, L.WF_DF].copy(),
            d_back_m=wf[:, L.WF_DB].copy(),
            x_front_m=wf[:, L.WF_XF].copy(),
            x_back_m=wf[:, L.WF_XB].copy(),
            v_front_mps=wf[:, L.WF_VF].copy(),
            v_back_mps=wf[:, L.WF_VB].copy(),
        )

    def entrance_stats(self) -> dict[str, np.ndarray]:
        """Per world [B]: vehicles entered and waiting (both lanes), the longest queue since
        reset, and the mean entrance delay (s) of the entered vehicles."""
        st = self.state
        entered = st.entered
        return {
            "entered": entered.copy(),
            "queue": st.queue.sum(axis=1),
            "max_queue": st.max_queue.copy(),
            "mean_delay_s": st.entry_delay_s / np.maximum(entered, 1),
        }

    # ------------------------------------------------------------------ placing vehicles
    def add_vehicle(
        self,
        world: int,
        x_m: float,
        v_mps: float,
        lane: int,
        v0_mps: float | None = None,
        headway_s: float | None = None,
        profile: int = 0,
        politeness: float = 0.0,
    ) -> int:
        """Put one mainline vehicle on the road of `world` (scenario set-ups, tests, validation);
        returns its slot."""
        if lane not in (L.RIGHT, L.LEFT):
            raise ValueError(f"lane must be RIGHT (0) or LEFT (1), got {lane!r}")
        if not (self.cfg.road.x_entrance_m <= x_m <= self.cfg.road.x_exit_m) or v_mps < 0:
            raise ValueError(f"vehicle at x_m={x_m}, v_mps={v_mps} is off the road")
        need = int(self.wi[world, L.WI_N_ACTIVE]) + 2 * max(int(self._served_k[world]), 1) + 3
        self._reserve_slots(np.array([world]), np.array([need]))
        free = np.flatnonzero(self.vi[world, L.VI_ACTIVE, 1:] == 0)
        s = int(free[0]) + 1
        d = self.cfg.driver
        self.vf[world, :, s] = 0.0
        self.vf[world, L.VF_X, s], self.vf[world, L.VF_V, s] = x_m, v_mps
        self.vf[world, L.VF_V0, s] = self.v_limit if v0_mps is None else v0_mps
        self.vf[world, L.VF_T, s] = np.mean(d.time_headway_s) if headway_s is None else headway_s
        self.vf[world, L.VF_POL, s] = politeness
        self.vf[world, L.VF_SINCE_LC, s] = d.lane_change_cooldown_s
        self.vi[world, :, s] = 0
        self.vi[world, L.VI_LANE, s], self.vi[world, L.VI_ACTIVE, s] = lane, 1
        self.vi[world, L.VI_PROFILE, s] = profile
        self.vi[world, L.VI_ID, s] = self.wi[world, L.WI_NEXT_ID]
        self.wi[world, L.WI_NEXT_ID] += 1
        sel = np.zeros(self.batch_size, dtype=bool)
        sel[world] = True
        kernels.rebuild_lanes(self.arrays, self.params, sel)
        self._restart_sensor(sel)
        return s

    def place(self, world: int, slot: int, x_m: float, v_mps: float | None = None) -> None:
        """Move the vehicle in `slot` of `world` to `x_m` (and speed `v_mps`), keeping the lane
        lists in order (scenario set-ups, tests). The ego is on the ramp before its overlap
        point and in the right lane from there on."""
        if not self.vi[world, L.VI_ACTIVE, slot]:
            raise ValueError(f"slot {slot} of world {world} holds no vehicle")
        self.vf[world, L.VF_X, slot] = x_m
        if v_mps is not None:
            self.vf[world, L.VF_V, slot] = v_mps
        if slot == EGO:
            self.vi[world, L.VI_LANE, EGO] = L.RIGHT if x_m >= self.cfg.x_overlap_m else RAMP
        sel = np.zeros(self.batch_size, dtype=bool)
        sel[world] = True
        kernels.rebuild_lanes(self.arrays, self.params, sel)
        self._restart_sensor(sel)

    def _restart_sensor(self, sel: np.ndarray) -> None:
        """A scene set up by hand: the ego's sensor starts a fresh history there (imperfect
        sensing only; the ego then sees its first measurement until `latency_s` has passed)."""
        if not self.cfg.sensing.active:
            return
        for b in np.flatnonzero(sel).tolist():  # one measurement now, k + 2 for the next call
            self._top_up_noise(b, max(int(self._served_k[b]), 1) + 3)
        kernels.sense_restart(self.arrays, self.sensor, self.params, sel)
        self._check_overflow()

    def clear_traffic(self, mask: np.ndarray | None = None) -> None:
        """Empty the roads of `mask` (all if None) and stop their arrivals: scenario set-ups
        place their own vehicles with `add_vehicle`."""
        sel = self._mask(mask)
        self.remove_ego(sel)
        self.vi[sel, L.VI_ACTIVE, 1:] = 0
        self.vi[sel, L.VI_LANE, 1:] = RAMP
        self.sched[sel, :2, :, L.SC_T] = np.inf  # every drawn arrival postponed forever
        if self.cfg.ramp.flowing:
            self.sched[sel, EGO_STREAM, :, L.SC_T] = np.inf
        kernels.rebuild_lanes(self.arrays, self.params, sel)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue bit for bit: arrays, generator states, the config."""
        if self.streams.tilted is not None:
            raise ValueError(
                "state_dict: a core drawing from a proposal is not saved (its estimates keep "
                "their per-batch results instead; marlmerge.evaluation.estimate)"
            )
        state = {
            "version": STATE_DICT_VERSION,
            "config": to_dict(self.cfg),
            "batch_size": self.batch_size,
            "arrays": {name: getattr(self, name).copy() for name in _ARRAYS},
            "generators": [[g.bit_generator.state for g in gens] for gens in self.streams.gens],
            # an int while the worlds agree (always with one group), else one per world
            "served_k": (
                int(self._served_k[0])
                if np.all(self._served_k == self._served_k[0])
                else self._served_k.tolist()
            ),
            "world_tag": self.world_tag.copy(),
            "world_scenarios": (
                [to_dict(c) for c in self.streams.cfgs]
                if self.cfg.sample.active or self.fixed_scenarios
                else []
            ),
        }
        if self._group_of is not None:  # with draw groups only: a core without is as it was
            state["group_slots"] = self._group_slots.tolist()
        return state

    def load_state_dict(self, saved: dict[str, Any]) -> None:
        """Restore a `state_dict` of a core with the same config and batch size."""
        version = saved.get("version")
        if version not in (1, 2, 3, 4, STATE_DICT_VERSION):
            raise ValueError(
                f"core state version {version!r} is not {STATE_DICT_VERSION} (saved by another "
                "version of marlmerge)"
            )
        cfg = from_dict(ScenarioConfig, saved["config"])
        if cfg != self.cfg:
            raise ValueError("core state was saved with a different scenario config")
        if saved["batch_size"] != self.batch_size:
            raise ValueError(
                f"core state has {saved['batch_size']} worlds, this core {self.batch_size}"
            )
        arrays = saved["arrays"]
        if version == 1:
            arrays = _upgrade_v1(saved, self)
        if version in (1, 2):
            arrays = _upgrade_v2(arrays)
        if version in (1, 2, 3):
            arrays = _upgrade_v3(arrays)
        elif version == 4:
            arrays = _upgrade_v4(arrays)
        for name in _ARRAYS:
            a = np.asarray(arrays[name])
            if a.ndim != getattr(self, name).ndim:
                raise ValueError(f"core state: array {name!r} has shape {a.shape}")
            setattr(self, name, a.copy())
        if (
            self.wi.shape[1] != L.WI_ROWS
            or self.lanes.shape[1] != 3
            or self.ring.shape
            != (
                self.batch_size * self._ring_len,
                self.obs_size,
            )
        ):
            raise ValueError("core state: per-world or sensor arrays do not fit this scenario")
        self.streams.seed(
            np.arange(self.batch_size),
            [np.random.SeedSequence(0) for _ in range(self.batch_size)],
        )
        for gens, states in zip(self.streams.gens, saved["generators"], strict=True):
            for g, s in zip(gens, states, strict=True):
                g.bit_generator.state = s
        self._served_k[:] = np.asarray(saved["served_k"], dtype=np.int64)
        self._group_slots[:] = saved.get("group_slots") or self.n_slots
        self.world_tag[:] = saved.get("world_tag", -1)
        for b, world in enumerate(saved.get("world_scenarios", [])):
            self._set_world_scenario(b, from_dict(ScenarioConfig, world))
        self._check_lanes()

    def _check_lanes(self) -> None:
        """The lane lists hold exactly the vehicles of each lane, downstream first."""
        for b in range(self.batch_size):
            for lane in (L.RIGHT, L.LEFT):
                n = int(self.wi[b, L.WI_N_RIGHT + lane])
                slots = self.lanes[b, lane, :n]
                want = np.flatnonzero(
                    (self.vi[b, L.VI_ACTIVE] == 1) & (self.vi[b, L.VI_LANE] == lane)
                )
                x = self.vf[b, L.VF_X, slots]
                if sorted(slots.tolist()) != want.tolist() or np.any(np.diff(x) > 0):
                    raise ValueError(f"core state: lane lists of world {b} are inconsistent")
            slots = self.lanes[b, L.RAMP_LIST, : int(self.wi[b, L.WI_N_RAMP])]
            on_ramp = (self.vi[b, L.VI_ACTIVE] == 1) & (self.vi[b, L.VI_LANE] == RAMP)
            on_ramp[EGO] = False
            x = self.vf[b, L.VF_X, slots]
            if sorted(slots.tolist()) != np.flatnonzero(on_ramp).tolist() or np.any(np.diff(x) > 0):
                raise ValueError(f"core state: the ramp list of world {b} is inconsistent")

    @property
    def egos_running(self) -> np.ndarray:
        """[B] bool: the world's ego is on the road and its episode has not ended."""
        return (self.vi[:, L.VI_ACTIVE, EGO] == 1) & (self.wi[:, L.WI_OUTCOME] == OUTCOME_NONE)


def _upgrade_v1(saved: dict[str, Any], core: TrafficCore) -> dict[str, np.ndarray]:
    """The arrays of a version-1 state (saved before the sensor existed, so with perfect
    sensing): the new `wi` rows zero, the sensor's arrays empty."""
    if core.cfg.sensing.active:  # pragma: no cover - a version-1 config has no sensing
        raise ValueError("core state of version 1 cannot hold a sensor's state")
    arrays = {name: np.asarray(saved["arrays"][name]) for name in _ARRAYS_V1}
    wi = arrays["wi"]
    if wi.ndim != 2 or wi.shape[1] != L.WI_ROWS_V1:
        raise ValueError(f"core state: array 'wi' has shape {wi.shape}")
    pad = np.zeros((wi.shape[0], L.WI_ROWS_V2 - L.WI_ROWS_V1), dtype=np.int64)
    arrays["wi"] = np.concatenate([wi, pad], axis=1)
    arrays["ring"] = np.zeros((core.batch_size * core._ring_len, core.obs_size))
    arrays["noise"] = np.zeros((core.batch_size, 0, L.NZ_COLS))
    return arrays


def _upgrade_v2(arrays: dict[str, Any]) -> dict[str, np.ndarray]:
    """The arrays of a version-2 state (saved before ramp flow): the new `vi`, `wf` and `wi`
    rows zero, an empty ramp list."""
    out = _zero_rows(
        arrays,
        ("vi", L.VI_ROWS, L.VI_ROWS_V2),
        ("wf", L.WF_ROWS_V3, L.WF_ROWS_V2),
        ("wi", L.WI_ROWS_V3, L.WI_ROWS_V2),
    )
    lanes = out["lanes"]
    if lanes.ndim != 3 or lanes.shape[1] != 2:
        raise ValueError(f"core state: array 'lanes' has shape {lanes.shape}")
    out["lanes"] = np.concatenate([lanes, np.full_like(lanes[:, :1], -1)], axis=1)
    return out


def _upgrade_v3(arrays: dict[str, Any]) -> dict[str, np.ndarray]:
    """The arrays of a version-3 state (saved before attention lapses): the new `vf`, `wf` and
    `wi` rows zero (no driver lapsing, no lapse drawn)."""
    return _zero_rows(
        arrays,
        ("vf", L.VF_ROWS, L.VF_ROWS_V3),
        ("wf", L.WF_ROWS, L.WF_ROWS_V3),
        ("wi", L.WI_ROWS, L.WI_ROWS_V3),
    )


def _upgrade_v4(arrays: dict[str, Any]) -> dict[str, np.ndarray]:
    """The arrays of a version-4 state (two lapse classes): its per-class lapse counts kept as
    those of classes 0 and 1, the new classes' zero (the counts only weigh draws under a
    proposal; the draws themselves do not depend on the classes)."""
    out = {name: np.asarray(a) for name, a in arrays.items()}
    wf = out["wf"]
    if wf.ndim != 2 or wf.shape[1] != L.WF_ROWS_V4:
        raise ValueError(f"core state: array 'wf' has shape {wf.shape}")
    new = np.zeros((wf.shape[0], L.WF_ROWS), dtype=wf.dtype)
    new[:, : L.WF_LAPSE_STEPS] = wf[:, : L.WF_LAPSE_STEPS]
    old_n = L.WF_LAPSE_STEPS + 2  # the version-4 lapse counts: [steps 0, steps 1, n 0, n 1]
    new[:, L.WF_LAPSE_STEPS : L.WF_LAPSE_STEPS + 2] = wf[:, L.WF_LAPSE_STEPS : old_n]
    new[:, L.WF_LAPSE_N : L.WF_LAPSE_N + 2] = wf[:, old_n : old_n + 2]
    out["wf"] = new
    return out


def _zero_rows(arrays: dict[str, Any], *grown: tuple[str, int, int]) -> dict[str, np.ndarray]:
    """`arrays` with each (name, rows, old) array grown from `old` to `rows` rows (axis 1) by
    rows of zeros; an array without `old` rows is refused."""
    out = {name: np.asarray(a) for name, a in arrays.items()}
    for name, rows, old in grown:
        a = out[name]
        if a.ndim < 2 or a.shape[1] != old:
            raise ValueError(f"core state: array {name!r} has shape {a.shape}")
        pad = np.zeros((a.shape[0], rows - old) + a.shape[2:], dtype=a.dtype)
        out[name] = np.concatenate([a, pad], axis=1)
    return out
