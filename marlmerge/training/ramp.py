"""Training one shared-parameter merging policy under ramp flow: the parts `train` takes instead
of the ego's when the run's scenario has `ramp.flow_vph > 0`.

The env is `RampFlowTorchEnv` (B worlds, the `"ramp"` group of K columns); the run's learner acts
for every column at once (`RampGroupPolicy`: one policy, shared parameters), and every acting
agent's step is a transition of the one replay (`ramp_rows`), so K merging vehicles per world
feed it. The loop, the learner, the checkpoints and the policy file are the ego's
(`marlmerge.training.train`); `egos.csv` holds a row per merging vehicle whose merge ended.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from marlmerge.config import ScenarioConfig
from marlmerge.config.training import TrainConfig
from marlmerge.evaluation.ramp_flow import check_ramp_scenario
from marlmerge.training.loop import LearningGroup
from marlmerge.training.shield import TrainShield, shielded
from marlmerge.views.ramp_flow_torchrl import GROUP, RampFlowTorchEnv

RAMP_AGENTS = 8
"""Agent columns per world: more than the ramp and the merge hold at once at 1,200 veh/h."""


def check_ramp_training(cfg: TrainConfig, scen: ScenarioConfig) -> None:
    """What ramp-flow training does not combine with, refused before any work."""
    if cfg.levels.replay_fraction > 0.0 or cfg.select.every_sim_steps > 0:
        raise ValueError(
            f"scenario {cfg.scenario!r} runs ramp flow (ramp.flow_vph = {scen.ramp.flow_vph}); "
            "[levels] and [select] need the one ego's episodes: leave them out"
        )
    check_ramp_scenario(scen, f"scenario {cfg.scenario!r}")


def make_ramp_env(cfg: TrainConfig, scen: ScenarioConfig) -> RampFlowTorchEnv:
    """B worlds of the run's ramp-flow scenario, seeded from `cfg.seed`."""
    return RampFlowTorchEnv(scen, cfg.num_worlds, cfg.seed, RAMP_AGENTS)


class RampGroupPolicy:
    """Collector policy of the `"ramp"` group: the group's learner acts for all B x K columns
    (free columns too; the env ignores them), one shared policy, through `shield` if the run
    has one."""

    def __init__(self, group: LearningGroup, shield: TrainShield | None = None) -> None:
        self.group, self.shield = group, shield

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        obs = td.get((GROUP, "observation"))  # [B, K, F]
        b, k, f = obs.shape
        flat = obs.reshape(b * k, f)
        for key, value in shielded(self.shield, flat, self.group.act(flat)).items():
            td.set((GROUP, key), value.reshape(b, k, -1))
        return td


def ramp_rows(group: LearningGroup, batch: TensorDictBase) -> torch.Tensor:
    """The packed transitions [n, obs | action | reward | terminal | next_obs] of the agents
    that acted in a batch [B, T], less those whose merge was truncated (`dropped`)."""
    flat = batch.reshape(-1)
    now, nxt = flat.get(GROUP), flat.get("next").get(GROUP)
    keep = now.get("mask") & ~nxt.get("dropped")  # [B * T, K]
    acted = TensorDict(
        {key: now.get(key)[keep] for key in now.keys() if key not in ("reward_terms",)},
        batch_size=[int(keep.sum())],
    )
    return torch.cat(
        [
            now.get("observation")[keep],
            group.learner.replay_action(acted),
            nxt.get("reward")[keep],
            nxt.get("terminal")[keep].unsqueeze(-1).float(),
            nxt.get("observation")[keep],
        ],
        -1,
    )
