"""Ramp merge as a PettingZoo `ParallelEnv`: a thin single-world view over `TrafficCore`.

Agents
    `ramp_0` the ramp vehicle (the ego), and `highway_0` ... `highway_{K-1}`: the mainline
    vehicles that take part in this episode's merge. The roster is fixed at `reset`: the right-lane
    vehicles whose arrival time at the merge point (at current speeds) is closest to the ego's,
    nearest in time first (fewer than K if the lane holds fewer). All other vehicles are background
    traffic driven by their scripted profile. With `control="ego"` only `ramp_0` is an agent and
    every mainline vehicle is scripted (the paper's single-ego setting).

Actions
    Box(1,) longitudinal acceleration in m/s^2, held for `sim.action_repeat` simulator steps.
    `ramp_0`: [-4.5, 2.5] by default, and with `ego.join = "chosen"` Box(2,): (acceleration,
    join), join in [-1, 1], > 0 changing into the right lane inside the merge zone
    (`marlmerge.sim.action`); `highway_*`: `sim.highway_agent_accel_bounds_mps2`
    (the same by default; scripted background traffic keeps the vehicle limits).
    Out-of-range values are clipped; NaN, infinite, non-numeric or wrongly shaped actions, agents
    that are not in `possible_agents` and missing actions of live agents raise `ValueError` naming
    the agent and the value (`marlmerge.sim.action`). Actions for possible agents that are not
    live (done, or not in this episode's roster) are checked the same way, then ignored, as
    torchrl's PettingZoo wrapper sends an action for every agent of a group. Controlled highway
    agents keep their lane.

Observations
    Box float32, scaled; layouts in `marlmerge.sim.observation` (the ego's by `ego.observation`:
    `EGO_FEATURES` or `EGO_EXTENDED_FEATURES`; `HIGHWAY_FEATURES`). Imperfect sensing
    (`[sensing]`) changes what `ramp_0` sees, never the rewards.

Rewards
    Sums over the env step of the per-simulator-step terms of `marlmerge.sim.reward`: the ego's
    `EGO_TERMS`; a highway agent's `LEARNED_HIGHWAY_TERMS` (its own driving terms plus the
    interaction terms of `InteractionConfig`, adversarial by default, `interaction.sign = -1`
    for cooperative agents).

Infos
    Flat and numeric, with the same keys at `reset` and at every step (so torchrl's PettingZoo
    wrapper can carry them): `reward_<term>` for each named reward term (`reward_terms(info)`
    collects them), and for `ramp_0` also `outcome` (0 running, 1 success, 2 collision,
    3 truncated; names in `OUTCOME_NAMES`), `ego_time_s`, `ego_x_m`, `vehicle_id` and, with
    `ego.safety_filter`, `filter_interventions` (simulator steps of the episode whose command the
    safety filter overrode); for highway agents `vehicle_id` and `profile` (a `Profile` code).

Episode end
    The episode is the ego's merge. `ramp_0` terminates on success or collision and is truncated
    when stalled or out of time; at that moment every highway agent is truncated (the road goes on).
    A highway agent that leaves the road downstream terminates. `reset()` without a seed sends the
    next ramp vehicle into the same flowing traffic (`sim.continue_traffic`); `reset(seed=...)`
    builds a fresh road in steady flow. `max_cycles` truncates every agent after that many env
    steps of an episode (PettingZoo's convention).

Factories
    `parallel_env(...)` (this ParallelEnv) and `env(...)` / `raw_env(...)` (the AEC form,
    `parallel_to_aec`), in PettingZoo's convention; `render_mode="human"` shows a window (needs
    pygame: the `[video]` extra).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import AECEnv, ParallelEnv

from marlmerge.config import ScenarioConfig, check_count, require_ego
from marlmerge.config.presets import find_preset, resolve_config  # noqa: F401  (their home: presets)
from marlmerge.sim import EGO, OUTCOME_COLLISION, OUTCOME_NONE, OUTCOME_SUCCESS, TrafficCore
from marlmerge.sim.action import action_bounds, action_size, agent_actions, check_can_step
from marlmerge.sim.observation import HIGHWAY_FEATURES, ego_obs_size
from marlmerge.sim.reward import EGO_TERMS, LEARNED_HIGHWAY_TERMS, total_reward
from marlmerge.sim.streams import check_seed
from marlmerge.views.aec import checked_aec

EGO_AGENT = "ramp_0"
ENV_NAME = "marlmerge_ramp_v2"


def reward_terms(info: dict[str, Any]) -> dict[str, float]:
    """The named reward terms of one agent's info: {"acceleration": ..., "gap_front": ..., ...}."""
    return {k[len("reward_") :]: float(v) for k, v in info.items() if k.startswith("reward_")}


class RampMergeParallelEnv(ParallelEnv):
    metadata = {
        "name": ENV_NAME,
        "render_modes": ["rgb_array", "human"],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(
        self,
        config: ScenarioConfig | str | Path | None = None,
        render_mode: str | None = None,
        control: str = "all",
        overrides: dict[str, Any] | None = None,
        max_cycles: int | None = None,
    ):
        if control not in ("all", "ego"):
            raise ValueError(f"control must be 'all' or 'ego', got {control!r}")
        if render_mode not in (None, "rgb_array", "human"):
            raise ValueError(
                f"render_mode must be None, 'rgb_array' or 'human', got {render_mode!r}"
            )
        if max_cycles is not None:
            check_count("max_cycles", max_cycles)
        self.cfg = resolve_config(config, **(overrides or {}))
        require_ego(self.cfg, "RampMergeParallelEnv")
        self.render_mode = render_mode
        self.control = control
        self.max_cycles = max_cycles
        self._cycles = 0
        self._viewer = None
        n_hw = self.cfg.sim.n_highway_agents if control == "all" else 0
        self.possible_agents = [EGO_AGENT] + [f"highway_{i}" for i in range(n_hw)]
        self.agents: list[str] = []
        hw_lo, hw_hi = self.cfg.sim.highway_agent_accel_bounds_mps2
        self._action_spaces = {EGO_AGENT: spaces.Box(*action_bounds(self.cfg), dtype=np.float32)}
        self._observation_spaces = {
            EGO_AGENT: spaces.Box(-np.inf, np.inf, (ego_obs_size(self.cfg),), np.float32)
        }
        for a in self.possible_agents[1:]:
            self._action_spaces[a] = spaces.Box(hw_lo, hw_hi, (1,), np.float32)
            self._observation_spaces[a] = spaces.Box(
                -np.inf, np.inf, (len(HIGHWAY_FEATURES),), np.float32
            )
        self.core: TrafficCore | None = None
        self._slots: dict[str, int] = {}
        self._ids: dict[str, int] = {}
        self._profiles: dict[str, int] = {}
        self._column: dict[str, int] = {}
        self.metadata = dict(
            self.metadata, render_fps=round(1.0 / (self.cfg.sim.dt_s * self.cfg.sim.action_repeat))
        )

    # PettingZoo asks for the same space object on every call
    def observation_space(self, agent: str) -> spaces.Box:
        return self._observation_spaces[self._check_agent(agent)]

    def action_space(self, agent: str) -> spaces.Box:
        return self._action_spaces[self._check_agent(agent)]

    def _check_agent(self, agent: str) -> str:
        if agent not in self._action_spaces:
            raise ValueError(f"unknown agent {agent!r} (possible agents: {self.possible_agents})")
        return agent

    # ------------------------------------------------------------------ reset
    def reset(self, seed: int | None = None, options: dict | None = None):
        check_seed(seed)
        if self.core is None:
            self.core = TrafficCore(self.cfg, batch_size=1, seed=seed)
        elif seed is not None:
            self.core.reset(seed=seed)
        elif self.cfg.sim.continue_traffic:
            self.core.next_ego(np.ones(1, dtype=bool))
        else:
            self.core.reset()
        self._pick_roster()
        self._cycles = 0
        self.agents = [EGO_AGENT] + list(self._slots)
        ego_obs, hw_obs = self.core.observe(self._roster)
        obs = self._observations(self.agents, ego_obs, hw_obs)
        infos = {EGO_AGENT: self._ego_info(dict.fromkeys(EGO_TERMS, 0.0))}
        for a in self._slots:
            infos[a] = self._highway_info(a, dict.fromkeys(LEARNED_HIGHWAY_TERMS, 0.0))
        return obs, infos

    def _ego_info(self, terms: dict[str, float]) -> dict[str, float | int]:
        st = self.core.state  # type: ignore[union-attr]
        info: dict[str, float | int] = {f"reward_{k}": terms[k] for k in EGO_TERMS}
        info["outcome"] = int(st.ego_outcome[0])
        info["ego_time_s"] = float(st.ego_time_s[0])
        info["ego_x_m"] = float(st.x_m[0, EGO])
        info["vehicle_id"] = int(st.vehicle_id[0, EGO])
        if self.cfg.ego.safety_filter:
            info["filter_interventions"] = int(st.filter_interventions[0])
        return info

    def _highway_info(self, agent: str, terms: dict[str, float]) -> dict[str, float | int]:
        info: dict[str, float | int] = {f"reward_{k}": terms[k] for k in LEARNED_HIGHWAY_TERMS}
        info["vehicle_id"] = self._ids[agent]
        info["profile"] = self._profiles[agent]
        return info

    def _pick_roster(self) -> None:
        core = self.core
        assert core is not None
        k = len(self.possible_agents) - 1
        self._roster = core.make_roster(core.pick_roster(k))
        slots, ids = self._roster.slots[0], self._roster.ids[0]
        chosen = [j for j in range(k) if slots[j] >= 0]
        self._slots = {f"highway_{j}": int(slots[j]) for j in chosen}
        self._ids = {f"highway_{j}": int(ids[j]) for j in chosen}
        profile = core.state.profile[0]
        self._profiles = {a: int(profile[s]) for a, s in self._slots.items()}
        self._column = {a: j for a, j in zip(self._slots, chosen, strict=True)}

    # ------------------------------------------------------------------ step
    @property
    def action_sizes(self) -> dict[str, int]:
        """Numbers per action of the agents that take more than one: the ego's (acceleration,
        join) with a join choice."""
        return {EGO_AGENT: action_size(self.cfg)}

    def _parse_actions(self, actions: dict[str, Any]) -> dict[str, np.ndarray]:
        return agent_actions(actions, self.possible_agents, self.agents, self.action_sizes)

    def step(self, actions: dict[str, Any]):
        check_can_step(self.agents, started=self.core is not None)
        core = self.core
        assert core is not None
        acts = self._parse_actions(actions)
        hw_agents = [a for a in self.agents if a != EGO_AGENT]
        roster_cmd = None
        if self._roster.n_agents:
            roster_cmd = np.full((1, self._roster.n_agents), np.nan)
            for a in hw_agents:
                roster_cmd[0, self._column[a]] = acts[a][0]
        ego = acts[EGO_AGENT]
        out = core.rollout(
            ego[:1],
            roster=self._roster,
            roster_accel=roster_cmd,
            ego_join=ego[1:] if ego.size > 1 else None,
        )
        outcome = int(out.ego_outcome[0])
        ego_terms = {t: float(out.ego_terms[0, i]) for i, t in enumerate(EGO_TERMS)}
        hw_terms = {
            a: {
                t: float(out.hw_terms[0, self._column[a], i])
                for i, t in enumerate(LEARNED_HIGHWAY_TERMS)
            }
            for a in hw_agents
        }
        gone = {a for a in hw_agents if out.left_road[0, self._column[a]]}

        agents = list(self.agents)
        obs = self._observations(agents, out.ego_obs, out.hw_obs)
        rewards = {EGO_AGENT: float(total_reward(out.ego_terms[0]))}
        rewards.update({a: float(sum(t.values())) for a, t in hw_terms.items()})
        ego_done = outcome != OUTCOME_NONE
        terminations = {a: False for a in agents}
        truncations = {a: False for a in agents}
        terminations[EGO_AGENT] = outcome in (OUTCOME_SUCCESS, OUTCOME_COLLISION)
        truncations[EGO_AGENT] = ego_done and not terminations[EGO_AGENT]
        for a in hw_agents:
            if a in gone:
                terminations[a] = True
            elif ego_done:
                truncations[a] = True
        infos = {EGO_AGENT: self._ego_info(ego_terms)}
        for a in hw_agents:
            infos[a] = self._highway_info(a, hw_terms[a])
        self._cycles += 1
        if self.max_cycles is not None and self._cycles >= self.max_cycles:
            truncations = {a: truncations[a] or not terminations[a] for a in agents}
        self.agents = [a for a in agents if not (terminations[a] or truncations[a])]
        if self.render_mode == "human":
            self.render()
        return obs, rewards, terminations, truncations, infos

    def _observations(
        self, agents: list[str], ego_obs: np.ndarray, hw_obs: np.ndarray
    ) -> dict[str, np.ndarray]:
        """Per-agent observations from the core's [1, F] and [1, K, 12] outputs."""
        obs = {EGO_AGENT: ego_obs[0]}
        for a in agents:
            if a != EGO_AGENT:
                obs[a] = hw_obs[0, self._column[a]]
        return obs

    # ------------------------------------------------------------------ rendering
    def render(self) -> np.ndarray | None:
        """rgb_array: the frame; human: shows it in a window (needs pygame) and returns None."""
        if self.render_mode is None or self.core is None:
            return None
        from marlmerge.views.render import Window, render_scene

        if self.render_mode == "human":
            if self._viewer is None:
                self._viewer = Window(f"marlmerge - {self.cfg.name}", self.metadata["render_fps"])
            self._viewer.show(render_scene(self.core, world=0, agent_slots=self.agent_slots))
            return None
        return render_scene(self.core, world=0, agent_slots=self.agent_slots)

    def close(self) -> None:
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None

    @property
    def agent_slots(self) -> dict[str, int]:
        """Vehicle slot of each live highway agent (the ego is slot 0)."""
        return {a: s for a, s in self._slots.items() if a in self.agents}


def parallel_env(
    config: ScenarioConfig | str | Path | None = None,
    render_mode: str | None = None,
    control: str = "all",
    overrides: dict[str, Any] | None = None,
    max_cycles: int | None = None,
) -> RampMergeParallelEnv:
    """The ramp-merge PettingZoo ParallelEnv (documented in this module's docstring).

    config: a `ScenarioConfig`, a preset path or a preset name from `envs/`; defaults if None.
    control: "all" (ego and highway agents act) or "ego" (mainline traffic is scripted).
    overrides: dotted config keys, e.g. {"traffic.flow_vph_per_lane": 800}.
    max_cycles: truncate every agent after this many env steps of an episode (PettingZoo's
        episode cap; None: the ego's own limits only).
    """
    return RampMergeParallelEnv(config, render_mode, control, overrides, max_cycles)


def raw_env(**kwargs: Any) -> AECEnv:
    """The same env as an AEC env (agents act one after the other; `parallel_to_aec`, each
    action checked when given: `marlmerge.views.aec`)."""
    return checked_aec(parallel_env(**kwargs))


def env(**kwargs: Any) -> AECEnv:
    """The AEC env of `raw_env`, with PettingZoo's order checks (they come with the
    conversion): `marlmerge.env()` in PettingZoo's `env()` / `parallel_env()` convention."""
    return raw_env(**kwargs)
