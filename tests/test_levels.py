"""Prioritised level replay: the replay distribution, the core's scenario source, training with it
and its exact resume."""

import csv

import numpy as np
import pytest

from marlmerge.config.presets import resolve_config
from marlmerge.config.training import LevelsConfig
from marlmerge.io import files
from marlmerge.sim import layout as L
from marlmerge.sim.core import TrafficCore
from marlmerge.sim.streams import world_changes
from marlmerge.training.levels import LevelReplay
from marlmerge.training.train import load_train_config, train


def _replay(**kw):
    return LevelReplay(LevelsConfig(**{"replay_fraction": 0.5, "min_levels": 1, **kw}))


def test_replay_ranks_by_failure_and_brings_stale_levels_back():
    """Three scored levels with failure scores 5.5/6, 1.5/6 and 0.5/6: with no staleness the
    replay probabilities are (1/rank)^(1/T) normalised; staleness mixes in the draws since
    each was chosen."""
    replay = _replay(temperature=0.5, staleness=0.0)
    scen = resolve_config("robust_mix")
    g = np.random.default_rng(0)
    tags = [replay.draw(scen, 0, g)[1] for _ in range(3)]  # no scored level yet: fresh draws
    assert tags == [0, 1, 2] and replay.draws == 3
    for tag, fails in zip(tags, (5, 1, 0), strict=True):
        replay.update(np.full(5, tag), np.arange(5) < fails)
    p = replay.probabilities([0, 1, 2])
    want = np.array([1.0, 1 / 4, 1 / 9])
    assert np.allclose(p, want / want.sum())
    stale = _replay(temperature=0.5, staleness=1.0)
    stale.load_state_dict(replay.state_dict())
    assert np.allclose(stale.probabilities([0, 1, 2]), np.array([2.0, 1.0, 0.0]) / 3.0)
    # a full buffer drops its lowest-scored level for a fresh draw
    small = _replay(capacity=3, replay_fraction=0.0)
    small.load_state_dict(replay.state_dict())
    _, tag = small.draw(scen, 0, g)
    assert tag == 3 and sorted(small.levels) == [0, 1, 3]
    small.update(np.array([2, 3]), np.array([True, False]))  # a dropped level is skipped
    assert small.levels[3].episodes == 1


def test_learnability_puts_levels_the_ego_sometimes_fails_first():
    """`score = "learnability"`: p (1 - p), p = (failures + m) / (episodes + 1), m the buffer's
    failure rate. A level failed once, or half the time, ranks above one always failed (40 of
    40) and one never failed; an unscored level is kept when the buffer is full, and the
    levels' ranks under "failure" are the plain failure rate's."""
    scen = resolve_config("robust_mix")
    g = np.random.default_rng(0)
    learn = _replay(score="learnability", temperature=1.0, staleness=0.0, capacity=5)
    tags = [learn.draw(scen, 0, g)[1] for _ in range(4)]
    for tag, (fails, eps) in zip(tags, ((1, 1), (4, 8), (40, 40), (0, 45)), strict=True):
        learn.update(np.full(eps, tag), np.arange(eps) < fails)
    m = 45 / 94
    p = (np.array([1, 4, 40, 0]) + m) / (np.array([1, 8, 40, 45]) + 1)
    assert np.allclose(learn.scores(tags), p * (1 - p))
    assert list(np.argsort(-learn.scores(tags))) == [1, 0, 2, 3]
    assert np.allclose(learn.probabilities(tags)[[1, 0, 2, 3]], np.array([12, 6, 4, 3]) / 25)
    fail = _replay(temperature=1.0, staleness=0.0)
    fail.load_state_dict(learn.state_dict())
    assert list(np.argsort(-fail.scores(tags))) == [2, 0, 1, 3]
    learn.cfg = LevelsConfig(replay_fraction=0.0, capacity=5, score="learnability")
    assert learn.draw(scen, 0, g)[1] == 4  # a fifth, unscored level fills the buffer
    assert learn.draw(scen, 0, g)[1] == 5  # full: the never-failed level goes, not the unscored
    assert sorted(learn.levels) == [0, 1, 2, 4, 5]
    with pytest.raises(ValueError, match="levels.score must be one of"):
        load_train_config("quick", **{"levels.score": "regret"})


def test_off_or_before_the_first_scores_the_core_draws_as_without_it():
    """A replay with replay_fraction = 0, or before min_levels levels are scored, draws each
    world's traffic from its own stream exactly as `[sample]` does."""
    scen = resolve_config("robust_mix4")
    plain = TrafficCore(scen, batch_size=4, seed=3)
    for source in (_replay(replay_fraction=0.0), _replay(min_levels=10_000)):
        core = TrafficCore(scen, batch_size=4, seed=3, scenario_source=source)
        for c in (plain, core):
            c.reset(seed=3)
            c.next_ego(np.ones(4, dtype=bool))  # resample_every_egos = 1: new traffic
        assert all(core.world_scenario(b) == plain.world_scenario(b) for b in range(4))
        assert list(core.world_tag) == list(range(source.next_id - 4, source.next_id))
        assert np.array_equal(core.state_dict()["arrays"]["vf"], plain.state_dict()["arrays"]["vf"])
    with pytest.raises(ValueError, match=r"\[sample\]"):
        TrafficCore(resolve_config("default"), scenario_source=_replay())


def test_replayed_levels_are_the_failing_ones():
    """Levels scored as failing come back far more often than their share of the buffer."""
    scen = resolve_config("robust_mix")
    replay = _replay(replay_fraction=0.9, staleness=0.0, temperature=0.3)
    g = np.random.default_rng(1)
    for _ in range(40):
        _, tag = replay.draw(scen, 0, g)
        replay.update(np.array([tag]), np.array([tag % 10 == 0]))  # every tenth level fails
    chosen = [replay.draw(scen, 0, g)[1] for _ in range(400)]
    replayed = [t for t in chosen if t < 40]
    assert len(replayed) > 300
    assert np.mean([t % 10 == 0 for t in replayed]) > 0.8  # 4 of 40 levels fail


class _OneLevel:
    """A scenario source that runs every new road on one level: level 0 of `replay`, drawn
    once."""

    def __init__(self, replay):
        self.replay = replay

    def draw(self, base, world, g):
        if not self.replay.levels:
            self.replay.draw(base, world, g)  # level 0: a fresh draw (with its road's seed)
        return base.replace(**world_changes(base, *self.replay.levels[0].draw)), 0

    def road(self, world, tag):
        return self.replay.road(world, tag)


def _road(core, b=0):
    """World b's vehicles now: position, speed, desired speed and lane of each slot."""
    arrays = core.state_dict()["arrays"]
    vf, vi = arrays["vf"][b], arrays["vi"][b]
    return np.concatenate([vf[[L.VF_X, L.VF_V, L.VF_V0]].ravel(), vi[L.VI_LANE].ravel()])


def test_replayed_roads_are_the_same_road():
    """With `replay_roads` a level carries the seed of its road: every world that runs it gets
    the same vehicles, the same ego; without it, the same traffic condition on new roads. The
    road's seed goes through the buffer's state, and older states without it still load."""
    scen = resolve_config("robust_mix4")
    roads = {}
    for on in (True, False):
        core = TrafficCore(
            scen, batch_size=2, seed=5, scenario_source=_OneLevel(_replay(replay_roads=on))
        )
        core.reset(seed=5)
        first = [_road(core, b) for b in range(2)]
        core.next_ego(np.ones(2, dtype=bool))  # resample_every_egos = 1: the level again
        roads[on] = first + [_road(core, b) for b in range(2)]
        assert core.world_scenario(0) == core.world_scenario(1)
    assert all(np.array_equal(roads[True][0], r) for r in roads[True][1:])
    assert not any(np.array_equal(roads[False][0], r) for r in roads[False][1:])
    replay = _replay(replay_roads=True)
    g = np.random.default_rng(2)
    tags = [replay.draw(scen, 0, g)[1] for _ in range(3)]
    seeds = [replay.road(0, t) for t in tags]
    assert len(set(seeds)) == 3 and all(isinstance(s, int) for s in seeds)
    again = _replay(replay_roads=True)
    again.load_state_dict(replay.state_dict())
    assert [again.road(0, t) for t in tags] == seeds
    old = replay.state_dict()
    old["levels"] = [entry[:6] for entry in old["levels"]]
    again.load_state_dict(old)
    assert [again.road(0, t) for t in tags] == [None] * 3
    with pytest.raises(ValueError, match="replay_roads = true needs levels.replay_fraction"):
        load_train_config("quick", **{"levels.replay_roads": True})


TINY = dict(
    scenario="robust_mix4",
    total_sim_steps=8_192,
    num_worlds=8,
    learning_starts=256,
    replay_capacity=5_000,
    update_path="fast",
    checkpoint_every_sim_steps=2_048,
    eval_episodes=4,
    eval_worlds=4,
    **{"levels.replay_fraction": 0.5, "levels.min_levels": 8},
)


@pytest.mark.slow
@pytest.mark.parametrize("roads", [False, True])
def test_training_with_level_replay_resumes_bit_for_bit(tmp_path, roads):
    cfg = load_train_config("quick", **TINY, **{"levels.replay_roads": roads})
    full, cut = tmp_path / "full", tmp_path / "cut"
    train(cfg, full, progress=False)
    train(cfg, cut, progress=False, stop_after_sim_steps=5_000)
    train(cfg, cut, resume=True, progress=False)
    assert (full / "egos.csv").read_text() == (cut / "egos.csv").read_text()
    a, b = (files.load(d / "policy.pt")["policy_state"]["net"] for d in (full, cut))
    assert all(np.array_equal(a[k].numpy(), b[k].numpy()) for k in a)
    levels = files.load(full / "checkpoint.pt")["levels"]
    assert all((lv[6] is not None) == roads for lv in levels["levels"])
    scored = [lv for lv in levels["levels"] if lv[3] > 0]
    assert len(scored) >= 8 and levels["draws"] > len(levels["levels"])  # levels were replayed
    with open(full / "egos.csv", newline="") as fh:
        egos = sum(1 for _ in csv.DictReader(fh))
    assert sum(lv[3] for lv in levels["levels"]) <= egos


def test_stress_regions_seed_the_buffer(tmp_path):
    """`[levels] seed_presets`: each preset's [sample] box (and its road) becomes
    `seed_levels` levels scored as one failure each, replayed before any fresh draw is scored;
    a preset that does not load or seeds without replay is refused, naming the key."""
    region = tmp_path / "region_01.toml"
    region.write_text(
        'name = "region_01"\n[road]\nmerge_zone_m = 60.0\n'
        "[sample]\nflow_vph_per_lane = [2000.0, 2100.0]\nadversarial_share = [0.9, 1.0]\n"
    )
    scen = resolve_config("robust_mix")
    replay = _replay(seed_presets=(str(region),), seed_levels=5, min_levels=1)
    replay.seed_levels(scen, run_seed=3)
    assert len(replay.levels) == 5 and all(lv.score == 0.75 for lv in replay.levels.values())
    for level in replay.levels.values():
        values = level.draw[0]
        assert 2000.0 <= values["flow_vph_per_lane"] <= 2100.0
        assert 0.9 <= values["adversarial_share"] <= 1.0 and values["merge_zone_m"] == 60.0
    g = np.random.default_rng(0)
    cfg, tag = replay.draw(scen, 0, g)
    while tag >= 5:  # a fresh draw joins the buffer; replays pick the seeded levels
        cfg, tag = replay.draw(scen, 0, g)
    assert cfg.road.merge_zone_m == 60.0 and cfg.traffic.flow_vph_per_lane >= 2000.0
    again = _replay(seed_presets=(str(region),), seed_levels=5)
    again.seed_levels(scen, run_seed=3)
    assert [again.levels[i].draw for i in range(5)] == [replay.levels[i].draw for i in range(5)]
    with pytest.raises(ValueError, match=r"levels.seed_presets\[0\] = 'nope'"):
        load_train_config(
            "quick", **{"levels.replay_fraction": 0.5, "levels.seed_presets": ["nope"]}
        )
    with pytest.raises(ValueError, match="needs levels.replay_fraction > 0"):
        load_train_config("quick", **{"levels.seed_presets": [str(region)]})
