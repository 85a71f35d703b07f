"""What the single-ego views share (Gymnasium's env and vector env, the SB3 VecEnv): B worlds of
one core with the ramp vehicle as the agent (`EgoWorlds`), its spaces and its per-world infos."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from gymnasium import spaces

from marlmerge.config import ScenarioConfig, require_ego
from marlmerge.sim import TrafficCore
from marlmerge.sim.action import action_bounds, split_actions
from marlmerge.sim.observation import HIGHWAY_FEATURES, ego_obs_size
from marlmerge.sim.reward import EGO_TERMS

HighwayPolicy = Callable[[np.ndarray], np.ndarray]
"""highway observations [B, K, 12] -> accelerations [B, K, 1] (m/s^2)."""


class EgoWorlds:
    """B worlds of one core with their ego as the agent; the highway agents (if a highway
    policy drives them) re-drawn at every departure."""

    def __init__(
        self,
        cfg: ScenarioConfig,
        num_worlds: int,
        highway_policy: HighwayPolicy | None,
        seed: int | Sequence[int] | None = None,
    ):
        require_ego(cfg, "the single-ego view")
        self.cfg = cfg
        self.b = num_worlds
        self.highway_policy = highway_policy
        self.k = cfg.sim.n_highway_agents if highway_policy is not None else 0
        self.core = TrafficCore(cfg, batch_size=num_worlds, seed=seed)
        self.roster = self.core.make_roster(self.core.pick_roster(self.k))
        self.hw_obs = np.zeros((num_worlds, self.k, len(HIGHWAY_FEATURES)), dtype=np.float32)

    def new_rosters(self, rows: np.ndarray) -> None:
        fresh = self.core.make_roster(self.core.pick_roster(self.k))
        self.roster.rows[:, rows] = fresh.rows[:, rows]

    def observe(self) -> np.ndarray:
        ego_obs, self.hw_obs = self.core.observe(self.roster)
        return ego_obs

    def interventions(self) -> np.ndarray | None:
        """[B] the safety filter's overrides in each world's episode; None with the filter off."""
        if not self.cfg.ego.safety_filter:
            return None
        return self.core.state.filter_interventions.copy()

    def step(
        self, action: np.ndarray, worlds: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """action [B] or, with a join choice, [B, 2] (`marlmerge.sim.action`; in the worlds of
        the mask `worlds`, all if None) -> (obs [B, F], terms [B, len(EGO_TERMS)], outcome [B],
        ego_time_s [B])."""
        cmd = None
        if self.highway_policy is not None:
            act = np.asarray(self.highway_policy(self.hw_obs), dtype=np.float64)
            cmd = np.where(self.roster.mask, act.reshape(self.b, self.k), np.nan)
        accel, join = split_actions(action)
        out = self.core.rollout(
            accel, roster=self.roster, roster_accel=cmd, worlds=worlds, ego_join=join
        )
        self.hw_obs = out.hw_obs
        return out.ego_obs, out.ego_terms, out.ego_outcome, self.core.state.ego_time_s.copy()


def ego_spaces(cfg: ScenarioConfig) -> tuple[spaces.Box, spaces.Box]:
    """The ego's observation Box(F) and action Box(1) (m/s^2, within its bounds), Box(2) with
    `ego.join = "chosen"` (acceleration, join; `marlmerge.sim.action`)."""
    return (
        spaces.Box(-np.inf, np.inf, (ego_obs_size(cfg),), np.float32),
        spaces.Box(*action_bounds(cfg), dtype=np.float32),
    )


def ego_infos(
    terms: np.ndarray,
    outcome: np.ndarray,
    time_s: np.ndarray,
    interventions: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Per-world infos [B] each; `filter_interventions` only when given (the filter is on)."""
    info = {f"reward_{t}": terms[:, i] for i, t in enumerate(EGO_TERMS)}
    info["outcome"] = outcome.astype(np.int64)
    info["ego_time_s"] = time_s
    if interventions is not None:
        info["filter_interventions"] = interventions.astype(np.int64)
    return info
