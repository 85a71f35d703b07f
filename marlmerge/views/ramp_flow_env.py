"""Ramp flow as a PettingZoo `ParallelEnv`: every merging vehicle is an agent
(`ramp.flow_vph > 0`; a thin single-world view over `TrafficCore`).

Agents
    `ramp_0` ... `ramp_{K-1}` (`possible_agents`): `ramp_i` is the i-th ramp vehicle of the
    episode. It becomes an agent when it enters the ramp and stays one until its own merge ends;
    `agents` holds the live ones, so agents appear (in the step's returns, with reward 0) and
    leave during an episode, and no name comes back (PettingZoo's rule). K (`max_agents`) is by
    default 1.5 x the ramp vehicles the episode expects, plus 20; later ramp vehicles drive by
    IDM behind their ramp leader (`infos[...]["unnamed_on_ramp"]` counts those on the ramp).
    Mainline vehicles are scripted.

Actions
    Box(1,) longitudinal acceleration in m/s^2 within `ego.accel_bounds_mps2` (out-of-range
    values clipped), held for `sim.action_repeat` simulator steps; on the ramp capped by IDM
    behind the ramp vehicle ahead. With `ego.join = "chosen"` Box(2,): (acceleration, join),
    join in [-1, 1], > 0 changing into the right lane inside the merge zone; a vehicle that has
    not joined stops at the acceleration lane's end (`marlmerge.sim.action`). Checked as
    `RampMergeParallelEnv` checks them: a bad value, an unknown agent or a missing action of a
    live agent raises `ValueError` naming the agent.

Observations
    Box float32 [7]: the paper's state (`EGO_FEATURES`, scaled) of this vehicle, with perfect
    sensing: its gap vehicles in the right lane at its position (its leader and follower once it
    has joined); [8] with `ego.join = "chosen"`, ending with `on_ramp`
    (`ramp_agent_features`).

Rewards
    The paper's ego terms (`EGO_TERMS`) for this vehicle's own merge, summed over the env step,
    with its realised acceleration; the jerk term is not counted.

Infos
    Flat and numeric, the same keys at every step: `reward_<term>`, `outcome` (0 running,
    1 success, 2 collision, 3 truncated), `time_s` (since it became an agent), `x_m`,
    `vehicle_id` and `unnamed_on_ramp`.

Episode end
    An agent terminates on success (past `ego.success_distance_m`) or collision, and is
    truncated after `ego.max_episode_s` or when stalled (`ego.stall_*`). The episode is
    `max_cycles` env steps of the road (default 1,000: 400 s): steps in which no agent is live
    pass inside the call that would leave none, so `agents` is empty only at the end, when every
    live agent is truncated. `reset(seed=...)` builds a fresh road; `reset()` continues the
    flowing traffic.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import AECEnv, ParallelEnv

from marlmerge.config import ScenarioConfig, check_count
from marlmerge.config.presets import resolve_config
from marlmerge.sim import (
    OUTCOME_COLLISION,
    OUTCOME_NONE,
    OUTCOME_SUCCESS,
    OUTCOME_TRUNCATED,
    TrafficCore,
)
from marlmerge.sim.action import action_bounds, action_size, agent_actions, check_can_step
from marlmerge.sim.observation import ramp_agent_features
from marlmerge.sim.reward import EGO_TERMS, total_reward
from marlmerge.sim.streams import check_seed
from marlmerge.views.aec import checked_aec
from marlmerge.views.ramp_agents import RampAgentTable

ENV_NAME = "marlmerge_ramp_flow_v1"
DEFAULT_MAX_CYCLES = 1000


class RampFlowParallelEnv(ParallelEnv):
    metadata = {"name": ENV_NAME, "render_modes": [], "is_parallelizable": True}

    def __init__(
        self,
        config: ScenarioConfig | str | Path | None = None,
        max_agents: int | None = None,
        overrides: dict[str, Any] | None = None,
        max_cycles: int = DEFAULT_MAX_CYCLES,
    ):
        max_cycles = check_count("max_cycles", max_cycles)
        self.cfg = resolve_config(config, **(overrides or {}))
        if not self.cfg.ramp.flowing:
            raise ValueError(
                f"RampFlowParallelEnv needs ramp flow: ramp.flow_vph = {self.cfg.ramp.flow_vph} "
                "(the paper's one ego: RampMergeParallelEnv)"
            )
        self._step_s = self.cfg.sim.dt_s * self.cfg.sim.action_repeat
        if max_agents is None:
            expected = max_cycles * self._step_s * self.cfg.ramp.flow_vph / 3600.0
            max_agents = int(np.ceil(1.5 * expected)) + 20
        max_agents = check_count("max_agents", max_agents)
        self.max_cycles = max_cycles
        self.render_mode = None
        self.possible_agents = [f"ramp_{i}" for i in range(max_agents)]
        self.agents: list[str] = []
        self._action_space = spaces.Box(*action_bounds(self.cfg), dtype=np.float32)
        n_obs = len(ramp_agent_features(self.cfg))
        self._observation_space = spaces.Box(-np.inf, np.inf, (n_obs,), np.float32)
        self.core: TrafficCore | None = None
        self._table: RampAgentTable | None = None
        self._cycles = 0

    def observation_space(self, agent: str) -> spaces.Box:
        self._check_agent(agent)
        return self._observation_space

    def action_space(self, agent: str) -> spaces.Box:
        self._check_agent(agent)
        return self._action_space

    def _check_agent(self, agent: str) -> str:
        if agent not in self.possible_agents:
            raise ValueError(f"unknown agent {agent!r} (possible agents: {self.possible_agents})")
        return agent

    # ------------------------------------------------------------------ reset and step
    def reset(self, seed: int | None = None, options: dict | None = None):
        check_seed(seed)
        if self.core is None:
            self.core = TrafficCore(self.cfg, batch_size=1, seed=seed)
            self._table = RampAgentTable(self.core, len(self.possible_agents), reuse=False)
        elif seed is not None:
            self.core.reset(seed=seed)
        assert self._table is not None
        self._table.clear()
        self._cycles = 0
        self._table.assign()
        self._until_an_agent()
        self.agents = self._live()
        slots = self._table.slots()
        none = dict.fromkeys(self.agents, OUTCOME_NONE)
        return self._observe(slots), self._infos(self.agents, {}, none, slots)

    def step(self, actions: dict[str, Any]):
        check_can_step(self.agents, started=self.core is not None)
        core, table = self.core, self._table
        assert core is not None and table is not None
        acts = self._parse_actions(actions)
        agents = list(self.agents)
        cmd = np.full((1, len(self.possible_agents), 2), np.nan)  # (acceleration, join)
        for a, act in acts.items():
            cmd[0, self._column(a), : act.size] = act
        out = core.rollout(
            np.full(1, np.nan),
            roster=table.roster(),
            roster_accel=cmd[..., 0],
            roster_join=cmd[..., 1],
        )
        self._cycles += 1
        sums = {a: out.hw_terms[0, self._column(a)] for a in agents}
        terms = {a: dict(zip(EGO_TERMS, sums[a].tolist(), strict=True)) for a in agents}
        rewards = {a: float(total_reward(sums[a])) for a in agents}
        slots = table.slots()
        outcome = table.outcomes(slots)[0]
        last = self._cycles >= self.max_cycles
        ends = {a: int(outcome[self._column(a)]) for a in agents}
        terminations = {a: ends[a] in (OUTCOME_SUCCESS, OUTCOME_COLLISION) for a in agents}
        truncations = {a: ends[a] == OUTCOME_TRUNCATED or last for a in agents}
        obs = self._observe(slots)
        infos = self._infos(agents, terms, ends, slots)
        table.release((outcome != OUTCOME_NONE)[None] | last)
        if not last:  # the new ramp vehicles join this step's returns
            table.assign()
            self._until_an_agent()
            new = [a for a in self._live() if a not in agents]
            slots = table.slots()
            obs.update({a: o for a, o in self._observe(slots).items() if a in new})
            infos.update(self._infos(new, {}, dict.fromkeys(new, OUTCOME_NONE), slots))
            for a in new:
                rewards[a], terminations[a], truncations[a] = 0.0, False, False
        self.agents = self._live()
        return obs, rewards, terminations, truncations, infos

    # ------------------------------------------------------------------ helpers
    @property
    def action_sizes(self) -> dict[str, int]:
        """Numbers per action of every ramp agent: (acceleration, join) with a join choice."""
        return dict.fromkeys(self.possible_agents, action_size(self.cfg))

    def _parse_actions(self, actions: dict[str, Any]) -> dict[str, np.ndarray]:
        return agent_actions(actions, self.possible_agents, self.agents, self.action_sizes)

    def _column(self, agent: str) -> int:
        return int(agent.rsplit("_", 1)[1])

    def _live(self) -> list[str]:
        assert self._table is not None
        return [self.possible_agents[j] for j in np.flatnonzero(self._table.live[0])]

    def _until_an_agent(self) -> None:
        """Steps with no live agent pass here (scripted), until a ramp vehicle enters or the
        episode's steps are spent."""
        core, table = self.core, self._table
        assert core is not None and table is not None
        while not table.live.any() and self._cycles < self.max_cycles:
            core.rollout(np.full(1, np.nan))
            self._cycles += 1
            table.assign()

    def _observe(self, slots: np.ndarray) -> dict[str, np.ndarray]:
        """Every live agent's observation (those whose merge just ended: their last), from the
        table's `slots()` of now."""
        assert self.core is not None and self._table is not None
        obs = self.core.observe_agents(self._table.roster(slots))[0]
        return {
            self.possible_agents[j]: obs[j].astype(np.float32)
            for j in np.flatnonzero(self._table.live[0])
        }

    def _infos(
        self,
        agents: list[str],
        terms: dict[str, dict[str, float]],
        outcomes: dict[str, int],
        slots: np.ndarray,
    ) -> dict[str, dict[str, float]]:
        """The agents' infos (`terms`: each one's summed reward terms; none: zeros), from the
        table's `slots()` of now."""
        assert self.core is not None and self._table is not None
        st, table = self.core.state, self._table
        unnamed = int(table.unnamed_on_ramp(slots)[0])
        zero = dict.fromkeys(EGO_TERMS, 0.0)
        infos = {}
        for a in agents:
            j = self._column(a)
            s = int(slots[0, j])
            infos[a] = {
                **{f"reward_{t}": v for t, v in terms.get(a, zero).items()},
                "outcome": outcomes[a],
                "time_s": float(st.t_s[0] - table.since_s[0, j]),
                "x_m": float(st.x_m[0, s]) if s >= 0 else float("nan"),
                "vehicle_id": int(table.ids[0, j]),
                "unnamed_on_ramp": unnamed,
            }
        return infos


def ramp_flow_parallel_env(
    config: ScenarioConfig | str | Path | None = None,
    max_agents: int | None = None,
    overrides: dict[str, Any] | None = None,
    max_cycles: int = DEFAULT_MAX_CYCLES,
) -> RampFlowParallelEnv:
    """The ramp-flow PettingZoo ParallelEnv (documented in this module's docstring)."""
    return RampFlowParallelEnv(config, max_agents, overrides, max_cycles)


def ramp_flow_env(**kwargs: Any) -> AECEnv:
    """The same env as an AEC env (agents act one after the other; `parallel_to_aec`, each
    action checked when given: `marlmerge.views.aec`)."""
    return checked_aec(ramp_flow_parallel_env(**kwargs))
