"""Gap acceptance's shield in the training loop (`TrainConfig.shield`, `shield_penalty`,
`shield_imitation`).

It drives, or it judges:

- **Drives** (`shield_penalty` and `shield_imitation` 0, `TrainConfig.shield_drives`): while
  collecting, the learner's command for each acting
  vehicle passes through `GapShield`, as the grid's `@shield` (or `@shield-left`) passes a
  trained policy's: the vehicle drives what the shield lets through, and the replay keeps that
  command, so the learner's Q (or critic) is of the commands actually driven (shielded learning,
  Alshiekh et al., AAAI 2018). The policy learns to arrive where the shield has nothing to
  overrule; it is meant to be deployed behind the same shield (`quadq@shield:RUN`), which is how
  the run's `evaluation.json` measures it.
- **Judges** (`shield_penalty` or `shield_imitation` > 0): the vehicle drives the learner's own
  command, so the learner sees where its commands lead, and the shield's verdicts train it:
  - `shield_penalty`: the policy writes `shield_cost` [..., 1], `shield_penalty` x |command -
    what the shield would let through| (m/s^2), which `marlmerge.training.loop.transition_rows`
    takes off the reward the replay keeps;
  - `shield_imitation`: before each update the shield judges the greedy command of every
    replayed state, and the loss pulls it towards the shield's where the shield would overrule
    it (`shield_teacher`, `FastQuadQUpdater.imitate`).

  Such a policy is meant to drive bare, and `evaluation.json` measures it so.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from marlmerge.config import ScenarioConfig
from marlmerge.config.training import JUDGING_KEYS, TrainConfig
from marlmerge.learners.base import Learner
from marlmerge.learners.quadq_flat import Teacher
from marlmerge.policies.gap_acceptance import GapShield, grid_shield

SHIELD_COST = "shield_cost"
"""The key of the judging shield's cost [..., 1] in a collected batch (reward units)."""


@dataclass(frozen=True)
class TrainShield:
    """The run's shield and what it does: drives (`penalty` and `imitation` 0) or judges
    (`penalty`: the reward lost per m/s^2 between the command and the shield's; `imitation`:
    the weight of the loss's imitation term)."""

    shield: GapShield
    penalty: float = 0.0
    imitation: float = 0.0

    @property
    def drives(self) -> bool:
        return self.penalty == 0.0 and self.imitation == 0.0


def make_train_shield(cfg: TrainConfig, scen: ScenarioConfig) -> TrainShield | None:
    """The run's shield (None for `shield = "none"`), refused before any work, naming the key,
    where the scenario cannot take it (`GapShield`'s own checks: a chosen join point, or the
    left-lane shield without left-lane features; a judging shield under ramp flow, whose
    transitions do not go through `transition_rows`)."""
    if cfg.shield == "none":
        return None
    for key in JUDGING_KEYS:
        value = getattr(cfg, key)
        if value > 0.0 and scen.ramp.flowing:
            raise ValueError(
                f"{key} = {value} on scenario {cfg.scenario!r}: a judging shield trains one "
                f"ego per world, not ramp flow (use {key} = 0)"
            )
    try:
        shield = grid_shield(scen, cfg.shield == "shield-left")
        return TrainShield(shield, cfg.shield_penalty, cfg.shield_imitation)
    except ValueError as e:
        raise ValueError(f"shield = {cfg.shield!r} on scenario {cfg.scenario!r}: {e}") from None


def deployed_shield(cfg: TrainConfig, scen: ScenarioConfig) -> GapShield | None:
    """The shield the run's policy is meant to drive behind (and is evaluated behind): the
    driving shield; none for a judging one."""
    return grid_shield(scen, cfg.shield == "shield-left") if cfg.shield_drives else None


def shield_teacher(shield: GapShield) -> Teacher:
    """The shield as a teacher (`QuadQLearner.imitate`): obs [N, d] and commands [N, 1] ->
    what it lets through [N, 1], on the commands' device."""

    def teach(obs: Tensor, command: Tensor) -> Tensor:
        driven = shield(obs.cpu().numpy(), command.cpu().numpy())
        return torch.as_tensor(driven, dtype=command.dtype).to(command.device)

    return teach


def teach(learner: Learner, shield: TrainShield | None) -> None:
    """Give the learner the shield as its teacher if the run has `shield_imitation`."""
    if shield is not None and shield.imitation > 0.0:
        learner.imitate(shield_teacher(shield.shield), shield.imitation)  # type: ignore[attr-defined]


def shielded(
    shield: TrainShield | None, obs: Tensor, acted: dict[str, Tensor]
) -> dict[str, Tensor]:
    """`acted` with its `action` [..., 1] (m/s^2) replaced by what the driving `shield` lets
    through for the observations `obs` [..., F]; with a `penalty`, `acted` and its
    `shield_cost` [..., 1]; unchanged without a shield or with one that only teaches."""
    if shield is None or (shield.imitation > 0.0 and shield.penalty == 0.0):
        return acted  # no shield, or one that teaches at the learner's updates (`teach`)
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
