"""Traffic drawn per world (`[sample]`): in range, seeded per world, redrawn, checkpointed."""

from dataclasses import replace

import numpy as np
import pytest

from marlmerge.config import MPH_TO_MPS, ScenarioConfig
from marlmerge.config.presets import resolve_config
from marlmerge.sim import EGO, TrafficCore
from marlmerge.sim import layout as L
from marlmerge.sim.observation import SPEED_SCALE_MPS
from marlmerge.sim.streams import world_seed_sequences
from marlmerge.views.torchrl_env import BatchedMergeEnv

RANGES = {
    "sample.flow_vph_per_lane": [400.0, 1800.0],
    "sample.speed_limit_mph": [50.0, 70.0],
    "sample.entry_speed_fraction": [0.6, 0.95],
    "sample.adversarial_share": [0.0, 1.0],
    "sample.cooperative_share": [0.2, 0.4],
    "sample.ego_start_speed_mps": [12.0, 24.0],
}


def _cfg(**extra) -> ScenarioConfig:
    return ScenarioConfig().replace(**{**RANGES, **extra})


def _run(core: TrafficCore, steps: int, start: int = 0) -> np.ndarray:
    rows = []
    for i in range(start, start + steps):
        out = core.rollout(np.full(core.batch_size, np.sin(i)))
        rows.append(np.concatenate([out.ego_obs.ravel(), out.ego_terms.ravel()]))
        core.next_ego(out.ego_outcome != 0)
    return np.array(rows)


def test_each_world_draws_its_own_traffic_within_the_ranges():
    assert not ScenarioConfig().sample.active and _cfg().sample.active
    core = TrafficCore(_cfg(), batch_size=8, seed=1)
    worlds = [core.world_scenario(b) for b in range(8)]
    flows = [w.traffic.flow_vph_per_lane for w in worlds]
    assert len(set(flows)) == 8 and all(400 <= f <= 1800 for f in flows)
    for w in worlds:
        limit_mps = w.road.speed_limit_mph * MPH_TO_MPS
        assert 50 <= w.road.speed_limit_mph <= 70
        assert 0.6 * limit_mps <= w.traffic.entry_speed_mps[0] <= 0.95 * limit_mps
        assert sum(w.driver.mix) == pytest.approx(1.0)
        coop_of_rest = w.driver.mix_cooperative / (1 - w.driver.mix_adversarial)
        assert 0.2 <= coop_of_rest <= 0.4
        lo, hi = w.ego.start_speed_mps
        assert hi - lo == pytest.approx(6.0) and 12 - 3 <= lo and hi <= 24 + 3
        # the road geometry and the ego's settings are the scenario's
        assert w.road.merge_zone_m == core.cfg.road.merge_zone_m
        assert replace(w.ego, start_speed_mps=core.cfg.ego.start_speed_mps) == core.cfg.ego
    # the vehicles drive by their world's speed limit: desired speeds scale with it
    for b in range(8):
        on_road = core.vi[b, L.VI_ACTIVE] == 1
        on_road[EGO] = False
        v0 = core.vf[b, L.VF_V0, on_road]
        limit_mps = worlds[b].road.speed_limit_mph * MPH_TO_MPS
        assert np.all(v0 <= 1.1 * limit_mps * (1 + 1e-9))


def test_a_world_is_its_seed_alone_and_runs_repeat_bit_for_bit():
    cfg = _cfg()
    a, b = TrafficCore(cfg, batch_size=4, seed=7), TrafficCore(cfg, batch_size=4, seed=7)
    assert np.array_equal(_run(a, 300), _run(b, 300))
    seqs = world_seed_sequences(4, 7, np.arange(4))
    single = TrafficCore(cfg, batch_size=1, seed=[seqs[2]])
    assert single.world_scenario(0) == TrafficCore(cfg, batch_size=4, seed=7).world_scenario(2)
    other = TrafficCore(cfg, batch_size=4, seed=8)
    assert other.world_scenario(0) != TrafficCore(cfg, batch_size=4, seed=7).world_scenario(0)


@pytest.mark.parametrize("every", [1, 3])
def test_worlds_draw_new_traffic_every_n_ramp_vehicles(every):
    core = TrafficCore(_cfg(**{"sample.resample_every_egos": every}), batch_size=1, seed=3)
    seen = [core.world_scenario(0)]
    egos = 0
    for _ in range(3000):
        out = core.rollout(np.array([0.5]))
        if out.ego_outcome[0] != 0:
            egos += 1
            core.next_ego(np.array([True]))
            seen.append(core.world_scenario(0))
        if egos == 6:
            break
    assert egos == 6
    changed = [seen[i + 1] != seen[i] for i in range(6)]
    assert changed == [(i + 1) % every == 0 for i in range(6)]


def test_a_sampled_core_resumes_bit_for_bit_from_its_state():
    cfg = _cfg()
    core = TrafficCore(cfg, batch_size=4, seed=11)
    first = _run(core, 120)
    saved = core.state_dict()
    rest = _run(core, 200, start=120)
    again = TrafficCore(cfg, batch_size=4, seed=0)
    again.load_state_dict(saved)
    assert np.array_equal(_run(again, 200, start=120), rest)
    assert [again.world_scenario(b) for b in range(4)] == [core.world_scenario(b) for b in range(4)]
    assert first.shape[0] == 120


def test_the_ego_observes_its_worlds_speed_limit():
    env = BatchedMergeEnv(_cfg(), num_worlds=4, seed=2)
    td = env.reset()
    limits = [env.core.world_scenario(b).road.speed_limit_mps for b in range(4)]
    assert np.allclose(td["observation"][:, 6].numpy(), np.array(limits) / SPEED_SCALE_MPS)


def test_bad_ranges_name_the_key():
    with pytest.raises(ValueError, match="sample.flow_vph_per_lane"):
        _cfg(**{"sample.flow_vph_per_lane": [1800.0, 400.0]})
    with pytest.raises(ValueError, match="sample.adversarial_share"):
        _cfg(**{"sample.adversarial_share": [0.0, 1.5]})
    with pytest.raises(ValueError, match="sample.resample_every_egos"):
        _cfg(**{"sample.resample_every_egos": 0})
    with pytest.raises(ValueError, match="sample.sensing_range_m"):
        _cfg(**{"sample.sensing_range_m": [0.0, 100.0]})
    assert resolve_config("robust_mix").sample.active


def test_a_share_of_draws_has_drivers_of_one_profile():
    cfg = _cfg(**{"sample.pure_mix_fraction": 0.5})
    core = TrafficCore(cfg, batch_size=64, seed=4)
    mixes = [core.world_scenario(b).driver.mix for b in range(64)]
    pure = [m for m in mixes if sorted(m) == [0.0, 0.0, 1.0]]
    assert 20 <= len(pure) <= 44  # about half of 64
    assert {m.index(1.0) for m in pure} == {0, 1, 2}  # every profile appears
    # without it, the first draws of a world are those of the recipe without pure mixes
    plain = TrafficCore(_cfg(), batch_size=4, seed=4)
    with_pure = TrafficCore(cfg, batch_size=4, seed=4)
    for b in range(4):
        a, p = plain.world_scenario(b), with_pure.world_scenario(b)
        assert a.traffic == p.traffic and a.road == p.road


def test_worlds_draw_their_sensing_range_and_see_that_far():
    cfg = _cfg(**{"sample.sensing_range_m": [70.0, 150.0], "ego.observation": "extended"})
    core = TrafficCore(cfg, batch_size=6, seed=3)
    ranges = np.array([core.world_scenario(b).ego.sensing_range_m for b in range(6)])
    assert len(set(ranges)) == 6 and ranges.min() >= 70.0 and ranges.max() <= 150.0
    # the other draws are those of the same seed without a sensing range: it is drawn last
    plain = TrafficCore(_cfg(), batch_size=6, seed=3)
    for b in range(6):
        drawn, other = core.world_scenario(b), plain.world_scenario(b)
        assert drawn.traffic == other.traffic and drawn.driver == other.driver
        assert drawn.road == other.road and drawn.ego.start_speed_mps == other.ego.start_speed_mps
    # a missing left-lane vehicle ahead is reported at the world's own range
    left_front_dx = core.observe()[0][:, 10] * 100.0
    seen = left_front_dx < ranges - 1e-3
    assert np.allclose(left_front_dx[~seen], ranges[~seen], atol=1e-3)
    assert np.all(left_front_dx[seen] <= ranges[seen])
