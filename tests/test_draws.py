"""The compiled draws ahead (`marlmerge.sim.draws`) against NumPy's `Generator`, bit for bit.

First each distribution on its own (many seeds, enough draws to reach the ziggurats' rare
branches), then whole cores: drawn ahead in compiled code and through the streams' NumPy calls
(`TrafficCore.compiled_draws = False`), every state array and every generator's state must be
the same after each call, for the paper's mode, drawn traffic, ramp flow, sensor noise, lapses,
draw groups and a restored checkpoint.
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from marlmerge.config import ScenarioConfig
from marlmerge.config.presets import resolve_config
from marlmerge.sim import OUTCOME_NONE, TrafficCore
from marlmerge.sim import draws as dr

FNS = dr.bitgen_functions()


@numba.njit(cache=False)
def _fill(fns: np.ndarray, st: np.uint64, kind: int, out: np.ndarray) -> None:
    for i in range(out.shape[0]):
        if kind == 0:
            out[i] = dr.next_double(fns, st)
        elif kind == 1:
            out[i] = dr.standard_exponential(fns, st)
        else:
            out[i] = dr.standard_normal(fns, st)


@pytest.mark.parametrize("kind", ["random", "standard_exponential", "standard_normal"])
def test_each_distribution_is_numpys(kind: str) -> None:
    """200,000 draws (the ziggurats' tails and wedges included) and the generator's state after
    them, for three seeds."""
    for seed in (0, 1, 20261207):
        ours, theirs = np.random.default_rng(seed), np.random.default_rng(seed)
        got = np.empty(200_000)
        code = ("random", "standard_exponential", "standard_normal").index(kind)
        _fill(FNS, dr.state_address(ours), code, got)
        want = getattr(theirs, kind)(200_000)
        np.testing.assert_array_equal(got, want)
        assert ours.bit_generator.state == theirs.bit_generator.state


def test_other_bit_generators_are_refused() -> None:
    with pytest.raises(TypeError, match="PCG64"):
        dr.state_address(np.random.Generator(np.random.MT19937(0)))


def _run(cfg: ScenarioConfig, compiled: bool, calls: int, **kw: object) -> list[tuple]:
    """Every state array and generator state after each of `calls` random-command calls."""
    core = TrafficCore(cfg, seed=7, **kw)  # type: ignore[arg-type]
    core.compiled_draws = compiled
    rng = np.random.default_rng(3)
    lo, hi = cfg.ego.accel_bounds_mps2
    snaps = []
    for call in range(calls):
        out = core.rollout(rng.uniform(lo, hi, size=core.batch_size))
        done = out.ego_outcome != OUTCOME_NONE
        if not cfg.ramp.flowing and done.any():
            core.next_ego(done)
        if call % 7 == 6 and cfg.sample.active:  # new roads mid-run: fresh draws ahead
            core.reset(mask=rng.random(core.batch_size) < 0.3)
        snaps.append(_snapshot(core))
    return snaps


def _snapshot(core: TrafficCore) -> tuple:
    arrays = tuple(a.copy() for a in (core.vf, core.vi, core.wf, core.wi, core.sched, core.noise))
    gens = [[g.bit_generator.state for g in gens] for gens in core.streams.gens]
    return arrays, gens


def _assert_same(got: list[tuple], want: list[tuple]) -> None:
    names = ("vf", "vi", "wf", "wi", "sched", "noise")
    for call, ((a_got, g_got), (a_want, g_want)) in enumerate(zip(got, want, strict=True)):
        for name, x, y in zip(names, a_got, a_want, strict=True):
            assert np.array_equal(x, y, equal_nan=True), f"call {call}: {name} differs"
        assert g_got == g_want, f"call {call}: a generator's state differs"


CASES = {
    "paper": (ScenarioConfig(), {"batch_size": 4}),
    "dense": (ScenarioConfig().replace(**{"traffic.flow_vph_per_lane": 2200.0}), {"batch_size": 3}),
    "hardened_mix": (resolve_config("hardened_mix"), {"batch_size": 6}),
    "ramp_flow": (ScenarioConfig().replace(**{"ramp.flow_vph": 900.0}), {"batch_size": 3}),
    "noise_and_lapses": (
        resolve_config("lapses").replace(**{"sensing.position_noise_std_m": 1.0}),
        {"batch_size": 3},
    ),
    "groups": (
        resolve_config("hardened_mix"),
        {"batch_size": 6, "world_groups": [0, 0, 1, 1, 2, 2]},
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_cores_draw_as_numpy(case: str) -> None:
    cfg, kw = CASES[case]
    _assert_same(_run(cfg, True, 150, **kw), _run(cfg, False, 150, **kw))


def test_restored_core_draws_as_numpy() -> None:
    """A core restored from a checkpoint reads its generators' new states (`state_dict`)."""
    cfg = ScenarioConfig()
    cores = []
    for compiled in (True, False):
        core = TrafficCore(cfg, batch_size=3, seed=1)
        core.compiled_draws = compiled
        for _ in range(60):
            out = core.rollout(np.zeros(3))
            core.next_ego(out.ego_outcome != OUTCOME_NONE)
        saved = core.state_dict()
        fresh = TrafficCore(cfg, batch_size=3, seed=99)
        fresh.compiled_draws = compiled
        fresh.rollout(np.zeros(3))  # its generators' addresses are known before the restore
        fresh.load_state_dict(saved)
        for _ in range(200):
            out = fresh.rollout(np.ones(3))
            fresh.next_ego(out.ego_outcome != OUTCOME_NONE)
        cores.append(_snapshot(fresh))
    _assert_same([cores[0]], [cores[1]])


def test_a_copied_core_draws_from_its_own_generators() -> None:
    """A deep copy takes its generators' addresses afresh: drawing ahead in the copy leaves the
    original's generators where they were, and both go on as the same world."""
    import copy

    core = TrafficCore(ScenarioConfig(), batch_size=2, seed=5)
    core.rollout(np.zeros(2))
    twin = copy.deepcopy(core)
    before = [g.bit_generator.state for g in core.streams.gens[0]]
    for _ in range(400):
        out = twin.rollout(np.zeros(2))
        twin.next_ego(out.ego_outcome != OUTCOME_NONE)
    assert [g.bit_generator.state for g in core.streams.gens[0]] == before
    for _ in range(400):
        out = core.rollout(np.zeros(2))
        core.next_ego(out.ego_outcome != OUTCOME_NONE)
    assert np.array_equal(core.vf, twin.vf, equal_nan=True)
