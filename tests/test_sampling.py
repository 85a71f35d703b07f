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


WIDENED = {
    "sample.desired_speed_factor": [0.5, 1.3],
    "sample.time_headway_s": [0.6, 2.2],
    "sample.politeness": [0.0, 1.0],
    "sample.yield_max_brake_mps2": [0.5, 3.0],
    "sample.adversarial_accel_mps2": [1.0, 4.0],
    "sample.ramp_length_m": [40.0, 250.0],
    "sample.merge_zone_m": [30.0, 140.0],
}


def test_the_widened_keys_draw_drivers_and_road_within_their_ranges():
    core = TrafficCore(_cfg(**WIDENED), batch_size=8, seed=2)
    base = core.cfg.driver
    for w in (core.world_scenario(b) for b in range(8)):
        d, r = w.driver, w.road
        for key, (lo, hi) in (("desired_speed_factor", (0.5, 1.3)), ("time_headway_s", (0.6, 2.2))):
            band, width = getattr(d, key), np.diff(getattr(base, key))[0]
            assert lo <= np.mean(band) <= hi and np.diff(band)[0] == pytest.approx(width)
        assert 0.5 <= d.yield_max_brake_mps2 <= 3 and 1 <= d.adversarial_accel_mps2 <= 4
        assert 40 <= r.ramp_length_m <= 250 and 30 <= r.merge_zone_m <= 140
    assert len({core.world_scenario(b).road.merge_zone_m for b in range(8)}) == 8


def test_widening_keeps_the_existing_keys_draws_bit_identical():
    # the widened keys are drawn after the others: a preset without them draws as before
    plain = TrafficCore(_cfg(), batch_size=6, seed=3)
    wide = TrafficCore(_cfg(**WIDENED), batch_size=6, seed=3)
    for b in range(6):
        p, w = plain.world_scenario(b), wide.world_scenario(b)
        assert p.traffic == w.traffic and p.ego == w.ego and p.driver.mix == w.driver.mix


@pytest.mark.parametrize("key, value", [("road.ramp_length_m", 90.0), ("road.merge_zone_m", 60.0)])
def test_a_world_drawn_onto_a_road_drives_as_a_core_built_on_that_road(key, value):
    # per-world geometry reaches the kernels: a degenerate range [v, v] in [sample] gives the
    # same trajectories as a scenario whose road has v, with the same other draws
    # (every range degenerate: the extra draw shifts no later draw's value)
    sampled = {"sample.flow_vph_per_lane": [1500.0, 1500.0]}
    on_road = ScenarioConfig().replace(**sampled, **{f"sample.{key.split('.')[1]}": [value] * 2})
    drawn = TrafficCore(on_road, 4, 5)
    built = TrafficCore(ScenarioConfig().replace(**sampled, **{key: value}), 4, 5)
    assert np.array_equal(_run(drawn, 400), _run(built, 400))


def test_a_drawn_centre_outside_its_fields_bounds_is_refused_naming_the_key():
    with pytest.raises(ValueError, match="sample.desired_speed_factor"):
        ScenarioConfig().replace(**{"sample.desired_speed_factor": [0.5, 1.95]})
    with pytest.raises(ValueError, match="highway_upstream_m"):
        ScenarioConfig().replace(**{"sample.ramp_length_m": [100.0, 380.0]})


def test_worlds_given_their_scenarios_drive_as_cores_built_on_each():
    base = ScenarioConfig()
    own = [
        base.replace(**{"traffic.flow_vph_per_lane": 700.0, "road.merge_zone_m": 60.0}),
        base.replace(**{"driver.desired_speed_factor": [0.6, 0.8], "ego.sensing_range_m": 90.0}),
    ]
    batch = TrafficCore(base, 2, seed=[11, 12], scenarios=own)
    alone = [TrafficCore(world, 1, seed=[11 + b]) for b, world in enumerate(own)]
    rows_batch, rows_alone = [], []
    for i in range(300):
        out = batch.rollout(np.full(2, np.sin(i)))
        rows_batch.append(np.concatenate([out.ego_obs, out.ego_terms], axis=1))
        batch.next_ego(out.ego_outcome != 0)
        ones = [core.rollout(np.full(1, np.sin(i))) for core in alone]
        rows_alone.append(np.concatenate([np.c_[o.ego_obs, o.ego_terms] for o in ones]))
        for core, one in zip(alone, ones, strict=True):
            core.next_ego(one.ego_outcome != 0)
    assert np.array_equal(np.array(rows_batch), np.array(rows_alone))
    state = batch.state_dict()  # the worlds' scenarios are in the checkpoint
    assert [w["road"]["merge_zone_m"] for w in state["world_scenarios"]] == [60.0, 100.0]


def test_a_world_scenario_may_differ_only_in_what_sample_draws():
    base = ScenarioConfig()
    with pytest.raises(ValueError, match=r"scenarios\[1\]: driver.delta"):
        TrafficCore(base, 2, seed=0, scenarios=[base, base.replace(**{"driver.delta": 3.0})])
    with pytest.raises(ValueError, match="one per world"):
        TrafficCore(base, 2, seed=0, scenarios=[base])
    with pytest.raises(ValueError, match=r"\[sample\]"):
        TrafficCore(_cfg(), 1, seed=0, scenarios=[base])


@pytest.mark.parametrize(
    "mix", [(0.6, 0.3, 0.1), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.1, 0.7, 0.2)]
)
def test_drawn_profiles_are_what_generator_choice_draws(mix):
    """`Streams._profiles` replaces `Generator.choice(3, p=...)` (its checks cost a third of a
    chunk of arrivals): the same profiles, and the generator left in the same state."""
    from marlmerge.sim.streams import Streams

    keys = ("driver.mix_neutral", "driver.mix_cooperative", "driver.mix_adversarial")
    cfg = ScenarioConfig().replace(**dict(zip(keys, mix, strict=True)))
    streams = Streams(cfg, 1)
    p = np.asarray(cfg.driver.mix) / sum(cfg.driver.mix)
    for seed in range(50):
        ours, numpy = np.random.default_rng(seed), np.random.default_rng(seed)
        for n in (32, 5):
            expected = numpy.choice(3, size=n, p=p).astype(np.float64)
            assert np.array_equal(streams._profiles(cfg, ours, n), expected)
        assert ours.bit_generator.state == numpy.bit_generator.state


def test_the_hardened_roads_preset_is_hardened_mix_with_the_stress_spaces_roads():
    # the road keys are drawn last: each world's traffic is hardened_mix's, on its own road
    from marlmerge.evaluation.space import SPACE

    mix, roads = resolve_config("hardened_mix"), resolve_config("hardened_roads")
    assert (
        roads.replace(**{"sample.ramp_length_m": None, "sample.merge_zone_m": None}).replace(
            name="hardened_mix"
        )
        == mix
    )
    bounds = {d.key: (d.low, d.high) for d in SPACE}
    plain, drawn = TrafficCore(mix, 16, 7), TrafficCore(roads, 16, 7)
    for b in range(16):
        p, w = plain.world_scenario(b), drawn.world_scenario(b)
        assert (p.traffic, p.driver, p.ego) == (w.traffic, w.driver, w.ego)
        for key in ("ramp_length_m", "merge_zone_m"):
            lo, hi = bounds[key]
            assert lo <= getattr(w.road, key) <= hi
            assert getattr(p.road, key) == getattr(mix.road, key)
    assert len({drawn.world_scenario(b).road.ramp_length_m for b in range(16)}) == 16
