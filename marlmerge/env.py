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
    `ramp_0`: [-4.5, 2.5] by default; `highway_*`: `sim.highway_agent_accel_bounds_mps2`
    (the same by default; scripted background traffic keeps the vehicle limits).
    Out-of-range values are clipped; NaN, infinite, wrongly shaped actions, agents that are not in
    `possible_agents` and missing actions of live agents raise `ValueError` naming the agent and the
    value. Actions for possible agents that are not live (done, or not in this episode's roster) are
    ignored, as torchrl's PettingZoo wrapper sends an action for every agent of a group. Controlled
    highway agents keep their lane.

Observations
    Box float32, scaled; layouts in `marlmerge.observation` (`EGO_FEATURES`, `HIGHWAY_FEATURES`).

Rewards
    Sums over the env step of the per-simulator-step terms of `marlmerge.reward`: the ego's
    `EGO_TERMS`; a highway agent's `LEARNED_HIGHWAY_TERMS` (its own driving terms plus the
    interaction terms of `InteractionConfig`, adversarial by default, `interaction.sign = -1`
    for cooperative agents).

Infos
    Flat and numeric, with the same keys at `reset` and at every step (so torchrl's PettingZoo
    wrapper can carry them): `reward_<term>` for each named reward term (`reward_terms(info)`
    collects them), and for `ramp_0` also `outcome` (0 running, 1 success, 2 collision,
    3 truncated; names in `OUTCOME_NAMES`), `ego_time_s`, `ego_x_m`, `vehicle_id`; for highway
    agents `vehicle_id` and `profile` (a `Profile` code).

Episode end
    The episode is the ego's merge. `ramp_0` terminates on success or collision and is truncated
    when stalled or out of time; at that moment every highway agent is truncated (the road goes on).
    A highway agent that leaves the road downstream terminates. `reset()` without a seed sends the
    next ramp vehicle into the same flowing traffic (`sim.continue_traffic`); `reset(seed=...)`
    builds a fresh road in steady flow.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from marlmerge.config import ScenarioConfig, load_scenario
from marlmerge.core import (
    EGO,
    OUTCOME_COLLISION,
    OUTCOME_NONE,
    OUTCOME_SUCCESS,
    RIGHT,
    TrafficCore,
)
from marlmerge.observation import (
    EGO_FEATURES,
    HIGHWAY_FEATURES,
    ego_observation,
    highway_observation,
)
from marlmerge.reward import (
    EGO_TERMS,
    LEARNED_HIGHWAY_TERMS,
    ego_reward_terms,
    highway_agent_step_terms,
)

EGO_AGENT = "ramp_0"
ENV_NAME = "marlmerge_ramp_v0"


def resolve_config(config: ScenarioConfig | str | Path | None, **overrides: Any) -> ScenarioConfig:
    """A `ScenarioConfig` from a config, a preset path or name in `envs/`, or the defaults."""
    if config is None:
        cfg = ScenarioConfig()
    elif isinstance(config, ScenarioConfig):
        cfg = config
    else:
        cfg = load_scenario(find_preset(config))
    return cfg.replace(**overrides) if overrides else cfg


def find_preset(name: str | Path) -> Path:
    """A preset file: a path, or a name looked up in the repository's `envs/` folder."""
    path = Path(name)
    if path.suffix == ".toml" and path.exists():
        return path
    envs_dir = Path(__file__).resolve().parent.parent / "envs"
    candidate = envs_dir / f"{path.stem}.toml"
    if candidate.exists():
        return candidate
    known = sorted(p.stem for p in envs_dir.glob("*.toml")) if envs_dir.exists() else []
    raise ValueError(f"unknown scenario preset {str(name)!r} (known: {', '.join(known) or 'none'})")


def reward_terms(info: dict[str, Any]) -> dict[str, float]:
    """The named reward terms of one agent's info: {"acceleration": ..., "gap_front": ..., ...}."""
    return {k[len("reward_") :]: float(v) for k, v in info.items() if k.startswith("reward_")}


class RampMergeParallelEnv(ParallelEnv):
    metadata = {"name": ENV_NAME, "render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        config: ScenarioConfig | str | Path | None = None,
        render_mode: str | None = None,
        control: str = "all",
        overrides: dict[str, Any] | None = None,
    ):
        if control not in ("all", "ego"):
            raise ValueError(f"control must be 'all' or 'ego', got {control!r}")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.cfg = resolve_config(config, **(overrides or {}))
        self.render_mode = render_mode
        self.control = control
        n_hw = self.cfg.sim.n_highway_agents if control == "all" else 0
        self.possible_agents = [EGO_AGENT] + [f"highway_{i}" for i in range(n_hw)]
        self.agents: list[str] = []
        lo, hi = self.cfg.ego.accel_bounds_mps2
        hw_lo, hw_hi = self.cfg.sim.highway_agent_accel_bounds_mps2
        self._bounds = {EGO_AGENT: (lo, hi)}
        self._action_spaces = {EGO_AGENT: spaces.Box(lo, hi, (1,), np.float32)}
        self._observation_spaces = {
            EGO_AGENT: spaces.Box(-np.inf, np.inf, (len(EGO_FEATURES),), np.float32)
        }
        for a in self.possible_agents[1:]:
            self._bounds[a] = hw_lo, hw_hi
            self._action_spaces[a] = spaces.Box(hw_lo, hw_hi, (1,), np.float32)
            self._observation_spaces[a] = spaces.Box(
                -np.inf, np.inf, (len(HIGHWAY_FEATURES),), np.float32
            )
        self.core: TrafficCore | None = None
        self._slots: dict[str, int] = {}
        self._ids: dict[str, int] = {}
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
        if self.core is None:
            self.core = TrafficCore(self.cfg, batch_size=1, seed=seed)
        elif seed is not None:
            self.core.reset(seed=seed)
        elif self.cfg.sim.continue_traffic:
            self.core.next_ego(np.ones(1, dtype=bool))
        else:
            self.core.reset()
        self._pick_roster()
        self._ego_in_lane_s = 0.0
        self.agents = [EGO_AGENT] + list(self._slots)
        obs = self._observations(self.agents)
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
        return info

    def _highway_info(self, agent: str, terms: dict[str, float]) -> dict[str, float | int]:
        st = self.core.state  # type: ignore[union-attr]
        info: dict[str, float | int] = {f"reward_{k}": terms[k] for k in LEARNED_HIGHWAY_TERMS}
        info["vehicle_id"] = self._ids[agent]
        info["profile"] = int(st.profile[0, self._slots[agent]])
        return info

    def _pick_roster(self) -> None:
        core = self.core
        assert core is not None
        st = core.state
        slots = core.pick_roster(len(self.possible_agents) - 1)[0]
        chosen = slots[slots >= 0]
        self._slots = {f"highway_{i}": int(s) for i, s in enumerate(chosen)}
        self._ids = {a: int(st.vehicle_id[0, s]) for a, s in self._slots.items()}

    # ------------------------------------------------------------------ step
    def _parse_actions(self, actions: dict[str, Any]) -> dict[str, float]:
        if not isinstance(actions, dict):
            raise ValueError(f"actions must be a dict of agent -> action, got {type(actions)}")
        unknown = [a for a in actions if a not in self._action_spaces]
        if unknown:
            raise ValueError(
                f"unknown agent {unknown[0]!r} in actions (possible agents: {self.possible_agents})"
            )
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"no action for live agent {missing[0]!r}")
        out = {}
        for agent in self.agents:
            act = actions[agent]
            arr = np.asarray(act, dtype=np.float64)
            if arr.shape not in ((1,), ()):
                raise ValueError(
                    f"action of {agent!r} must have shape (1,), got shape {arr.shape} ({act!r})"
                )
            val = float(arr.reshape(()))
            if not np.isfinite(val):
                raise ValueError(f"action of {agent!r} must be finite, got {val}")
            lo, hi = self._bounds[agent]
            out[agent] = min(max(val, lo), hi)
        return out

    def step(self, actions: dict[str, Any]):
        if not self.agents:
            raise RuntimeError("step() called on a finished episode: call reset() first")
        core = self.core
        assert core is not None
        acts = self._parse_actions(actions)
        cfg = self.cfg
        st = core.state
        ego_a = np.array([acts[EGO_AGENT]])
        hw_agents = [a for a in self.agents if a != EGO_AGENT]
        hw_slots = np.array([self._slots[a] for a in hw_agents], dtype=np.int64)
        hw_cmd = None
        if hw_agents:
            hw_cmd = np.full((1, core.n_slots), np.nan)
            hw_cmd[0, hw_slots] = [acts[a] for a in hw_agents]
        hw_terms = {a: dict.fromkeys(LEARNED_HIGHWAY_TERMS, 0.0) for a in hw_agents}
        gone: set[str] = set()
        outcome = OUTCOME_NONE
        trace = []  # per simulator step: the ego quantities its reward depends on
        for _ in range(cfg.sim.action_repeat):
            ev = core.step(ego_a, hw_cmd)
            g = core.ego_gaps()
            trace.append(
                (
                    st.v_mps[0, EGO],
                    st.x_m[0, EGO],
                    g.d_front_m[0],
                    g.d_back_m[0],
                    g.v_back_mps[0],
                    ev.collided[0, EGO],
                )
            )
            in_lane = st.lane[0, EGO] == RIGHT
            self._ego_in_lane_s = self._ego_in_lane_s + cfg.sim.dt_s if in_lane else 0.0
            if hw_agents:
                live = [a for a in hw_agents if a not in gone]
                s = np.array([[self._slots[a] for a in live]], dtype=np.int64)
                h = highway_agent_step_terms(core, ev, g, s, np.array([self._ego_in_lane_s]))
                for i, a in enumerate(live):
                    for k, v in h.items():
                        hw_terms[a][k] += float(v[0, i])
                    if not self._still_on_road(a):
                        gone.add(a)
                        hw_cmd[0, self._slots[a]] = np.nan
            outcome = int(ev.ego_outcome[0])
            if outcome != OUTCOME_NONE:
                break
        v, x, d_f, d_b, v_b, hit = np.array(trace).T
        terms = ego_reward_terms(
            cfg.reward, np.full(v.shape, ego_a[0]), v, x, d_f, d_b, v_b, hit > 0.5, core.v_limit
        )
        ego_terms = {k: float(terms[k].sum()) for k in EGO_TERMS}

        agents = list(self.agents)
        obs = self._observations(agents)
        rewards = {EGO_AGENT: float(sum(ego_terms.values()))}
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
        self.agents = [a for a in agents if not (terminations[a] or truncations[a])]
        return obs, rewards, terminations, truncations, infos

    def _still_on_road(self, agent: str) -> bool:
        st = self.core.state  # type: ignore[union-attr]
        s = self._slots[agent]
        return bool(st.active[0, s]) and int(st.vehicle_id[0, s]) == self._ids[agent]

    def _observations(self, agents: list[str]) -> dict[str, np.ndarray]:
        core = self.core
        assert core is not None
        obs = {EGO_AGENT: ego_observation(core)[0]}
        hw = [a for a in agents if a != EGO_AGENT]
        if hw:
            slots = np.array([[self._slots[a] for a in hw]], dtype=np.int64)
            o = highway_observation(core, slots)[0]
            for i, a in enumerate(hw):
                obs[a] = o[i]
        return obs

    # ------------------------------------------------------------------ rendering
    def render(self) -> np.ndarray | None:
        if self.render_mode is None or self.core is None:
            return None
        from marlmerge.render import render_frame

        return render_frame(self.core, world=0, agent_slots=self._slots)

    def close(self) -> None:
        pass

    @property
    def agent_slots(self) -> dict[str, int]:
        """Vehicle slot of each live highway agent (the ego is slot 0)."""
        return {a: s for a, s in self._slots.items() if a in self.agents}


def parallel_env(
    config: ScenarioConfig | str | Path | None = None,
    render_mode: str | None = None,
    control: str = "all",
    overrides: dict[str, Any] | None = None,
) -> RampMergeParallelEnv:
    """The ramp-merge PettingZoo ParallelEnv (documented in this module's docstring).

    config: a `ScenarioConfig`, a preset path or a preset name from `envs/`; defaults if None.
    control: "all" (ego and highway agents act) or "ego" (mainline traffic is scripted).
    overrides: dotted config keys, e.g. {"traffic.flow_vph_per_lane": 800}.
    """
    return RampMergeParallelEnv(config, render_mode, control, overrides)
