"""Gymnasium views of the core: the ramp vehicle as a single agent.

    import gymnasium, marlmerge
    env = gymnasium.make("marlmerge/RampMerge-v1", render_mode="rgb_array")   # config="adversarial"
    envs = gymnasium.make_vec("marlmerge/RampMerge-v1", num_envs=64,
                              vectorization_mode="vector_entry_point")

`RampMergeEnv` (one world) and `RampMergeVectorEnv` (B worlds of one batched core, not B copies
of the single env) share one implementation, `_EgoWorlds`, over `TrafficCore.rollout`.

Spaces: observation Box(F) float32 (F = 7, the paper's state, or 16 with `ego.observation =
"extended"`; `marlmerge.spec.observation`), action Box(1) in the ego's bounds (m/s^2, held for
`sim.action_repeat` simulator steps).
Reward: the sum of the named terms (`marlmerge.spec.reward.EGO_TERMS`); `info` holds each as
`reward_<term>`, and `outcome` (0 running, 1 success, 2 collision, 3 truncated), `ego_time_s`,
and with `ego.safety_filter` `filter_interventions` (the filter's overrides in the episode).
Episode: one ramp vehicle; terminated on success or collision, truncated when it stalls or runs
out of time; a `step` after that raises `RuntimeError` until `reset`. `reset(seed=s)` builds a
fresh road in steady flow, the same road for the same seed whatever came before; `reset()` sends
the next ramp vehicle into the same flowing traffic.

Mainline traffic is scripted, or given `highway_policy` (observations [B, K, 12] -> accelerations
[B, K, 1], e.g. `marlmerge.ScriptedHighwayPolicy` or a loaded learned policy), the policy drives
the K = `sim.n_highway_agents` highway agents of each merge.

The vector env autoresets as Gymnasium's default (`AutoresetMode.NEXT_STEP`): the step after a
world's episode ended resets that world (the next ramp vehicle), ignoring its action and
returning reward 0. `reset(seed=s)` seeds world i with s + i, so world i is the single env reset
with seed s + i.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from marlmerge.config import ScenarioConfig
from marlmerge.presets import resolve_config
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_SUCCESS, OUTCOME_TRUNCATED, TrafficCore
from marlmerge.sim.streams import check_seed, is_seed
from marlmerge.spec.action import as_actions
from marlmerge.spec.observation import HIGHWAY_FEATURES, ego_obs_size
from marlmerge.spec.reward import EGO_TERMS, total_reward

ENV_ID = "marlmerge/RampMerge-v1"
HighwayPolicy = Callable[[np.ndarray], np.ndarray]
"""highway observations [B, K, 12] -> accelerations [B, K, 1] (m/s^2)."""


class _EgoWorlds:
    """B worlds of one core with their ego as the agent; the highway agents (if a highway
    policy drives them) re-drawn at every departure."""

    def __init__(
        self,
        cfg: ScenarioConfig,
        num_worlds: int,
        highway_policy: HighwayPolicy | None,
        seed: int | Sequence[int] | None = None,
    ):
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
        """action [B] (in the worlds of the mask `worlds`, all if None) -> (obs [B, F], terms
        [B, len(EGO_TERMS)], outcome [B], ego_time_s [B])."""
        cmd = None
        if self.highway_policy is not None:
            act = np.asarray(self.highway_policy(self.hw_obs), dtype=np.float64)
            cmd = np.where(self.roster.mask, act.reshape(self.b, self.k), np.nan)
        out = self.core.rollout(action, roster=self.roster, roster_accel=cmd, worlds=worlds)
        self.hw_obs = out.hw_obs
        return out.ego_obs, out.ego_terms, out.ego_outcome, self.core.state.ego_time_s.copy()


def _spaces(cfg: ScenarioConfig) -> tuple[spaces.Box, spaces.Box]:
    lo, hi = cfg.ego.accel_bounds_mps2
    return (
        spaces.Box(-np.inf, np.inf, (ego_obs_size(cfg),), np.float32),
        spaces.Box(np.float32(lo), np.float32(hi), (1,), np.float32),
    )


def _infos(
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


class RampMergeEnv(gymnasium.Env):
    """The ramp vehicle of one world as a Gymnasium env (see the module docstring)."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 10}

    def __init__(
        self,
        config: ScenarioConfig | str | Path | None = None,
        render_mode: str | None = None,
        highway_policy: HighwayPolicy | None = None,
        overrides: dict[str, Any] | None = None,
    ):
        if render_mode not in (None, *self.metadata["render_modes"]):
            raise ValueError(
                f"render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}"
            )
        self.cfg = resolve_config(config, **(overrides or {}))
        self.render_mode = render_mode
        self.highway_policy = highway_policy
        self.observation_space, self.action_space = _spaces(self.cfg)
        self.metadata = dict(self.metadata, render_fps=_env_step_fps(self.cfg))
        self._worlds: _EgoWorlds | None = None
        self._done = False
        """The episode ended: `step` refuses until `reset`."""
        self._viewer = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        check_seed(seed)
        super().reset(seed=seed)
        self._done = False
        if self._worlds is None:
            self._worlds = _EgoWorlds(self.cfg, 1, self.highway_policy, seed)
        elif seed is not None:
            self._worlds.core.reset(seed=seed)
        else:
            self._worlds.core.next_ego(np.ones(1, dtype=bool))
        self._worlds.new_rosters(np.ones(1, dtype=bool))
        obs = self._worlds.observe()[0]
        zeros = np.zeros((1, len(EGO_TERMS)))
        infos = _infos(zeros, np.zeros(1), np.zeros(1), self._worlds.interventions())
        info = {k: v[0] for k, v in infos.items()}
        self._render_human()
        return obs, info

    def step(self, action):
        if self._worlds is None:
            raise RuntimeError("step() before reset()")
        if self._done:
            raise RuntimeError(
                "step() after the episode ended (terminated or truncated): call reset() first"
            )
        obs, terms, outcome, t = self._worlds.step(as_actions(action, (1,)))
        o = int(outcome[0])
        terminated = o in (OUTCOME_SUCCESS, OUTCOME_COLLISION)
        truncated = o == OUTCOME_TRUNCATED
        self._done = terminated or truncated
        infos = _infos(terms, outcome, t, self._worlds.interventions())
        info = {k: v[0] for k, v in infos.items()}
        self._render_human()
        return obs[0], float(total_reward(terms[0])), terminated, truncated, info

    @property
    def core(self) -> TrafficCore:
        if self._worlds is None:
            raise RuntimeError("the env has no road before reset()")
        return self._worlds.core

    def render(self) -> np.ndarray | None:
        if self.render_mode is None or self._worlds is None:
            return None
        from marlmerge.render import render_scene

        frame = render_scene(self.core, world=0)
        if self.render_mode == "human":
            self._show(frame)
            return None
        return frame

    def _render_human(self) -> None:
        if self.render_mode == "human":
            self.render()

    def _show(self, frame: np.ndarray) -> None:
        from marlmerge.render import Window

        if self._viewer is None:
            self._viewer = Window(f"marlmerge - {self.cfg.name}", self.metadata["render_fps"])
        self._viewer.show(frame)

    def close(self) -> None:
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None


def _env_step_fps(cfg: ScenarioConfig) -> int:
    return max(1, round(1.0 / (cfg.sim.dt_s * cfg.sim.action_repeat)))


class RampMergeVectorEnv(gymnasium.vector.VectorEnv):
    """`num_envs` worlds of one batched core as a Gymnasium vector env (next-step autoreset)."""

    metadata = {
        "render_modes": ["rgb_array"],
        "autoreset_mode": gymnasium.vector.AutoresetMode.NEXT_STEP,
    }

    def __init__(
        self,
        num_envs: int = 16,
        config: ScenarioConfig | str | Path | None = None,
        render_mode: str | None = None,
        highway_policy: HighwayPolicy | None = None,
        overrides: dict[str, Any] | None = None,
    ):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.cfg = resolve_config(config, **(overrides or {}))
        self.num_envs = int(num_envs)
        self.render_mode = render_mode
        self.highway_policy = highway_policy
        self.single_observation_space, self.single_action_space = _spaces(self.cfg)
        self.observation_space = gymnasium.vector.utils.batch_space(
            self.single_observation_space, self.num_envs
        )
        self.action_space = gymnasium.vector.utils.batch_space(
            self.single_action_space, self.num_envs
        )
        self.metadata = dict(self.metadata, render_fps=_env_step_fps(self.cfg))
        self._worlds: _EgoWorlds | None = None
        self._done = np.zeros(self.num_envs, dtype=bool)

    def reset(self, *, seed: int | Sequence[int] | None = None, options: dict | None = None):
        seeds = None
        check_seed(seed, self.num_envs)
        if seed is not None:
            seeds = [int(seed) + i for i in range(self.num_envs)] if is_seed(seed) else seed
        if self._worlds is None:
            self._worlds = _EgoWorlds(self.cfg, self.num_envs, self.highway_policy, seeds)
        elif seeds is not None:
            self._worlds.core.reset(seed=seeds)
        else:
            self._worlds.core.next_ego(np.ones(self.num_envs, dtype=bool))
        self._worlds.new_rosters(np.ones(self.num_envs, dtype=bool))
        self._done[:] = False
        b = self.num_envs
        return self._worlds.observe(), _infos(
            np.zeros((b, len(EGO_TERMS))), np.zeros(b), np.zeros(b), self._worlds.interventions()
        )

    def step(self, actions):
        if self._worlds is None:
            raise RuntimeError("step() before reset()")
        a = as_actions(actions, (self.num_envs, 1))
        restart = self._done.copy()
        if restart.any():  # next-step autoreset: these worlds send their next ramp vehicle and
            self._worlds.core.next_ego(restart)  # stand still this step (reward 0, not done)
            self._worlds.new_rosters(restart)
            obs, terms, outcome, t = self._worlds.step(a, worlds=~restart)
        else:
            obs, terms, outcome, t = self._worlds.step(a)
        terminated = (outcome == OUTCOME_SUCCESS) | (outcome == OUTCOME_COLLISION)
        truncated = outcome == OUTCOME_TRUNCATED
        self._done = terminated | truncated
        infos = _infos(terms, outcome, t, self._worlds.interventions())
        return obs, total_reward(terms), terminated, truncated, infos

    @property
    def core(self) -> TrafficCore:
        if self._worlds is None:
            raise RuntimeError("the env has no road before reset()")
        return self._worlds.core

    def render(self) -> tuple[np.ndarray, ...] | None:
        if self.render_mode is None or self._worlds is None:
            return None
        from marlmerge.render import render_scene

        return tuple(render_scene(self.core, world=i) for i in range(self.num_envs))


def register() -> None:
    """Register `marlmerge/RampMerge-v1` with Gymnasium (done on `import marlmerge`)."""
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(
            id=ENV_ID,
            entry_point="marlmerge.gym_env:RampMergeEnv",
            vector_entry_point="marlmerge.gym_env:RampMergeVectorEnv",
        )
