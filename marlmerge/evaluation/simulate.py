"""`marlmerge simulate`: ramp vehicles driven by a simple rule through scripted traffic, without
learning; one record per episode, a summary and a frame of the first merge."""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.policies.scripted import IdmEgoPolicy, constant_speed_action
from marlmerge.sim import EGO, OUTCOME_NAMES, OUTCOME_NONE
from marlmerge.views.pettingzoo_env import EGO_AGENT, parallel_env, reward_terms
from marlmerge.views.render import render_frame, save_png

EGO_RULES = ("hold", "idm", "random")
"""The ego rules: keep speed, IDM ignoring the merge, uniform random accelerations."""
SHOWN_TERMS = ("acceleration", "gap_front", "gap_back", "speed", "collision")
"""The reward terms an episode's line shows."""

EgoRule = Callable[[np.ndarray], np.ndarray]
"""ego observation [F] -> acceleration [1] (m/s^2)."""


def ego_rule(rule: str, cfg: ScenarioConfig, rng: np.random.Generator) -> EgoRule:
    """The ego rule named `rule` (one of `EGO_RULES`); "random" draws from `rng`."""
    if rule == "hold":
        return constant_speed_action
    if rule == "idm":
        return IdmEgoPolicy(cfg)
    if rule == "random":
        lo, hi = cfg.ego.accel_bounds_mps2
        return lambda obs: rng.uniform(lo, hi, size=1).astype(np.float32)
    raise ValueError(f"ego rule must be one of {', '.join(EGO_RULES)}, got {rule!r}")


@dataclass
class SimulateResult:
    summary: dict[str, Any]
    """episodes, success / collision / truncated rates, env steps and env steps per second."""
    episodes: list[dict[str, Any]]
    """One record per episode: outcome, time_s, reward and the summed reward terms."""
    frame: Path | None
    """The frame saved as the first ramp vehicle reached its join point (None if none did)."""


def simulate(
    scenario: str | Path | ScenarioConfig,
    ego: str,
    episodes: int,
    seed: int,
    out: Path,
    on_episode: Callable[[dict[str, Any]], None] | None = None,
) -> SimulateResult:
    """Drive `episodes` ramp vehicles with the rule `ego` on the road of `seed`; write
    `out/episodes.json` and `out/frame.png`; `on_episode` sees each record as it ends."""
    env = parallel_env(scenario, render_mode="rgb_array", control="ego")
    cfg = env.cfg
    policy = ego_rule(ego, cfg, np.random.default_rng(seed))
    out.mkdir(parents=True, exist_ok=True)
    obs, _ = env.reset(seed=seed)
    outcomes: Counter[str] = Counter()
    frame, records, steps = None, [], 0
    t0 = time.perf_counter()
    for ep in range(episodes):
        totals: Counter[str] = Counter()
        while env.agents:
            obs, _, _, _, info = env.step({EGO_AGENT: policy(obs[EGO_AGENT])})
            steps += 1
            totals.update(reward_terms(info[EGO_AGENT]))
            if frame is None and env.core.state.x_m[0, EGO] >= cfg.x_overlap_m - 10.0:
                frame = out / "frame.png"
                save_png(frame, render_frame(env.core, agent_slots=env.agent_slots))
        last = info[EGO_AGENT]
        outcome = OUTCOME_NAMES[last["outcome"]]
        outcomes[outcome] += 1
        record = {"episode": ep, "outcome": outcome, "time_s": last["ego_time_s"]}
        records.append({**record, "reward": sum(totals.values()), **dict(totals)})
        if on_episode is not None:
            on_episode(records[-1])
        obs, _ = env.reset()
        assert env.core.state.ego_outcome[0] == OUTCOME_NONE
    summary = {
        "episodes": episodes,
        **{f"{k}_rate": outcomes[k] / episodes for k in ("success", "collision", "truncated")},
        "env_steps": steps,
        "env_steps_per_s": steps / (time.perf_counter() - t0),
    }
    (out / "episodes.json").write_text(
        json.dumps({"summary": summary, "episodes": records}, indent=1)
    )
    return SimulateResult(summary, records, frame)
