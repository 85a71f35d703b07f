"""The core owns its state: checkpoints continue bit for bit; worlds do not depend on their batch,
on threads, or on the compiler."""

import textwrap

import numpy as np
import pytest
from scenes import same_with_and_without_jit

from marlmerge.config import ScenarioConfig
from marlmerge.sim import TrafficCore

CFG = ScenarioConfig()


def _drive(core: TrafficCore, n: int, seed: int = 0) -> list[np.ndarray]:
    """n env steps with seeded random ego actions; the ego observations after each."""
    rng = np.random.default_rng(seed)
    obs = []
    for _ in range(n):
        out = core.rollout(rng.uniform(-4.5, 2.5, core.batch_size))
        obs.append(np.concatenate([out.ego_obs.ravel(), out.ego_terms.ravel()]))
        core.next_ego(out.ego_outcome != 0)
    return obs


def test_state_dict_round_trip_continues_bit_for_bit():
    core = TrafficCore(CFG, batch_size=3, seed=4)
    _drive(core, 150)
    saved = core.state_dict()
    expected = _drive(core, 300, seed=1)
    other = TrafficCore(CFG, batch_size=3, seed=99)
    other.load_state_dict(saved)
    got = _drive(other, 300, seed=1)
    assert all(np.array_equal(a, b) for a, b in zip(expected, got, strict=True))
    assert np.array_equal(core.vf, other.vf) and np.array_equal(core.lanes, other.lanes)


def test_state_dict_refuses_another_scenario_or_batch():
    saved = TrafficCore(CFG, batch_size=2, seed=0).state_dict()
    with pytest.raises(ValueError, match="different scenario"):
        TrafficCore(CFG.replace(**{"traffic.flow_vph_per_lane": 900.0}), 2).load_state_dict(saved)
    with pytest.raises(ValueError, match="worlds"):
        TrafficCore(CFG, batch_size=3).load_state_dict(saved)


def test_a_corrupt_state_is_refused():
    saved = TrafficCore(CFG, batch_size=2, seed=0).state_dict()
    saved["arrays"]["lanes"][1, 0, :2] = saved["arrays"]["lanes"][1, 0, 1::-1]
    with pytest.raises(ValueError, match="world 1"):
        TrafficCore(CFG, batch_size=2).load_state_dict(saved)


def test_state_views_are_read_only():
    core = TrafficCore(CFG, batch_size=1, seed=0)
    with pytest.raises(ValueError, match="read-only"):
        core.state.x_m[0, 0] = 5.0


def test_a_world_is_the_same_alone_or_in_a_batch_serial_or_parallel():
    seeds = [10, 11, 12, 13]
    batch = TrafficCore(CFG, batch_size=4, seed=seeds, parallel=False)
    threads = TrafficCore(CFG, batch_size=4, seed=seeds, parallel=True)
    a = np.stack(_drive(batch, 120))
    b = np.stack(_drive(threads, 120))
    assert np.array_equal(a, b)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-4.5, 2.5, (120, 4))
    for w, seed in enumerate(seeds):
        single = TrafficCore(CFG, batch_size=1, seed=[seed])
        together = TrafficCore(CFG, batch_size=4, seed=seeds)
        for t in range(120):
            o1 = single.rollout(actions[t, w : w + 1])
            o4 = together.rollout(actions[t])
            assert np.array_equal(o1.ego_obs[0], o4.ego_obs[w])
            single.next_ego(o1.ego_outcome != 0)
            together.next_ego(o4.ego_outcome != 0)


@pytest.mark.slow
def test_same_trajectory_with_the_compiler_off(tmp_path):
    code = textwrap.dedent("""
        import numpy as np
        from marlmerge.config import ScenarioConfig
        from marlmerge.sim import TrafficCore
        cfg = ScenarioConfig().replace(**{"traffic.warmup_s": 2.0})
        core = TrafficCore(cfg, batch_size=1, seed=3)
        rows = []
        for i in range(40):
            out = core.rollout(np.array([np.sin(i) * 2.0]))
            rows.append(np.concatenate([out.ego_obs[0], out.ego_terms[0], core.vf[0, 0]]))
            core.next_ego(out.ego_outcome != 0)
        np.save(__import__("sys").argv[1], np.stack(rows))
    """)
    assert same_with_and_without_jit(code, tmp_path)
