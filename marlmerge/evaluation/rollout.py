"""Evaluation of an ego policy on held-out roads: outcomes, merge time, comfort, safety.

Metrics are computed from what happened, separately from the reward. Episode e is the first ego
of a fresh world seeded `seed + e` (a road in steady flow; worlds are independent of the batch
they run in), so the list of episodes is fixed by (`episodes`, `seed`) and shared by every
policy evaluated with them; `worlds` only sets how many run at once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch

from marlmerge.config import ScenarioConfig, check_count
from marlmerge.evaluation.metrics import EpisodeTrajectory, TrajectoryRecorder, wilson_interval
from marlmerge.evaluation.plausibility import HighwayTally, summarize_highway
from marlmerge.policies.gap_acceptance import GapShield, ShieldTally
from marlmerge.sim import (
    EGO,
    OUTCOME_COLLISION,
    OUTCOME_SUCCESS,
    OUTCOME_TRUNCATED,
    TrafficCore,
)
from marlmerge.sim.layout import VF_X, WF_LAPSE_LOGW, WF_LAPSE_N, WF_LAPSE_STEPS
from marlmerge.sim.proposal import (
    N_LAPSE_CLASSES,
    N_STATS,
    ST_LAPSE_N,
    ST_LAPSE_STEPS,
    Proposal,
)
from marlmerge.sim.streams import WorldSeed
from marlmerge.views.torchrl_env import BatchedMergeEnv
from marlmerge.views.torchrl_groups import GROUP, MultiAgentMergeEnv

EgoPolicy = Callable[[torch.Tensor], torch.Tensor]
"""observation [B, F] (the scenario's `ego.observation` layout) -> acceleration [B, 1] (m/s^2);
[B, 2] (acceleration, join) with `ego.join = "chosen"` (`marlmerge.sim.action`)."""
HighwayPolicy = Callable[[torch.Tensor], torch.Tensor]
"""highway observation [B, K, 12] -> acceleration [B, K, 1] (m/s^2)."""


@torch.no_grad()
def rollout_first_egos(
    policy: EgoPolicy,
    scenario: ScenarioConfig,
    episodes: int,
    seed: int,
    worlds: int = 50,
    record: bool = False,
    highway_policy: HighwayPolicy | None = None,
    road_seeds: Sequence[WorldSeed] | None = None,
    scenarios: Sequence[ScenarioConfig] | None = None,
    proposal: Proposal | None = None,
    lapse_branches: Sequence[int] | None = None,
) -> tuple[dict[str, np.ndarray], list[dict[str, np.ndarray]]]:
    """Run the first ego of `episodes` fresh worlds to its end.

    Returns per-episode records (outcome code, time_s, total reward, mean |accel|, collisions
    between mainline vehicles during the episode, the safety filter's interventions: simulator
    steps whose command it overrode, 0 with the filter off) and, with `record`, each episode's
    `EpisodeTrajectory` (simulator-step samples up to its end). With `highway_policy`, the K
    highway agents of every world (`MultiAgentMergeEnv`) are driven by it instead of their
    scripted profiles (the roads are the same either way), and the records add the highway
    agents' plausibility counts (`marlmerge.evaluation.plausibility`). `road_seeds` (one per
    episode) replace the seeds `seed + e`; `scenarios` (one per episode, differing from
    `scenario` only in what `[sample]` draws) give each episode its own traffic and road.
    With `proposal` the traffic is importance-sampled (`marlmerge.sim.proposal`) and the
    records add each episode's `log_weight` (log p/q of its draws when it ended), `draw_stats`
    [E, N_STATS] (what the proposal drew) and `min_gap_m` (the smallest bumper gap to the
    right-lane vehicles at the ego's position while it was in the merge zone or beyond).
    `lapse_branches` (one per episode, with a proposal that splits lapses): the branch each
    episode runs (`TrafficCore.set_lapse_branches`; -1: the trunk).
    """
    episodes, worlds = check_count("episodes", episodes), check_count("worlds", worlds)
    given = {"scenarios": scenarios, "proposal": proposal, "lapse_branches": lapse_branches}
    if highway_policy is not None and any(v is not None for v in given.values()):
        named = ", ".join(k for k, v in given.items() if v is not None)
        raise ValueError(f"{named}: not with a highway policy")
    if lapse_branches is not None and len(lapse_branches) != episodes:
        raise ValueError(f"lapse_branches: one per episode ({episodes}), got {len(lapse_branches)}")
    rec: dict[str, list[np.ndarray]] = {}
    traces: list[EpisodeTrajectory] = []
    for g in range(-(-episodes // worlds)):
        batch = slice(g * worlds, min((g + 1) * worlds, episodes))
        nw = batch.stop - batch.start
        seeds = (
            [seed + e for e in range(batch.start, batch.stop)]
            if road_seeds is None
            else list(road_seeds[batch])
        )
        if highway_policy is None:
            env = BatchedMergeEnv(
                scenario,
                num_worlds=nw,
                seed=seeds,
                scenarios=None if scenarios is None else scenarios[batch],
                proposal=proposal,
            )
            if lapse_branches is not None:
                env.core.set_lapse_branches(np.asarray(lapse_branches[batch], dtype=np.int64))
        else:
            env = MultiAgentMergeEnv(scenario, num_worlds=nw, seed=seeds)
            env.set_opponent_mix(1, 0.0)
        records, batch_traces = _run_batch(
            env, policy, scenario, nw, record, highway_policy, proposal is not None
        )
        for key, values in records.items():
            rec.setdefault(key, []).append(values)
        traces += batch_traces
    return {k: np.concatenate(v) for k, v in rec.items()}, traces


def _run_batch(
    env: BatchedMergeEnv | MultiAgentMergeEnv,
    policy: EgoPolicy,
    scenario: ScenarioConfig,
    nw: int,
    record: bool,
    highway_policy: HighwayPolicy | None,
    weighted: bool,
) -> tuple[dict[str, np.ndarray], list[EpisodeTrajectory]]:
    """Run the first ego of each of `env`'s `nw` worlds to its end: the per-episode records of
    `rollout_first_egos` and, with `record`, the episodes' trajectories (in world order)."""
    lo, hi = scenario.ego.accel_bounds_mps2
    td = env.reset()
    background0 = env.core.state.background_collisions.copy()
    background = np.zeros(nw, dtype=np.int64)
    recorded: list[tuple[int, EpisodeTrajectory]] = []  # (world, episode)
    if record:
        recorder = TrajectoryRecorder(scenario, nw)
        env.recorder = lambda out, rec=recorder, got=recorded: got.extend(rec.record(out))
    tally = None if highway_policy is None else HighwayTally(scenario, nw)
    weights = WeightTally(env.core, nw) if weighted else None
    shields = shield_count(policy, nw)
    outcome = np.zeros(nw, dtype=np.int64)
    interventions = np.zeros(nw, dtype=np.int64)
    time_s, reward, abs_accel, steps = (np.zeros(nw) for _ in range(4))
    while (outcome == 0).any():
        action = policy(td.get("observation")).reshape(nw, -1)  # [B, A]
        if shields is not None:
            shields.add(outcome == 0)
        td.set("action", action)
        if highway_policy is not None:
            td.set((GROUP, "action"), highway_policy(td.get((GROUP, "observation"))))
        nxt = env.step(td).get("next")
        running = outcome == 0
        if tally is not None:
            tally.add(td, nxt, running)
        if weights is not None:
            weights.add(running, nxt.get("outcome").reshape(nw).numpy() != 0)
        background = np.where(
            running, env.core.state.background_collisions - background0, background
        )
        abs_accel += np.abs(action[:, 0].double().clamp(lo, hi).numpy()) * running
        steps += running
        reward += nxt.get("reward").reshape(nw).numpy() * running
        new = nxt.get("outcome").reshape(nw).numpy()
        ended = running & (new != 0)
        outcome[ended] = new[ended]
        time_s[ended] = nxt.get("ego_time_s").reshape(nw).numpy()[ended]
        interventions[ended] = env.core.state.filter_interventions[ended]
        td = nxt
    records = {
        "outcome": outcome,
        "time_s": time_s,
        "reward": reward,
        "mean_abs_accel": abs_accel / np.maximum(steps, 1),
        "background_collisions": background,
        "filter_interventions": interventions,
    }
    for extra in (tally, weights, shields):
        records |= {} if extra is None else extra.records()
    return records, [traj for _, traj in sorted(recorded, key=lambda e: e[0])]


class ShieldCount:
    """Per episode, the ego's commands that the policy's shield (`policy.shield`, a `GapShield`
    as `@shield` builds it) judged on the ramp and changed, counted while the episode runs."""

    def __init__(self, shield: GapShield, n: int):
        self.tally = shield.tally
        self.judged = np.zeros(n, dtype=np.int64)
        self.changed = np.zeros(n, dtype=np.int64)

    def add(self, running: np.ndarray) -> None:
        """After a call of the policy on all n worlds: count the rows of running episodes."""
        assert self.tally.last_judged is not None and self.tally.last_changed is not None
        self.judged += running & self.tally.last_judged.reshape(-1)
        self.changed += running & self.tally.last_changed.reshape(-1)

    def records(self) -> dict[str, np.ndarray]:
        return {"shield_judged": self.judged, "shield_changed": self.changed}


def shield_count(policy: EgoPolicy, n: int) -> ShieldCount | None:
    """A `ShieldCount` for a policy behind gap acceptance's shield, else None."""
    shield = getattr(policy, "shield", None)
    return ShieldCount(shield, n) if isinstance(shield, GapShield) else None


class WeightTally:
    """Each episode's log-likelihood ratio, proposal statistics and closest gap, taken when it
    ends (the world goes on drawing after that)."""

    def __init__(self, core: TrafficCore, n: int):
        self.core = core
        self.log_w = np.zeros(n)
        self.stats = np.zeros((n, N_STATS))
        self.min_gap_m = np.full(n, np.inf)

    def add(self, running: np.ndarray, ended: np.ndarray) -> None:
        tilted = self.core.streams.tilted
        assert tilted is not None
        gaps = self.core.ego_gaps()
        in_zone = self.core.vf[:, VF_X, EGO] >= self.core.cfg.road.x_zone_start_m
        gap = np.minimum(gaps.d_front_m, gaps.d_back_m)
        closer = running & in_zone & (gap < self.min_gap_m)
        self.min_gap_m[closer] = gap[closer]
        end = running & ended
        wf = self.core.wf[end]
        self.log_w[end] = tilted.log_w[end] + wf[:, WF_LAPSE_LOGW]  # the kernel's lapse draws
        self.stats[end] = tilted.stats[end]
        n = N_LAPSE_CLASSES
        self.stats[end, ST_LAPSE_STEPS : ST_LAPSE_STEPS + n] = wf[
            :, WF_LAPSE_STEPS : WF_LAPSE_STEPS + n
        ]
        self.stats[end, ST_LAPSE_N : ST_LAPSE_N + n] = wf[:, WF_LAPSE_N : WF_LAPSE_N + n]

    def records(self) -> dict[str, np.ndarray]:
        return {"log_weight": self.log_w, "draw_stats": self.stats, "min_gap_m": self.min_gap_m}


def run_episodes(
    policy: EgoPolicy,
    scenario: ScenarioConfig,
    episodes: int,
    seed: int,
    worlds: int = 50,
    highway_policy: HighwayPolicy | None = None,
) -> dict[str, np.ndarray]:
    """Per-episode records: outcome code, time_s, total reward, mean |accel| (m/s^2), ..."""
    return rollout_first_egos(
        policy, scenario, episodes, seed, worlds, highway_policy=highway_policy
    )[0]


def summarize(rec: dict[str, np.ndarray]) -> dict[str, float]:
    o = rec["outcome"]
    ok = o == OUTCOME_SUCCESS
    rates = {
        "success": ok,
        "collision": o == OUTCOME_COLLISION,
        "truncation": o == OUTCOME_TRUNCATED,
    }
    return {
        "episodes": int(o.size),
        **{f"{k}_rate": float(np.mean(v)) for k, v in rates.items()},
        **{f"{k}_ci95": list(wilson_interval(int(v.sum()), int(v.size))) for k, v in rates.items()},
        "mean_merge_time_s": float(np.mean(rec["time_s"][ok])) if ok.any() else float("nan"),
        "mean_abs_accel_mps2": float(np.mean(rec["mean_abs_accel"])),
        "mean_total_reward": float(np.mean(rec["reward"])),
        "background_collisions_per_episode": float(np.mean(rec["background_collisions"])),
        **summarize_highway(rec),
        **summarize_shield(rec),
    }


def summarize_shield(rec: dict[str, np.ndarray]) -> dict[str, float | int | None]:
    """Behind a shield (`ShieldCount`): the ego's commands it judged on the ramp and the share
    it changed (None with none judged); nothing without one."""
    if "shield_judged" not in rec:
        return {}
    total = ShieldTally(int(rec["shield_judged"].sum()), int(rec["shield_changed"].sum()))
    return {"shield_judged": total.judged, "shield_changed_share": total.share}


def evaluate_policy(
    policy: EgoPolicy,
    scenario: ScenarioConfig,
    episodes: int = 200,
    seed: int = 1_000_000,
    worlds: int = 50,
    highway_policy: HighwayPolicy | None = None,
) -> dict[str, float]:
    """Summary of `episodes` held-out episodes of a policy (e.g. a learner's greedy action),
    optionally against a learned highway policy."""
    return summarize(run_episodes(policy, scenario, episodes, seed, worlds, highway_policy))
