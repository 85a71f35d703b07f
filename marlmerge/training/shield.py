"""Gap acceptance's shield in the training loop (`TrainConfig.shield`).

While collecting, the learner's command for each acting vehicle passes through `GapShield`, as
the grid's `@shield` (or `@shield-left`) passes a trained policy's: the vehicle drives what the
shield lets through, and the replay keeps that command, so the learner's Q (or critic) is of
the commands actually driven (shielded learning, Alshiekh et al., AAAI 2018). The policy learns
to arrive where the shield has nothing to overrule; it is meant to be deployed behind the same
shield (`quadq@shield:RUN`), which is how the run's `evaluation.json` measures it.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from marlmerge.config import ScenarioConfig
from marlmerge.config.training import TrainConfig
from marlmerge.policies.gap_acceptance import GapShield, grid_shield


def make_train_shield(cfg: TrainConfig, scen: ScenarioConfig) -> GapShield | None:
    """The run's shield (None for `shield = "none"`), refused before any work, naming the key,
    where the scenario cannot take it (`GapShield`'s own checks: a chosen join point, or the
    left-lane shield without left-lane features)."""
    if cfg.shield == "none":
        return None
    try:
        return grid_shield(scen, cfg.shield == "shield-left")
    except ValueError as e:
        raise ValueError(f"shield = {cfg.shield!r} on scenario {cfg.scenario!r}: {e}") from None


def shielded(shield: GapShield | None, obs: Tensor, acted: dict[str, Tensor]) -> dict[str, Tensor]:
    """`acted` with its `action` [..., 1] (m/s^2) replaced by what `shield` lets through for
    the observations `obs` [..., F] (unchanged without a shield)."""
    if shield is None:
        return acted
    action = acted["action"]
    flat_obs = obs.reshape(-1, obs.shape[-1]).cpu().numpy()
    driven = shield(flat_obs, action.reshape(-1, 1).cpu().numpy())
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
