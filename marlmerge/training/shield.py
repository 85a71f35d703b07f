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
from marlmerge.policies.gap_acceptance import GapShield
from marlmerge.sim.observation import shows_left_lane


def make_train_shield(cfg: TrainConfig, scen: ScenarioConfig) -> GapShield | None:
    """The run's shield (None for `shield = "none"`), refused before any work where the
    scenario cannot take it."""
    if cfg.shield == "none":
        return None
    where = f"shield = {cfg.shield!r} on scenario {cfg.scenario!r}"
    if scen.ego.chooses_join:
        raise ValueError(
            f"{where}: ego.join = {scen.ego.join!r} leaves the join to the policy; the shield "
            "judges joins at the overlap point (use ego.join = 'forced')"
        )
    left = cfg.shield == "shield-left"
    if left and not shows_left_lane(scen):
        raise ValueError(
            f"{where}: the shield reads the left lane, which ego.observation = "
            f"{scen.ego.observation!r} does not show (use 'extended' or 'extended_accel')"
        )
    return GapShield(scen, watch_left=left, cap_in_lane=left, keep_rolling=left)


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
    """The greedy `policy` (obs [B, F] -> action [B, 1]) with its commands through `shield`."""
    if shield is None:
        return policy
    return lambda obs: shielded(shield, obs, {"action": policy(obs)})["action"]
