"""Prioritised replay of traffic conditions (levels) where the ego fails, as in PLR.

A scenario with `[sample]` gives every world a fresh draw of traffic (a level: the drawn values
of the `[sample]` keys) for each new road. With `[levels] replay_fraction > 0` a training run
(`marlmerge.training.train`) hands the core a `LevelReplay` (`TrafficCore(scenario_source=...)`):
each new road replays a level from its buffer with probability `replay_fraction`, else it is a
fresh draw that joins the buffer. Every finished ego scores its level: the level's failure rate
(collisions and truncations, `(failures + 1/2) / (episodes + 1)`). A level is replayed with the
probability of Jiang et al.'s Prioritized Level Replay (ICML 2021):

    P = (1 - staleness) * P_score + staleness * P_stale
    P_score ~ (1 / rank of its score) ** (1 / temperature)
    P_stale ~ draws since the level was last chosen

over the levels scored at least once; a full buffer drops its lowest-scored level (the oldest
among equals) for a fresh draw. With `score = "learnability"` the score is p (1 - p) instead,
p the level's failure rate shrunk towards the buffer's (`LevelsConfig.score`). Every choice is
drawn from the world's scenario stream, so a run is reproducible and resumes bit for bit
(`state_dict`); with `replay_fraction = 0` the draws are those of `[sample]` itself.

A level is a traffic condition: replayed, it runs on a new road of that traffic. With
`replay_roads = true` a level is one road, as PLR's levels are seeds: each fresh level also
draws a road seed, and the world's generators (all but its scenario stream) start from it
(`Streams.seed_road`), so a replayed level has the same vehicles on the road, the same
arrivals and the same ego departure as when it failed; only what the ego does differs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.config.training import LevelsConfig
from marlmerge.sim.streams import WorldDraw, draw_world_values, world_changes

SEED_KEY = 7
"""spawn_key root of the generators that draw the seeded levels (`LevelReplay.seed_levels`)."""


@dataclass
class Level:
    draw: WorldDraw
    episodes: int = 0
    failures: int = 0
    last_chosen: int = 0
    """The replay's draw count when the level was last chosen (or added)."""
    road: int | None = None
    """With `replay_roads`: the seed of the level's road (`Streams.seed_road`)."""

    @property
    def score(self) -> float:
        return (self.failures + 0.5) / (self.episodes + 1.0)


class LevelReplay:
    """The buffer of levels, their scores and the choice of each new road's level (see the
    module docstring); a `marlmerge.sim.streams.ScenarioSource`."""

    def __init__(self, cfg: LevelsConfig) -> None:
        self.cfg = cfg
        self.levels: dict[int, Level] = {}
        self.next_id = 0
        self.draws = 0

    # ---- the scenario source -----------------------------------------------------------------

    def draw(
        self, base: ScenarioConfig, world: int, g: np.random.Generator
    ) -> tuple[ScenarioConfig, int]:
        """The next road's traffic for a world and the level's id (its tag)."""
        self.draws += 1
        scored = [i for i, lv in self.levels.items() if lv.episodes > 0]
        replay = (
            self.cfg.replay_fraction > 0.0
            and len(scored) >= self.cfg.min_levels
            and g.uniform() < self.cfg.replay_fraction
        )
        if replay:
            tag = scored[int(g.choice(len(scored), p=self.probabilities(scored)))]
            level = self.levels[tag]
            level.last_chosen = self.draws
        else:
            tag, level = self._add(draw_world_values(base, g), self._road_seed(g))
        return base.replace(**world_changes(base, *level.draw)), tag

    def road(self, world: int, tag: int) -> int | None:
        """The seed of level `tag`'s road with `replay_roads`, else None (a fresh road)."""
        return self.levels[tag].road

    def _road_seed(self, g: np.random.Generator) -> int | None:
        return int(g.integers(2**63)) if self.cfg.replay_roads else None

    def probabilities(self, ids: list[int]) -> np.ndarray:
        """PLR's replay distribution over the levels `ids` (scored ones)."""
        scores = self.scores(ids)
        ranks = np.empty(len(ids))
        ranks[np.argsort(-scores, kind="stable")] = np.arange(1, len(ids) + 1)
        p_score = (1.0 / ranks) ** (1.0 / self.cfg.temperature)
        p_score /= p_score.sum()
        stale = np.array([self.draws - self.levels[i].last_chosen for i in ids], dtype=float)
        p_stale = stale / stale.sum() if stale.sum() > 0 else np.full(len(ids), 1.0 / len(ids))
        return (1.0 - self.cfg.staleness) * p_score + self.cfg.staleness * p_stale

    def scores(self, ids: list[int]) -> np.ndarray:
        """The levels' scores (`LevelsConfig.score`) [len(ids)]."""
        if self.cfg.score == "failure":
            return np.array([self.levels[i].score for i in ids])
        episodes = np.array([self.levels[i].episodes for i in ids], dtype=float)
        failures = np.array([self.levels[i].failures for i in ids], dtype=float)
        scored = [lv for lv in self.levels.values() if lv.episodes > 0]
        n = sum(lv.episodes for lv in scored)
        m = sum(lv.failures for lv in scored) / n if n else 0.5
        p = (failures + m) / (episodes + 1.0)
        return np.where(episodes > 0, p * (1.0 - p), 0.25)

    def _add(self, draw: WorldDraw, road: int | None) -> tuple[int, Level]:
        if len(self.levels) >= self.cfg.capacity:
            ids = list(self.levels)  # in the order added: the oldest first among equal scores
            del self.levels[ids[int(np.argmin(self.scores(ids)))]]
        tag, self.next_id = self.next_id, self.next_id + 1
        self.levels[tag] = Level(draw, last_chosen=self.draws, road=road)
        return tag, self.levels[tag]

    def seed_levels(self, base: ScenarioConfig, run_seed: int) -> None:
        """Fill the buffer with `seed_levels` levels drawn from each of `seed_presets`
        (`LevelsConfig`): each preset's `[sample]` ranges drawn in the world's order, its road
        where it differs from `base`'s; each starts with the score of one failed ego. The draws
        come from `SeedSequence(run_seed, spawn_key=(SEED_KEY, preset index))`."""
        from marlmerge.config.presets import resolve_config

        for j, name in enumerate(self.cfg.seed_presets):
            preset = resolve_config(name)
            g = np.random.default_rng(np.random.SeedSequence(run_seed, spawn_key=(SEED_KEY, j)))
            road = {
                key: getattr(preset.road, key)
                for key in ("ramp_length_m", "merge_zone_m")
                if getattr(preset.road, key) != getattr(base.road, key)
            }
            for _ in range(self.cfg.seed_levels):
                values, pure = draw_world_values(preset, g)
                values |= {k: v for k, v in road.items() if values.get(k) is None}
                base.replace(**world_changes(base, values, pure))  # a clear error now if invalid
                _, level = self._add((values, pure), self._road_seed(g))
                level.episodes, level.failures = 1, 1

    # ---- scores ------------------------------------------------------------------------------

    def update(self, tags: np.ndarray, failed: np.ndarray) -> None:
        """Finished egos: their levels' tags [n] and whether each failed [n]; levels dropped
        meanwhile are skipped."""
        for tag, fail in zip(tags.tolist(), failed.tolist(), strict=True):
            level = self.levels.get(int(tag))
            if level is not None:
                level.episodes += 1
                level.failures += int(fail)

    def summary(self) -> dict[str, float]:
        """Buffer size and the mean failure score of the buffer and of its top tenth."""
        scores = np.sort([lv.score for lv in self.levels.values() if lv.episodes > 0])[::-1]
        top = scores[: max(len(scores) // 10, 1)]
        return {
            "levels": len(self.levels),
            "scored": len(scores),
            "mean_score": float(scores.mean()) if len(scores) else 0.0,
            "top_tenth_score": float(top.mean()) if len(scores) else 0.0,
        }

    # ---- checkpoints -------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {
            "next_id": self.next_id,
            "draws": self.draws,
            "levels": [
                [i, lv.draw[0], lv.draw[1], lv.episodes, lv.failures, lv.last_chosen, lv.road]
                for i, lv in self.levels.items()
            ],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.next_id, self.draws = state["next_id"], state["draws"]
        self.levels = {
            int(i): Level((dict(values), pure), episodes, failures, last, *road)
            for i, values, pure, episodes, failures, last, *road in state["levels"]
        }  # checkpoints written before `replay_roads` have no road


class SeedLevels:
    """The scenario source of S seeds' worlds in one env (`marlmerge train --seeds`): world
    `j * B + i` draws from seed j's own `LevelReplay` as world i of that seed's single run."""

    def __init__(self, replays: list[LevelReplay], worlds_per_seed: int) -> None:
        self.replays, self.b = replays, worlds_per_seed

    def draw(
        self, base: ScenarioConfig, world: int, g: np.random.Generator
    ) -> tuple[ScenarioConfig, int]:
        return self.replays[world // self.b].draw(base, world % self.b, g)

    def road(self, world: int, tag: int) -> int | None:
        return self.replays[world // self.b].road(world % self.b, tag)
