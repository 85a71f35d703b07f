"""Gymnasium views of the core: the ramp vehicle as a single agent.

    import gymnasium, marlmerge
    env = gymnasium.make("marlmerge/RampMerge-v2", render_mode="rgb_array")   # config="adversarial"
    envs = gymnasium.make_vec("marlmerge/RampMerge-v2", num_envs=64,
                              vectorization_mode="vector_entry_point")

`RampMergeEnv` (one world) and `RampMergeVectorEnv` (B worlds of one batched core, not B copies
of the single env) share one implementation, `EgoWorlds`, over `TrafficCore.rollout`.

Spaces: observation Box(F) float32 (F = 7, the paper's state, or 16 with `ego.observation =
"extended"`; `marlmerge.sim.observation`), action Box(1) in the ego's bounds (m/s^2, held for
`sim.action_repeat` simulator steps); with `ego.join = "chosen"` Box(2): (acceleration, join),
join in [-1, 1] (`marlmerge.sim.action`), and the observation ends with `on_ramp`.
Reward: the sum of the named terms (`marlmerge.sim.reward.EGO_TERMS`); `info` holds each as
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

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np

from marlmerge.config import ScenarioConfig, check_count
from marlmerge.config.presets import resolve_config
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_SUCCESS, OUTCOME_TRUNCATED, TrafficCore
from marlmerge.sim.action import action_size, as_actions
from marlmerge.sim.reward import EGO_TERMS, total_reward
from marlmerge.sim.streams import check_seed, is_seed
from marlmerge.views.single_ego import EgoWorlds, HighwayPolicy, ego_infos, ego_spaces


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
        self.observation_space, self.action_space = ego_spaces(self.cfg)
        self.metadata = dict(self.metadata, render_fps=_env_step_fps(self.cfg))
        self._worlds: EgoWorlds | None = None
        self._done = False
        """The episode ended: `step` refuses until `reset`."""
        self._viewer = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        check_seed(seed)
        super().reset(seed=seed)
        self._done = False
        if self._worlds is None:
            self._worlds = EgoWorlds(self.cfg, 1, self.highway_policy, seed)
        elif seed is not None:
            self._worlds.core.reset(seed=seed)
        else:
            self._worlds.core.next_ego(np.ones(1, dtype=bool))
        self._worlds.new_rosters(np.ones(1, dtype=bool))
        obs = self._worlds.observe()[0]
        zeros = np.zeros((1, len(EGO_TERMS)))
        infos = ego_infos(zeros, np.zeros(1), np.zeros(1), self._worlds.interventions())
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
        obs, terms, outcome, t = self._worlds.step(
            as_actions(action, (1, action_size(self.cfg)), shown=self.action_space.shape)
        )
        o = int(outcome[0])
        terminated = o in (OUTCOME_SUCCESS, OUTCOME_COLLISION)
        truncated = o == OUTCOME_TRUNCATED
        self._done = terminated or truncated
        infos = ego_infos(terms, outcome, t, self._worlds.interventions())
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
        from marlmerge.views.render import render_scene

        frame = render_scene(self.core, world=0)
        if self.render_mode == "human":
            self._show(frame)
            return None
        return frame

    def _render_human(self) -> None:
        if self.render_mode == "human":
            self.render()

    def _show(self, frame: np.ndarray) -> None:
        from marlmerge.views.render import Window

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
        self.num_envs = check_count("num_envs", num_envs)
        self.cfg = resolve_config(config, **(overrides or {}))
        self.render_mode = render_mode
        self.highway_policy = highway_policy
        self.single_observation_space, self.single_action_space = ego_spaces(self.cfg)
        self.observation_space = gymnasium.vector.utils.batch_space(
            self.single_observation_space, self.num_envs
        )
        self.action_space = gymnasium.vector.utils.batch_space(
            self.single_action_space, self.num_envs
        )
        self.metadata = dict(self.metadata, render_fps=_env_step_fps(self.cfg))
        self._worlds: EgoWorlds | None = None
        self._done = np.zeros(self.num_envs, dtype=bool)

    def reset(self, *, seed: int | Sequence[int] | None = None, options: dict | None = None):
        seeds = None
        check_seed(seed, self.num_envs)
        if seed is not None:
            seeds = [int(seed) + i for i in range(self.num_envs)] if is_seed(seed) else seed
        if self._worlds is None:
            self._worlds = EgoWorlds(self.cfg, self.num_envs, self.highway_policy, seeds)
        elif seeds is not None:
            self._worlds.core.reset(seed=seeds)
        else:
            self._worlds.core.next_ego(np.ones(self.num_envs, dtype=bool))
        self._worlds.new_rosters(np.ones(self.num_envs, dtype=bool))
        self._done[:] = False
        b = self.num_envs
        return self._worlds.observe(), ego_infos(
            np.zeros((b, len(EGO_TERMS))), np.zeros(b), np.zeros(b), self._worlds.interventions()
        )

    def step(self, actions):
        if self._worlds is None:
            raise RuntimeError("step() before reset()")
        a = as_actions(actions, (self.num_envs, action_size(self.cfg)))
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
        infos = ego_infos(terms, outcome, t, self._worlds.interventions())
        return obs, total_reward(terms), terminated, truncated, infos

    @property
    def core(self) -> TrafficCore:
        if self._worlds is None:
            raise RuntimeError("the env has no road before reset()")
        return self._worlds.core

    def render(self) -> tuple[np.ndarray, ...] | None:
        if self.render_mode is None or self._worlds is None:
            return None
        from marlmerge.views.render import render_scene

        return tuple(render_scene(self.core, world=i) for i in range(self.num_envs))
