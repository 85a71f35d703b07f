"""Gap acceptance's shield in the training loop (`TrainConfig.shield`, `shield_penalty`).

It drives, or it judges:

- **Drives** (`shield_penalty = 0`): while collecting, the learner's command for each acting
  vehicle passes through `GapShield`, as the grid's `@shield` (or `@shield-left`) passes a
  trained policy's: the vehicle drives what the shield lets through, and the replay keeps that
  command, so the learner's Q (or critic) is of the commands actually driven (shielded learning,
  Alshiekh et al., AAAI 2018). The policy learns to arrive where the shield has nothing to
  overrule; it is meant to be deployed behind the same shield (`quadq@shield:RUN`), which is how
  the run's `evaluation.json` measures it.
- **Judges** (`shield_penalty > 0`): the vehicle drives the learner's own command, and the
  policy writes `shield_cost` [..., 1], `shield_penalty` x |command - what the shield would let
  through| (m/s^2), which `marlmerge.training.loop.transition_rows` takes off the reward the
  replay keeps. The learner sees where its own commands lead and pays for those gap acceptance
  would overrule; it is meant to drive bare, and `evaluation.json` measures it so.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from marlmerge.config import ScenarioConfig
from marlmerge.config.training import TrainConfig
from marlmerge.policies.gap_acceptance import GapShield, grid_shield

SHIELD_COST = "shield_cost"
"""The key of the judging shield's cost [..., 1] in a collected batch (reward units)."""


@dataclass(frozen=True)
class TrainShield:
    """The run's shield and what it does: drives (`penalty` 0) or judges (`penalty` > 0, the
    reward lost per m/s^2 between the command and the shield's)."""

    shield: GapShield
    penalty: float = 0.0


def make_train_shield(cfg: TrainConfig, scen: ScenarioConfig) -> TrainShield | None:
    """The run's shield (None for `shield = "none"`), refused before any work, naming the key,
    where the scenario cannot take it (`GapShield`'s own checks: a chosen join point, or the
    left-lane shield without left-lane features; a judging shield under ramp flow, whose
    transitions do not go through `transition_rows`)."""
    if cfg.shield == "none":
        return None
    if cfg.shield_penalty > 0.0 and scen.ramp.flowing:
        raise ValueError(
            f"shield_penalty = {cfg.shield_penalty} on scenario {cfg.scenario!r}: a judging "
            "shield trains one ego per world, not ramp flow (use shield_penalty = 0)"
        )
    try:
        return TrainShield(grid_shield(scen, cfg.shield == "shield-left"), cfg.shield_penalty)
    except ValueError as e:
        raise ValueError(f"shield = {cfg.shield!r} on scenario {cfg.scenario!r}: {e}") from None


def deployed_shield(cfg: TrainConfig, scen: ScenarioConfig) -> GapShield | None:
    """The shield the run's policy is meant to drive behind (and is evaluated behind): the
    driving shield; none for a judging one."""
    train_shield = make_train_shield(cfg, scen)
    if train_shield is None or train_shield.penalty > 0.0:
        return None
    return train_shield.shield


def shielded(
    shield: TrainShield | None, obs: Tensor, acted: dict[str, Tensor]
) -> dict[str, Tensor]:
    """`acted` with its `action` [..., 1] (m/s^2) replaced by what the driving `shield` lets
    through for the observations `obs` [..., F]; with a judging one, `acted` and its
    `shield_cost` [..., 1]; unchanged without a shield."""
    if shield is None:
        return acted
    action = acted["action"]
    command = action.reshape(-1, 1).cpu().numpy()
    driven = shield.shield(obs.reshape(-1, obs.shape[-1]).cpu().numpy(), command)
    if shield.penalty > 0.0:
        cost = shield.penalty * np.abs(driven - command)
        out = torch.as_tensor(cost, dtype=action.dtype).reshape(action.shape)
        return {**acted, SHIELD_COST: out.to(action.device)}
    out = torch.as_tensor(driven, dtype=action.dtype).reshape(action.shape)
    return {**acted, "action": out.to(action.device)}


def behind_shield(
    policy: Callable[[Tensor], Tensor], shield: GapShield | None
) -> Callable[[Tensor], Tensor]:
    """The greedy `policy` (obs [B, F] -> action [B, 1]) with its commands through `shield`, as
    the grid's `@shield` drives it (so its evaluation counts what the shield changed)."""
    if shield is None:
        return policy
    from marlmerge.evaluation.registry import ShieldedPolicy

    return ShieldedPolicy(policy, shield)
