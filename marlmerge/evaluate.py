"""Evaluation of an ego policy on held-out roads: outcomes, merge time, comfort, safety.

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
from marlmerge.core import (
    EGO,
    OUTCOME_COLLISION,
    OUTCOME_SUCCESS,
    OUTCOME_TRUNCATED,
    EgoGaps,
    StepEvents,
    TrafficCore,
)

EgoPolicy = Callable[[torch.Tensor], torch.Tensor]
"""observation [B, 7] -> acceleration [B, 1] (m/s^2)."""

TRACE_FIELDS = (
    "x_m",
    "v_mps",
    "a_mps2",
    "d_front_m",
    "v_front_mps",
    "d_back_m",
    "v_back_mps",
    "a_back_mps2",
    "outcome",
)


class TrajectoryRecorder:
    """Records the ego and its gap vehicles of every world at every simulator step.

    Attach as `env.recorder`; `columns()` gives [T, B] arrays. A missing gap vehicle has an
    infinite gap and NaN speed and acceleration.
    """

    def __init__(self) -> None:
        self.rows: list[tuple[np.ndarray, ...]] = []

    def __call__(self, core: TrafficCore, ev: StepEvents, g: EgoGaps) -> None:
        st = core.state
        b = np.arange(core.batch_size)
        has_f, has_b = g.front >= 0, g.back >= 0
        back = np.maximum(g.back, 0)
        self.rows.append(
            (
                st.x_m[:, EGO].copy(),
                st.v_mps[:, EGO].copy(),
                st.a_mps2[:, EGO].copy(),
                np.where(has_f, g.d_front_m, np.inf),
                np.where(has_f, g.v_front_mps, np.nan),
                np.where(has_b, g.d_back_m, np.inf),
                np.where(has_b, g.v_back_mps, np.nan),
                np.where(has_b, st.a_mps2[b, back], np.nan),
                ev.ego_outcome.copy(),
            )
        )

    def columns(self) -> dict[str, np.ndarray]:
        return {name: np.stack([r[i] for r in self.rows]) for i, name in enumerate(TRACE_FIELDS)}


@torch.no_grad()
def rollout_first_egos(
    policy: EgoPolicy,
    scenario: ScenarioConfig,
    episodes: int,
    seed: int,
    worlds: int = 50,
    record: bool = False,
) -> tuple[dict[str, np.ndarray], list[dict[str, np.ndarray]]]:
    """Run the first ego of `episodes` fresh worlds to its end.

    Returns per-episode records (outcome code, time_s, total reward, mean |accel|) and, with
    `record`, each episode's simulator-step trace (`TRACE_FIELDS`, arrays [T]) up to its end.
    """
    rec: dict[str, list[np.ndarray]] = {
        "outcome": [],
        "time_s": [],
        "reward": [],
        "mean_abs_accel": [],
    }
    traces: list[dict[str, np.ndarray]] = []
    lo, hi = scenario.ego.accel_bounds_mps2
    for g in range(-(-episodes // worlds)):
        nw = min(worlds, episodes - g * worlds)
        env = BatchedMergeEnv(scenario, num_worlds=nw, seed=seed + g)
        recorder = TrajectoryRecorder() if record else None
        env.recorder = recorder
        td = env.reset()
        outcome = np.zeros(nw, dtype=np.int64)
        time_s, reward, abs_accel, steps = (np.zeros(nw) for _ in range(4))
        while (outcome == 0).any():
            action = policy(td.get("observation")).reshape(nw, 1)
            td.set("action", action)
            nxt = env.step(td).get("next")
            running = outcome == 0
            abs_accel += np.abs(action.reshape(nw).double().clamp(lo, hi).numpy()) * running
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
        if recorder is not None:
            cols = recorder.columns()
            end = np.argmax(cols["outcome"] != 0, axis=0)  # [B] step of the first outcome
            for w in range(nw):
                traces.append({k: v[: end[w] + 1, w] for k, v in cols.items()})
    return {k: np.concatenate(v) for k, v in rec.items()}, traces


def run_episodes(
    policy: EgoPolicy, scenario: ScenarioConfig, episodes: int, seed: int, worlds: int = 50
) -> dict[str, np.ndarray]:
    """Per-episode records: outcome code, time_s, total reward, mean |accel| (m/s^2)."""
    return rollout_first_egos(policy, scenario, episodes, seed, worlds)[0]


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


def evaluate_policy(
    policy: EgoPolicy,
    scenario: ScenarioConfig,
    episodes: int = 200,
    seed: int = 1_000_000,
    worlds: int = 50,
) -> dict[str, float]:
    """Summary of `episodes` held-out episodes of a policy (e.g. a learner's greedy action)."""
    return summarize(run_episodes(policy, scenario, episodes, seed, worlds))
