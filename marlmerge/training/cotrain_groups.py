"""The two learning groups of co-training and what they act and learn from.

The ego (the paper's quadratic-Q learner) and the highway group (a residual quadratic Q, or PPO
with `highway_algorithm = "ppo"`) of one seed: how each is made and explores, the collector
policy that acts for both (`JointPolicy`), the transitions each learns from, and the ego's
policy file. `marlmerge.training.cotrain` runs them.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torch import Tensor

from marlmerge.config import ScenarioConfig, to_dict
from marlmerge.config.cotraining import CoTrainConfig
from marlmerge.config.scenario import InteractionConfig
from marlmerge.io.policy_file import read_policy, write_policy
from marlmerge.learners.highway import (
    OFFSET_BOUNDS_MPS2,
    HighwayPolicy,
    ResidualHighwayPolicy,
    snapshot_policy,
)
from marlmerge.learners.ppo import PPOHighwayLearner, critic_observation, critic_size
from marlmerge.learners.quadq import GaussianExploration, QuadraticQNet
from marlmerge.learners.quadq_learner import QuadQLearner
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_TRUNCATED
from marlmerge.training.loop import LearningGroup, make_replay
from marlmerge.views.torchrl_groups import GROUP


class JointPolicy:
    """Sets the ego's `"action"` and the highway group's `("highway", "action")`.

    ego(obs [B, d]) -> [B, 1]; highway[o](obs [n, K, 12]) -> [n, K, 1] for the worlds whose
    `"opponent"` is o (worlds with -1 are scripted: their actions are ignored, zeros are sent).
    A highway policy may return a dict instead: `"action"` and what else its learner keeps from
    acting (PPO's pre-squash sample `"z"`), each [n, K, m], set under `("highway", key)`.
    """

    def __init__(
        self,
        ego: Callable[[Tensor], Tensor],
        highway: list[Callable[[Tensor], Tensor | dict[str, Tensor]]],
    ) -> None:
        self.ego = ego
        self.highway = highway

    @torch.no_grad()
    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        for key, value in self.actions(td).items():
            td.set(key, value)
        return td

    @torch.no_grad()
    def actions(self, td: TensorDictBase) -> dict[Any, Tensor]:
        """What `__call__` sets: `"action"` [B, 1] and `("highway", key)` [B, K, m]."""
        acted = {"action": self.ego(td.get("observation"))}
        obs = td.get((GROUP, "observation"))  # [B, K, 12]
        opp = td.get("opponent").reshape(-1)  # [B]
        out: dict[str, Tensor] = {"action": torch.zeros(*obs.shape[:-1], 1)}
        for o in torch.unique(opp).tolist():
            if o >= 0:
                sel = opp == o
                hw = self.highway[o](obs[sel])
                for key, value in (hw if isinstance(hw, dict) else {"action": hw}).items():
                    out.setdefault(key, torch.zeros(*obs.shape[:-1], value.shape[-1]))[sel] = value
        acted.update({(GROUP, key): value for key, value in out.items()})
        return acted


def save_ego_policy(path: Path, net: QuadraticQNet, cfg: CoTrainConfig, scen: ScenarioConfig):
    """The ego in the `policy.pt` format of `train.py` (readable by `load_policy`, the grid);
    copies of the weights, which are views of a fast path's flat buffer (of every seed's, when
    seeds are co-trained in one process) that the file must not carry."""
    weights = {k: v.clone() for k, v in net.state_dict().items()}
    write_policy(
        path,
        "ego",
        "quadq",
        (net.action_low, net.action_high),
        {"net": weights, "hidden": cfg.hidden},
        to_dict(cfg),
        to_dict(scen),
    )


def make_group(
    cfg: CoTrainConfig,
    name: str,
    obs_dim: int,
    bounds: tuple[float, float],
    seed: int,
    updates_per_sim_step: float,
    init_weights: dict[str, Tensor] | None = None,
) -> LearningGroup:
    """A quadratic-Q learning group: network from `seed`, exploration noise `seed + 1`,
    minibatches `seed + 2`; it explores only in the phases that say so (`explore`)."""
    sample_gen = torch.Generator().manual_seed(seed + 2)
    learner = QuadQLearner(
        obs_dim,
        cfg.hidden,
        *bounds,
        gamma=cfg.gamma,
        lr=cfg.lr,
        target_update_period=cfg.target_update_period,
        exploration=GaussianExploration(0.0, 0.0, 1, *bounds),
        update_path=cfg.update_path,
        updates_per_call=cfg.updates_per_call,
        seed=seed,
        sample_generator=sample_gen,
        init_weights=init_weights,
        device=cfg.device,
    )
    return LearningGroup(
        name,
        learner,
        make_replay(cfg.replay_capacity, sample_gen, cfg.device),
        noise_gen=torch.Generator().manual_seed(seed + 1),
        sample_gen=sample_gen,
        updates_per_sim_step=updates_per_sim_step,
        batch_size=cfg.batch_size,
        learning_starts=cfg.learning_starts,
        loss_log_every=cfg.loss_log_every,
        exploring=False,
    )


def make_ppo_group(cfg: CoTrainConfig, obs_dim: int, ego_dim: int, k: int, seed: int):
    """The highway group with the PPO learner of `[ppo]` (networks from `seed`, exploration
    noise `seed + 1`, minibatch order `seed + 2`); it always samples while it learns."""
    p = cfg.ppo
    learner = PPOHighwayLearner(
        obs_dim,
        critic_size(obs_dim, ego_dim, k, p.critic),
        cfg.hidden,
        *highway_bounds(cfg),
        gamma=cfg.gamma,
        lmbda=p.gae_lambda,
        lr=p.lr,
        clip_epsilon=p.clip_epsilon,
        entropy_coeff=p.entropy_coeff,
        critic_coeff=p.critic_coeff,
        epochs=p.epochs,
        minibatches=p.minibatches,
        max_grad_norm=p.max_grad_norm,
        init_std=p.init_std,
        seed=seed,
        device=cfg.device,
    )
    sample_gen = torch.Generator().manual_seed(seed + 2)
    rollout = cfg.num_worlds * cfg.env_steps_per_batch * k  # agent steps of one batch, at most
    return LearningGroup(
        GROUP,
        learner,
        make_replay(rollout, sample_gen, cfg.device),
        noise_gen=torch.Generator().manual_seed(seed + 1),
        sample_gen=sample_gen,
        updates_per_sim_step=0.0,
        batch_size=cfg.batch_size,
        learning_starts=0,
        loss_log_every=1,
        exploring=False,
    )


def highway_bounds(cfg: CoTrainConfig) -> tuple[float, float]:
    """What the highway learner's action is squashed into: the adjustment's m/s^2 or the
    desired-speed factor's range (`CoTrainConfig.highway_action`)."""
    if cfg.highway_action == "desired_speed":
        return cfg.highway_speed_factor_bounds
    return OFFSET_BOUNDS_MPS2


def highway_snapshot(
    cfg: CoTrainConfig, scen: ScenarioConfig, weights: dict[str, Tensor]
) -> HighwayPolicy:
    """The greedy highway policy of pool weights of `cfg`'s highway learner and action."""
    return snapshot_policy(
        weights,
        cfg.hidden,
        scen,
        highway_bounds(cfg),
        cfg.highway_algorithm,
        cfg.highway_action,
        cfg.highway_envelope,
    )


def explore(group: LearningGroup, start: float, end: float, decay_sim_steps: int) -> None:
    """The group explores this phase: Gaussian noise whose std falls linearly from `start` to
    `end` m/s^2 over `decay_sim_steps` of the phase (`explore_step`), then constant."""
    net = group.learner.net  # type: ignore[attr-defined]
    group.learner.exploration = GaussianExploration(  # type: ignore[attr-defined]
        start, end, max(decay_sim_steps, 1), net.action_low, net.action_high
    )
    group.exploring = start > 0.0 or end > 0.0


def ego_init_weights(cfg: CoTrainConfig, scen: ScenarioConfig) -> dict[str, Tensor] | None:
    """The network weights of `cfg.ego_init` (checked against the run's settings), or None."""
    if not cfg.ego_init:
        return None
    saved = read_policy(cfg.ego_init, "ego")
    if saved["algorithm"] != "quadq":
        raise ValueError(f"ego_init {cfg.ego_init!r} is not a quadratic-Q policy")
    hidden = saved["policy_state"]["hidden"]
    if hidden != cfg.hidden:
        raise ValueError(f"ego_init {cfg.ego_init!r} has hidden={hidden}, not {cfg.hidden}")
    if tuple(saved["action_bounds_mps2"]) != tuple(scen.ego.accel_bounds_mps2):
        raise ValueError(
            f"ego_init {cfg.ego_init!r} acts in {saved['action_bounds_mps2']} m/s^2, the "
            f"scenario's ego in {scen.ego.accel_bounds_mps2}"
        )
    return saved["policy_state"]["net"]


def highway_rows(batch: TensorDictBase, residual: ResidualHighwayPolicy) -> Tensor:
    """The learning highway agents' transitions of a batch [B, T, K]: acting agents only; an
    agent leaving downstream is dropped (an absorbing 0 would pay agents to race off the road), a
    collision is terminal with its penalty. The action is the adjustment the net learns (the
    applied acceleration, after clipping, minus the IDM part)."""
    nxt = batch.get("next")
    valid = batch.get((GROUP, "mask")) & (batch.get("opponent") >= 0)  # [B, T, K]
    keep = valid & ~nxt.get((GROUP, "exited"))
    obs = batch.get((GROUP, "observation"))[keep]
    return torch.cat(
        [
            obs,
            batch.get((GROUP, "action"))[keep] - residual.base(obs),
            nxt.get((GROUP, "reward"))[keep],
            nxt.get((GROUP, "left_road"))[keep].float().unsqueeze(-1),
            nxt.get((GROUP, "observation"))[keep],
        ],
        -1,
    )


def shape_with_ego_value(
    batch: TensorDictBase, net: QuadraticQNet, gamma: float, weight: float, sign: float
) -> Tensor:
    """Add `CoTrainConfig.ego_value_shaping` to the highway group's reward of a batch [B, T]
    in place: `sign * weight * (V(s) - gamma * (1 - terminated) * V(s'))` for every agent of
    the world, V = the ego network's max_a Q (C(s)) on the ego's observations. Returns the
    shaping [B, T, 1]."""
    nxt = batch.get("next")
    with torch.no_grad():
        dev = next(net.parameters()).device  # the learner's; the batch is on the CPU
        value = net.max_value(batch.get("observation").to(dev)).cpu()  # [B, T, 1]
        next_value = net.max_value(nxt.get("observation").to(dev)).cpu()  # [B, T, 1]
    not_term = (~nxt.get("terminated")).to(value.dtype)  # [B, T, 1]
    shaping = sign * weight * (value - gamma * not_term * next_value)  # [B, T, 1]
    reward = nxt.get((GROUP, "reward"))  # [B, T, K, 1]
    nxt.set((GROUP, "reward"), reward + shaping.unsqueeze(-2).to(reward.dtype))
    return shaping


def rule_acting(
    ego: Callable[[Tensor], Tensor], rule: Callable[[np.ndarray], np.ndarray], n_rule: int
) -> Callable[[Tensor], Tensor]:
    """The ramp vehicles' commands of a seed's worlds: the ego's, except in the last `n_rule`
    worlds, where the rule (gap acceptance) drives on the same observation
    (`CoTrainConfig.fairness_worlds`)."""

    def act(obs: Tensor) -> Tensor:  # obs [B, d] -> [B, m]
        action = ego(obs)
        ruled = torch.as_tensor(rule(obs[-n_rule:].cpu().numpy()), dtype=action.dtype)
        return torch.cat([action[:-n_rule], ruled.to(action.device)])

    return act


RULE_FAILURE_TERMS = ("ego_collision", "ego_stall")
"""The interaction terms of a ramp vehicle's failures (`InteractionConfig`), which do not count
for the highway agents where the rule drives it; the near-failures (hard braking, unsafe gaps)
still do, as pressing a careful driver is what an adversary does."""


def count_against_in_rule_worlds(
    batch: TensorDictBase, n_rule: int, weight: float, interaction: InteractionConfig
) -> None:
    """In the last `n_rule` worlds of a batch [B, T] (the rule driver's,
    `CoTrainConfig.fairness_worlds`), in place: the highway group's failure terms
    (`RULE_FAILURE_TERMS`) are taken off its reward, and at the step the rule's ramp vehicle
    collides or runs out of time every learning agent acting in that world loses `weight` x
    `w_ego_collision` or `w_ego_stall`: the rule's failure is the whole group's, whoever was
    beside it."""
    nxt = batch.get("next")
    terms = nxt.get((GROUP, "reward_terms"))
    rule = nxt.get((GROUP, "reward"))[-n_rule:]  # [n, T, K, 1]
    failures = sum(terms.get(t)[-n_rule:] for t in RULE_FAILURE_TERMS)  # [n, T, K, 1]
    done = nxt.get("done")[-n_rule:]  # [n, T, 1]
    outcome = nxt.get("outcome")[-n_rule:]  # [n, T, 1]
    cost = torch.where(outcome == OUTCOME_COLLISION, interaction.w_ego_collision, 0.0)
    cost = torch.where(outcome == OUTCOME_TRUNCATED, interaction.w_ego_stall, cost)
    cost = weight * cost * done  # [n, T, 1]
    acting = batch.get((GROUP, "mask"))[-n_rule:].unsqueeze(-1)  # [n, T, K, 1]
    reward = nxt.get((GROUP, "reward")).clone()
    shared = acting * cost.unsqueeze(-2)  # [n, T, K, 1]
    reward[-n_rule:] = rule - failures.to(rule.dtype) - shared.to(rule.dtype)
    nxt.set((GROUP, "reward"), reward)


def ppo_highway_rows(batch: TensorDictBase, learner: PPOHighwayLearner, critic: str) -> Tensor:
    """The learning highway agents' rollout of a batch [B, T, K] as PPO rows (GAE advantages
    per agent slot; `PPOHighwayLearner.rollout_rows`), from the pre-squash samples `z` the
    policy acted with; `critic` ("local" / "central") is the learner's critic input."""
    nxt = batch.get("next")
    obs, next_obs = batch.get((GROUP, "observation")), nxt.get((GROUP, "observation"))
    valid = batch.get((GROUP, "mask")) & (batch.get("opponent") >= 0)  # [B, T, K]
    left, exited = nxt.get((GROUP, "left_road")), nxt.get((GROUP, "exited"))
    world_done = nxt.get("done").expand_as(valid)  # [B, T, 1] -> [B, T, K]
    return learner.rollout_rows(
        obs,
        critic_observation(obs, batch.get("observation"), critic),
        batch.get((GROUP, "z")),
        nxt.get((GROUP, "reward")),
        critic_observation(next_obs, nxt.get("observation"), critic),
        valid,
        left | world_done,
        left & ~exited,
        exited,
    )
