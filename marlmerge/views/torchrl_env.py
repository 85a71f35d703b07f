"""A native torchrl view of the batched core: B worlds, one learning ego per world.

`BatchedMergeEnv` is a torchrl `EnvBase` with batch size `[B]`. Every world runs its own traffic
(scripted mainline drivers) and its own sequence of ramp vehicles; the ego of each world is the
agent. One env step is one `TrafficCore.rollout` (the action held for `sim.action_repeat`
simulator steps, rewards and observations computed by the core), exactly as in the PettingZoo
view; this view only reshapes its outputs into tensors. A world whose ego is done is reset by
torchrl's partial reset (`"_reset"` mask): the next ramp vehicle departs into the same flowing
traffic.

Keys (all with leading dim B):
    "observation" [B, F]   the ego's observation: F = 7 (the paper's state) or 16
                           (`ego.observation = "extended"`), `marlmerge.sim.observation`
    "action"      [B, A]   acceleration in m/s^2, clipped to the ego bounds (A = 1); with
                           `ego.join = "chosen"` A = 2, then the join in [-1, 1] (> 0: join
                           now; `marlmerge.sim.action`); NaN raises
    "reward"      [B, 1]   sum of the named terms over the env step
    "reward_terms", <term> [B, 1] each named term (`marlmerge.sim.reward.EGO_TERMS`)
    "outcome"     [B, 1]   int64 OUTCOME_* code of the ego (0 while running)
    "ego_time_s"  [B, 1]   time since the ego departed (frozen once its episode ended)
    "done" / "terminated" / "truncated" [B, 1]: terminated on success or collision, truncated when
                           stalled or out of time.
    "filter_interventions" [B, 1] int64, only with `ego.safety_filter`: simulator steps of the
                           ego's episode whose command the safety filter overrode.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from marlmerge.config import ScenarioConfig, require_ego
from marlmerge.config.presets import resolve_config
from marlmerge.sim import (
    OUTCOME_COLLISION,
    OUTCOME_SUCCESS,
    OUTCOME_TRUNCATED,
    Rollout,
    Roster,
    TrafficCore,
)
from marlmerge.sim.action import action_bounds, action_size, as_actions, split_actions
from marlmerge.sim.proposal import Proposal
from marlmerge.sim.reward import EGO_TERMS, total_reward
from marlmerge.sim.streams import ScenarioSource


class BatchedMergeEnv(EnvBase):
    """torchrl env over `TrafficCore`: `num_worlds` independent worlds stepped at once."""

    batch_locked = True

    def __init__(
        self,
        config: ScenarioConfig | str | Path | None = None,
        num_worlds: int = 16,
        seed: int | Sequence[int] = 0,
        overrides: dict[str, Any] | None = None,
        device: str | torch.device = "cpu",
        scenarios: Sequence[ScenarioConfig] | None = None,
        scenario_source: ScenarioSource | None = None,
        proposal: Proposal | None = None,
        world_groups: Sequence[int] | np.ndarray | None = None,
    ):
        """seed: one int for the batch, or one per world (`marlmerge.sim.streams`); scenarios:
        one per world, the traffic and road it runs; scenario_source: chooses each new road's
        traffic in place of `[sample]`'s draw, and the root key `"scenario_tag"` [B, 1] int64
        reports the tag of its choice; proposal: importance sampling of the traffic
        (`TrafficCore`); world_groups: [B] a group per world, each group running as an env of
        its worlds alone (`marlmerge.sim.core.draw_groups`)."""
        super().__init__(device=device, batch_size=torch.Size([num_worlds]))
        self.cfg = resolve_config(config, **(overrides or {}))
        require_ego(self.cfg, type(self).__name__)
        self.num_worlds = num_worlds
        self.core = TrafficCore(
            self.cfg,
            num_worlds,
            seed,
            scenarios=scenarios,
            scenario_source=scenario_source,
            proposal=proposal,
            world_groups=world_groups,
        )
        self.recorder: Callable[[Rollout], None] | None = None
        """Called with every env step's `Rollout` (evaluation records trajectories from its
        per-simulator-step ego trace)."""
        b = num_worlds
        self.action_size = action_size(self.cfg)
        self.observation_spec = Composite(
            observation=Unbounded((b, self.core.obs_size), dtype=torch.float32, device=device),
            reward_terms=Composite(
                {t: Unbounded((b, 1), dtype=torch.float32, device=device) for t in EGO_TERMS},
                shape=(b,),
                device=device,
            ),
            outcome=Unbounded((b, 1), dtype=torch.int64, device=device),
            ego_time_s=Unbounded((b, 1), dtype=torch.float32, device=device),
            shape=(b,),
            device=device,
        )
        if self.cfg.ego.safety_filter:
            self.observation_spec["filter_interventions"] = Unbounded(
                (b, 1), dtype=torch.int64, device=device
            )
        if scenario_source is not None:
            self.observation_spec["scenario_tag"] = Unbounded(
                (b, 1), dtype=torch.int64, device=device
            )
        self.action_spec = ego_action_spec(self.cfg, b, device)
        self.reward_spec = Unbounded((b, 1), dtype=torch.float32, device=device)
        self.full_done_spec = Composite(
            {
                k: Categorical(2, (b, 1), dtype=torch.bool, device=device)
                for k in ("done", "terminated", "truncated")
            },
            shape=(b,),
            device=device,
        )

    # ------------------------------------------------------------------ torchrl hooks
    def _set_seed(self, seed: int | None) -> None:
        self.core.reset(seed=seed)

    def sim_state(self) -> dict[str, Any]:
        """The simulation's state, for checkpoints (`load_sim_state` continues bit for bit)."""
        return {"core": self.core.state_dict()}

    def load_sim_state(self, saved: dict[str, Any]) -> None:
        """Restore `sim_state`; the next full reset keeps every world as it is."""
        self.core.load_state_dict(saved["core"])
        self.resume_without_reset()

    def resume_without_reset(self) -> None:
        """The next full reset keeps every world as it is (its ego mid-episode included), so a
        collector built on a restored core continues where the saved run stopped."""
        self._keep_on_reset = True

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        mask = np.ones(self.num_worlds, dtype=bool)
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict.get("_reset").reshape(self.num_worlds).cpu().numpy()
        elif getattr(self, "_keep_on_reset", False):
            mask = np.zeros(self.num_worlds, dtype=bool)
            self._keep_on_reset = False
        self.core.next_ego(mask)
        ego_obs, _ = self.core.observe()
        zeros = np.zeros((self.num_worlds, len(EGO_TERMS)))
        out = self._output(ego_obs, zeros, np.zeros(self.num_worlds, np.int64))
        del out["reward"]
        return out

    def _actions(self, tensordict: TensorDictBase) -> np.ndarray:
        """The ego actions [B] (accelerations) or [B, 2] (with the join) of a step; NaN or
        infinite values raise, naming the world."""
        action = required_key(tensordict, "action").to(torch.float64).cpu().numpy()
        return as_actions(action, (self.num_worlds, self.action_size))

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = self._simulate(self._actions(tensordict))
        return self._output(out.ego_obs, out.ego_terms, out.ego_outcome)

    def _simulate(
        self, action: np.ndarray, roster: Roster | None = None, roster_cmd: np.ndarray | None = None
    ) -> Rollout:
        """One env step of the core: the ego actions `action` [B] or [B, 2] (and the roster's
        commands [B, K], NaN = scripted) held for `sim.action_repeat` simulator steps."""
        accel, join = split_actions(action)
        out = self.core.rollout(accel, roster=roster, roster_accel=roster_cmd, ego_join=join)
        if self.recorder is not None:
            self.recorder(out)
        return out

    def _output(
        self, ego_obs: np.ndarray, terms: np.ndarray, outcome: np.ndarray
    ) -> TensorDictBase:
        """The root keys from a step's observations [B, F], summed terms [B, len(EGO_TERMS)] and
        outcomes."""
        b = self.num_worlds
        dev = self.device

        def col(a: np.ndarray, dtype: torch.dtype = torch.float32) -> torch.Tensor:
            return torch.as_tensor(np.asarray(a).reshape(b, 1), dtype=dtype, device=dev)

        terminated = (outcome == OUTCOME_SUCCESS) | (outcome == OUTCOME_COLLISION)
        truncated = outcome == OUTCOME_TRUNCATED
        out = TensorDict(
            {
                "observation": torch.as_tensor(ego_obs, device=dev),
                "reward": col(total_reward(terms)),
                "reward_terms": TensorDict(
                    {t: col(terms[:, i]) for i, t in enumerate(EGO_TERMS)}, batch_size=[b]
                ),
                "outcome": col(outcome, torch.int64),
                "ego_time_s": col(self.core.state.ego_time_s.copy()),
                "done": col(terminated | truncated, torch.bool),
                "terminated": col(terminated, torch.bool),
                "truncated": col(truncated, torch.bool),
            },
            batch_size=[b],
            device=dev,
        )
        if self.cfg.ego.safety_filter:
            out["filter_interventions"] = col(
                self.core.state.filter_interventions.copy(), torch.int64
            )
        if self.core.scenario_source is not None:
            out["scenario_tag"] = col(self.core.world_tag.copy(), torch.int64)
        return out


def seed_worlds(
    seeds: Sequence[int], worlds_per_seed: int
) -> tuple[list[np.random.SeedSequence], np.ndarray]:
    """S runs in one env of S x B worlds: each world's seed (world i of seed s seeded as world i
    of an env seeded with s, `marlmerge.sim.streams`) and its draw group [S x B] (each seed's
    worlds one group, `marlmerge.sim.core.draw_groups`: they run bit for bit as that env's,
    whatever the other seeds' worlds do)."""
    b = worlds_per_seed
    world_seeds = [np.random.SeedSequence(int(s), spawn_key=(i,)) for s in seeds for i in range(b)]
    return world_seeds, np.repeat(np.arange(len(seeds)), b)


def ego_action_spec(cfg: ScenarioConfig, b: int, device: Any) -> Bounded:
    """The ego's action spec [B, A] (`marlmerge.sim.action.action_bounds`)."""
    lo, hi = (torch.as_tensor(v).expand(b, len(v)) for v in action_bounds(cfg))
    return Bounded(lo, hi, (b, len(action_bounds(cfg)[0])), dtype=torch.float32, device=device)


def required_key(tensordict: TensorDictBase, key: str | tuple[str, ...]) -> torch.Tensor:
    """tensordict[key], or an error naming the key and the keys the step was given."""
    value = tensordict.get(key, None)
    if value is None:
        given = ", ".join(sorted(repr(k) for k in tensordict.keys()))
        raise KeyError(f"step: the tensordict has no {key!r} (its keys: {given})")
    return value
