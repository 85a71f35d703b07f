"""A Stable-Baselines3 `VecEnv` over the batched core (the `[sb3]` extra).

    from stable_baselines3 import SAC
    from marlmerge.views.sb3_env import MergeVecEnv
    model = SAC("MlpPolicy", MergeVecEnv(num_envs=8, seed=0)).learn(100_000)

`num_envs` worlds of one `TrafficCore`, each with its ramp vehicle as the agent, as in
`marlmerge.views.gym_env` (same spaces, reward, episode; mainline traffic scripted, or driven by a
`highway_policy`). SB3's conventions: a world whose episode ends is reset in the same step (the
next ramp vehicle departs into the same traffic), its last observation is in
`info["terminal_observation"]`, and `info["TimeLimit.truncated"]` tells a truncation (stalled or
out of time) from a termination (success or collision). `info` also holds the named reward terms
(`reward_<term>`) and the `outcome` of the step.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from marlmerge.config import ScenarioConfig, check_count
from marlmerge.config.presets import resolve_config
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_SUCCESS, OUTCOME_TRUNCATED
from marlmerge.sim.action import action_size, as_actions
from marlmerge.views.single_ego import EgoWorlds, HighwayPolicy, ego_infos, ego_spaces


class MergeVecEnv(VecEnv):
    """`num_envs` ramp-merge worlds as an SB3 VecEnv (see the module docstring)."""

    def __init__(
        self,
        num_envs: int = 8,
        config: ScenarioConfig | str | Path | None = None,
        seed: int | None = 0,
        highway_policy: HighwayPolicy | None = None,
        overrides: dict[str, Any] | None = None,
    ):
        num_envs = check_count("num_envs", num_envs)
        self.cfg = resolve_config(config, **(overrides or {}))
        obs_space, act_space = ego_spaces(self.cfg)
        super().__init__(num_envs, obs_space, act_space)
        self._seed = seed
        self._highway_policy = highway_policy
        self._worlds: EgoWorlds | None = None
        self._actions = np.zeros(num_envs)

    def reset(self) -> np.ndarray:
        seeds = None if self._seed is None else [self._seed + i for i in range(self.num_envs)]
        if self._worlds is None:
            self._worlds = EgoWorlds(self.cfg, self.num_envs, self._highway_policy, seeds)
        else:
            self._worlds.core.reset(seed=seeds)
        self._worlds.new_rosters(np.ones(self.num_envs, dtype=bool))
        self._seed = None  # later resets go on from the generators' state
        return self._worlds.observe()

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = as_actions(actions, (self.num_envs, action_size(self.cfg)))

    def step_wait(self):
        if self._worlds is None:
            raise RuntimeError("step() before reset()")
        obs, terms, outcome, t = self._worlds.step(self._actions)
        terminated = (outcome == OUTCOME_SUCCESS) | (outcome == OUTCOME_COLLISION)
        truncated = outcome == OUTCOME_TRUNCATED
        done = terminated | truncated
        flat = ego_infos(terms, outcome, t, self._worlds.interventions())
        infos: list[dict[str, Any]] = [
            {k: v[i] for k, v in flat.items()} for i in range(self.num_envs)
        ]
        if done.any():  # same-step reset, as SB3 expects
            for i in np.flatnonzero(done):
                infos[i]["terminal_observation"] = obs[i].copy()
                infos[i]["TimeLimit.truncated"] = bool(truncated[i])
            self._worlds.core.next_ego(done)
            self._worlds.new_rosters(done)
            obs = np.where(done[:, None], self._worlds.observe(), obs)
        return obs, terms.sum(axis=1).astype(np.float32), done, infos

    def close(self) -> None:
        self._worlds = None

    def seed(self, seed: int | None = None) -> Sequence[None | int]:
        self._seed = seed
        return [None if seed is None else seed + i for i in range(self.num_envs)]

    # SB3's attribute plumbing: every world shares the same config
    def get_attr(self, attr_name: str, indices=None) -> list[Any]:  # noqa: ANN001
        value = getattr(self, attr_name) if attr_name != "render_mode" else None
        return [value] * len(self._indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:  # noqa: ANN001
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *args: Any, indices=None, **kwargs: Any) -> list[Any]:  # noqa: ANN001
        return [getattr(self, method_name)(*args, **kwargs) for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class: type, indices=None) -> list[bool]:  # noqa: ANN001
        return [False] * len(self._indices(indices))

    def _indices(self, indices) -> list[int]:  # noqa: ANN001
        if indices is None:
            return list(range(self.num_envs))
        return [indices] if isinstance(indices, int) else list(indices)
