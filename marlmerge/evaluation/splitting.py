"""Crash rates by splitting at attention lapses: `marlmerge estimate --method split`.

Where a collision needs a lapse of the driver behind the ego's gap (`driver.lapse_rate_per_h`),
the rate is a sum over the step at which that lapse begins. Splitting runs that sum instead of
sampling it (conditional Monte Carlo over the lapse's start, its terms subsampled):

- the **trunk** of an episode is its road with that driver never beginning a lapse at a
  critical step (`marlmerge.sim.lapses`), each such step weighing 1 - p;
- a critical step of class c is a **branch point** with probability r_c (`BRANCH_P`, drawn
  from a hash of the road's key, step and vehicle, so the trunk and its branches agree);
- **branch** j replays the same road from its seed and begins the lapse at the j-th branch
  point, weighing (1 - p)^k p / r_c for the k critical steps before it; after it, every draw is
  natural.

Each episode's value is z = w_trunk 1[event in the trunk] + sum_j w_j 1[event in branch j].
Its expectation is the natural rate (each first lapse the trunk leaves out is run with
probability r_c and counted 1 / r_c times), the episodes are independent, and the estimate is
mean z with the normal 95 % interval of that mean. The summed weights w_trunk + sum_j w_j have
expectation 1 as well: their mean is the check `mean_weight`.

A branch must pass the trunk's steps exactly, which holds when the policy answers each world's
observation alone (a batched network's rows can differ in the last bit with the batch's make-up).
Every branch checks it: its forced lapse has to begin at its own branch point. A branch whose
replay drifted is counted in `replay_mismatches` and its episode still counts as run; the
estimate says so, since the sum then leaves out or repeats a term.

The cost is every simulated episode, the trunks and the branches: `episodes` in the report.
Traffic that needs no lapse to collide is in the trunk with weight near 1, as in Monte Carlo.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.evaluation.metrics import event_mask, weighted_mean_estimate
from marlmerge.sim.layout import N_LAPSE_CLASSES
from marlmerge.sim.proposal import ST_LAPSE_N, Proposal

if TYPE_CHECKING:
    from marlmerge.evaluation.rollout import EgoPolicy

BRANCH_P = (1.0, 0.5, 0.25, 0.1)
"""Per lapse class, the chance that a critical step is a branch point: near the square root of
the share of such lapses that end in a collision (44 %, 9 %, 2.3 %, 0.2 % by class,
`marlmerge.sim.lapses.CLASS_EDGES`), scaled so class 0 always branches. A branch's variance
grows as 1 / r and its cost as r; their product over the classes is least with r_c
proportional to the square root of the class's collision share."""


def split_proposal(cfg: ScenarioConfig) -> Proposal:
    """The scenario's own traffic with the lapses behind the ego's gap split (`BRANCH_P`)."""
    if cfg.driver.lapse_rate_per_h <= 0.0:
        raise ValueError(
            f"estimate --method split: scenario {cfg.name!r} has no attention lapses "
            "(driver.lapse_rate_per_h = 0), so there is nothing to split; use --method is or mc"
        )
    return replace(Proposal.natural(cfg), lapse_split=BRANCH_P)


def _branch_points(draw_stats: np.ndarray) -> np.ndarray:
    """[E] branch points each episode passed (in a branch: up to and including its own)."""
    return draw_stats[:, ST_LAPSE_N : ST_LAPSE_N + N_LAPSE_CLASSES].sum(axis=1).astype(np.int64)


def split_batch(
    policy: EgoPolicy,
    cfg: ScenarioConfig,
    seeds: list[np.random.SeedSequence],
    worlds: int,
    event: str,
) -> dict[str, np.ndarray]:
    """The trunks of the episodes seeded `seeds` and every branch of each: the trunk's event and
    log weight [E], and per branch [M] its episode, event, log weight and whether its replay
    began the lapse at its own branch point."""
    from marlmerge.evaluation.rollout import rollout_first_egos

    proposal = split_proposal(cfg)
    n = len(seeds)
    trunk, _ = rollout_first_egos(
        policy, cfg, n, 0, worlds, road_seeds=seeds, proposal=proposal, lapse_branches=[-1] * n
    )
    points = _branch_points(trunk["draw_stats"])  # [E]
    of = np.repeat(np.arange(n), points)  # [M] the episode of each branch
    j = np.arange(of.size) - np.repeat(np.cumsum(points) - points, points)  # [M] its point
    data = {
        "event": event_mask(trunk["outcome"], event),
        "log_weight": trunk["log_weight"],
        "branch_of": of,
        "branch_event": np.zeros(of.size, dtype=bool),
        "branch_log_weight": np.zeros(of.size),
        "branch_replayed": np.ones(of.size, dtype=bool),
    }
    if of.size:
        branch, _ = rollout_first_egos(
            policy,
            cfg,
            of.size,
            0,
            worlds,
            road_seeds=[seeds[e] for e in of],
            proposal=proposal,
            lapse_branches=j.tolist(),
        )
        data["branch_event"] = event_mask(branch["outcome"], event)
        data["branch_log_weight"] = branch["log_weight"]
        data["branch_replayed"] = _branch_points(branch["draw_stats"]) == j + 1
    return data


def episode_values(batch: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Each episode's weighted events z [E] and summed weights [E] (trunk and branches)."""
    w = np.exp(batch["log_weight"])
    z = np.where(batch["event"], w, 0.0)
    bw = np.exp(batch["branch_log_weight"])
    np.add.at(z, batch["branch_of"], np.where(batch["branch_event"], bw, 0.0))
    np.add.at(w, batch["branch_of"], bw)
    return z, w


def split_estimate(parts: list[dict[str, np.ndarray]]) -> dict[str, Any]:
    """The splitting estimate from batches of `split_batch`: the rate, its 95 % interval and
    the keys `weighted_estimate` reports, with the episodes simulated (trunks and branches)."""
    z, w = (np.concatenate(x) for x in zip(*(episode_values(p) for p in parts), strict=True))
    y = np.concatenate(
        [np.where(p["event"], np.exp(p["log_weight"]), 0.0) for p in parts]
        + [np.where(p["branch_event"], np.exp(p["branch_log_weight"]), 0.0) for p in parts]
    )  # every leaf's weighted event
    return weighted_mean_estimate(z, y) | {
        "events": int(np.count_nonzero(y)),
        "mean_weight": float(np.mean(w)),
        "trunk_episodes": z.size,
        "branch_episodes": sum(p["branch_of"].size for p in parts),
        "replay_mismatches": int(sum(np.count_nonzero(~p["branch_replayed"]) for p in parts)),
    }
