"""Evaluation of an ego policy on held-out roads: outcome rates, merge time, comfort.

Metrics are computed from what happened, separately from the reward. Each group of
`worlds` episodes runs on a `BatchedMergeEnv` seeded `seed + group`; an episode is the first ego
of a freshly seeded world (a road in steady flow), so the list of episodes is fixed by
(`episodes`, `seed`, `worlds`) and shared by every policy evaluated with them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from marlmerge.batched_env import BatchedMergeEnv
from marlmerge.config import ScenarioConfig
from marlmerge.core import OUTCOME_COLLISION, OUTCOME_SUCCESS, OUTCOME_TRUNCATED

EgoPolicy = Callable[[torch.Tensor], torch.Tensor]
"""observation [B, 7] -> acceleration [B, 1] (m/s^2)."""


@torch.no_grad()
def run_episodes(
    policy: EgoPolicy, scenario: ScenarioConfig, episodes: int, seed: int, worlds: int = 50
) -> dict[str, np.ndarray]:
    """Per-episode records: outcome code, time_s, total reward, mean |accel| (m/s^2)."""
    rec: dict[str, list[np.ndarray]] = {
        "outcome": [],
        "time_s": [],
        "reward": [],
        "mean_abs_accel": [],
    }
    n_groups = -(-episodes // worlds)
    for g in range(n_groups):
        nw = min(worlds, episodes - g * worlds)
        env = BatchedMergeEnv(scenario, num_worlds=nw, seed=seed + g)
        td = env.reset()
        outcome = np.zeros(nw, dtype=np.int64)
        time_s = np.zeros(nw)
        reward = np.zeros(nw)
        abs_accel = np.zeros(nw)
        steps = np.zeros(nw)
        lo, hi = scenario.ego.accel_bounds_mps2
        while (outcome == 0).any():
            action = policy(td.get("observation")).reshape(nw, 1)
            td.set("action", action)
            nxt = env.step(td).get("next")
            running = outcome == 0
            a = action.reshape(nw).double().clamp(lo, hi).numpy()
            abs_accel += np.abs(a) * running
            steps += running
            reward += nxt.get("reward").reshape(nw).numpy() * running
            new = nxt.get("outcome").reshape(nw).numpy()
            ended = running & (new != 0)
            outcome[ended] = new[ended]
            time_s[ended] = nxt.get("ego_time_s").reshape(nw).numpy()[ended]
            td = nxt
        rec["outcome"].append(outcome)
        rec["time_s"].append(time_s)
        rec["reward"].append(reward)
        rec["mean_abs_accel"].append(abs_accel / np.maximum(steps, 1))
    return {k: np.concatenate(v) for k, v in rec.items()}


def summarize(rec: dict[str, np.ndarray]) -> dict[str, float]:
    o = rec["outcome"]
    ok = o == OUTCOME_SUCCESS
    return {
        "episodes": int(o.size),
        "success_rate": float(np.mean(ok)),
        "collision_rate": float(np.mean(o == OUTCOME_COLLISION)),
        "truncation_rate": float(np.mean(o == OUTCOME_TRUNCATED)),
        "mean_merge_time_s": float(np.mean(rec["time_s"][ok])) if ok.any() else float("nan"),
        "mean_abs_accel_mps2": float(np.mean(rec["mean_abs_accel"])),
        "mean_total_reward": float(np.mean(rec["reward"])),
    }


def evaluate_greedy(
    net: torch.nn.Module,
    scenario: ScenarioConfig,
    episodes: int = 200,
    seed: int = 1_000_000,
    worlds: int = 50,
) -> dict[str, float]:
    """Greedy evaluation of a `QuadraticQNet` (action = B(s))."""
    return summarize(run_episodes(net.greedy, scenario, episodes, seed, worlds))
