"""Ramp flow as a batched torchrl env: B worlds, the torchrl agent group `"ramp"` of K columns.

Each column holds one ramp vehicle from the step it enters the ramp until its own merge ends
(`marlmerge.views.ramp_agents.RampAgentTable`, columns reused), so a shared-parameter policy acts
for every merging vehicle at once. The road never ends: the root `done` is always False, and
each agent's merge ends on its own.

Group keys (leading dims [B, K]):
    ("ramp", "observation")  [B, K, F]  the paper's state of the column's vehicle (F = 7;
                                        `ramp_agent_features`: 8 with `ego.join = "chosen"`,
                                        then `on_ramp`; zeros where the column is free)
    ("ramp", "mask")         [B, K]     the column holds an agent that acts in this step
    ("ramp", "action")       [B, K, A]  acceleration in m/s^2 within `ego.accel_bounds_mps2`
                                        (A = 1; with `ego.join = "chosen"` A = 2, then the
                                        join in [-1, 1], > 0: join now); NaN raises for an
                                        acting agent; free columns ignored
    ("ramp", "reward")       [B, K, 1]  the ego's terms for its own merge (`EGO_TERMS`, no jerk)
    ("ramp", "reward_terms", <term>)  [B, K, 1]
    ("ramp", "terminal")     [B, K]     in "next": its merge ended by success or collision in
                                        this step (its column may hold a new vehicle already)
    ("ramp", "dropped")      [B, K]     in "next": ... by truncation (not an outcome: learners
                                        drop that transition)
    ("ramp", "outcome")      [B, K]     in "next": int64 OUTCOME_* of the merge that ended in
                                        this step (0: none ended)
Root keys: "done", "terminated", "truncated" [B, 1], always False; "merged" [B, 1] int64 (the
world's ramp vehicles past the merge point so far).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from marlmerge.config import ScenarioConfig, check_count
from marlmerge.config.presets import resolve_config
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_NONE, OUTCOME_SUCCESS, TrafficCore
from marlmerge.sim.action import action_bounds, action_size
from marlmerge.sim.observation import ramp_agent_features
from marlmerge.sim.reward import EGO_TERMS, total_reward
from marlmerge.views.ramp_agents import RampAgentTable

GROUP = "ramp"


class RampFlowTorchEnv(EnvBase):
    """B worlds of ramp flow with the `"ramp"` agent group (see the module docstring)."""

    def __init__(
        self,
        config: ScenarioConfig | str | Path | None = None,
        num_worlds: int = 16,
        seed: int | Sequence[int] = 0,
        max_agents: int = 8,
        overrides: dict[str, Any] | None = None,
        device: str | torch.device = "cpu",
    ):
        super().__init__(device=device, batch_size=torch.Size([num_worlds]))
        self.cfg = resolve_config(config, **(overrides or {}))
        if not self.cfg.ramp.flowing:
            raise ValueError(
                f"RampFlowTorchEnv needs ramp flow: ramp.flow_vph = {self.cfg.ramp.flow_vph}"
            )
        max_agents = check_count("max_agents", max_agents)
        self.num_worlds, self.n_agents = num_worlds, max_agents
        self.core = TrafficCore(self.cfg, num_worlds, seed)
        self.table = RampAgentTable(self.core, max_agents, reuse=True)
        self.table.assign()
        b, k, dev = num_worlds, max_agents, device
        f = len(ramp_agent_features(self.cfg))
        self.action_size = m = action_size(self.cfg)
        lo, hi = (torch.as_tensor(v).expand(b, k, m) for v in action_bounds(self.cfg))

        def flag(*shape: int) -> Unbounded:
            return Unbounded(shape, dtype=torch.bool, device=dev)

        self.observation_spec = Composite(
            ramp=Composite(
                observation=Unbounded((b, k, f), dtype=torch.float32, device=dev),
                mask=flag(b, k),
                terminal=flag(b, k),
                dropped=flag(b, k),
                outcome=Unbounded((b, k), dtype=torch.int64, device=dev),
                reward_terms=Composite(
                    {t: Unbounded((b, k, 1), dtype=torch.float32, device=dev) for t in EGO_TERMS},
                    shape=(b, k),
                    device=dev,
                ),
                shape=(b, k),
                device=dev,
            ),
            merged=Unbounded((b, 1), dtype=torch.int64, device=dev),
            shape=(b,),
            device=dev,
        )
        self.full_action_spec = Composite(
            ramp=Composite(
                action=Bounded(lo, hi, (b, k, m), dtype=torch.float32, device=dev),
                shape=(b, k),
                device=dev,
            ),
            shape=(b,),
            device=dev,
        )
        self.full_reward_spec = Composite(
            ramp=Composite(
                reward=Unbounded((b, k, 1), dtype=torch.float32, device=dev),
                shape=(b, k),
                device=dev,
            ),
            shape=(b,),
            device=dev,
        )
        self.full_done_spec = Composite(
            {
                key: Categorical(2, (b, 1), dtype=torch.bool, device=dev)
                for key in ("done", "terminated", "truncated")
            },
            shape=(b,),
            device=dev,
        )

    # ------------------------------------------------------------------ torchrl hooks
    def _set_seed(self, seed: int | None) -> None:
        self.core.reset(seed=seed)
        self.table.clear()
        self.table.assign()

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        """The road goes on: a reset returns the current state (a fresh road: `set_seed`)."""
        b, k = self.num_worlds, self.n_agents
        if getattr(self, "_keep_on_reset", False):
            self._keep_on_reset = False
        no = np.zeros((b, k), dtype=bool)
        none = np.zeros((b, k), dtype=np.int64)
        return self._output(np.zeros((b, k, len(EGO_TERMS))), none, no, with_reward=False)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        b, k, m = self.num_worlds, self.n_agents, self.action_size
        act = tensordict.get((GROUP, "action"))
        if act.shape[-3:] != (b, k, m):
            raise ValueError(f"('ramp', 'action') must have shape {(b, k, m)}, got {act.shape}")
        cmd = act.reshape(b, k, m).to(torch.float64).cpu().numpy()
        live = self.table.live
        bad = live & ~np.isfinite(cmd).all(-1)
        if bad.any():
            w, a = (int(i[0]) for i in np.nonzero(bad))
            raise ValueError(
                f"action of ramp agent {a} in world {w} must be finite, got {cmd[w, a].tolist()}"
            )
        cmd = np.where(live[..., None], cmd, np.nan)
        out = self.core.rollout(
            np.full(b, np.nan),
            roster=self.table.roster(),
            roster_accel=cmd[..., 0],
            roster_join=cmd[..., 1] if m > 1 else None,
        )
        outcome = self.table.outcomes()
        ended = outcome != OUTCOME_NONE
        terminal = (outcome == OUTCOME_SUCCESS) | (outcome == OUTCOME_COLLISION)
        self.table.release(ended)
        self.table.assign()
        terms = np.where(live[..., None], out.hw_terms, 0.0)
        return self._output(terms, outcome, ended & ~terminal, with_reward=True)

    # ------------------------------------------------------------------ checkpoints
    def sim_state(self) -> dict[str, Any]:
        """The simulation and the agent table, for checkpoints (`load_sim_state`)."""
        t = self.table
        names = ("ids", "since_s", "stall_s", "newest", "used")
        return {
            "core": self.core.state_dict(),
            "table": {name: getattr(t, name).copy() for name in names},
        }

    def load_sim_state(self, saved: dict[str, Any]) -> None:
        self.core.load_state_dict(saved["core"])
        for key, value in saved["table"].items():
            getattr(self.table, key)[:] = value
        self.resume_without_reset()

    def resume_without_reset(self) -> None:
        """A collector built on a restored env continues where the saved run stopped (a reset
        never changes the road here)."""
        self._keep_on_reset = True

    def _output(
        self, terms: np.ndarray, outcome: np.ndarray, dropped: np.ndarray, with_reward: bool
    ) -> TensorDictBase:
        b, k, dev = self.num_worlds, self.n_agents, self.device
        obs = self.core.observe_agents(self.table.roster())

        def col(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.asarray(a).reshape(b, k, 1), dtype=torch.float32, device=dev)

        group = {
            "observation": torch.as_tensor(obs, dtype=torch.float32, device=dev),
            "mask": torch.as_tensor(self.table.live.copy(), device=dev),
            "terminal": torch.as_tensor(
                (outcome == OUTCOME_SUCCESS) | (outcome == OUTCOME_COLLISION), device=dev
            ),
            "dropped": torch.as_tensor(dropped, device=dev),
            "outcome": torch.as_tensor(outcome, dtype=torch.int64, device=dev),
            "reward_terms": TensorDict(
                {t: col(terms[..., i]) for i, t in enumerate(EGO_TERMS)}, batch_size=[b, k]
            ),
        }
        if with_reward:
            group["reward"] = col(total_reward(terms))
        no = torch.zeros((b, 1), dtype=torch.bool, device=dev)
        merged = self.core.state.ramp_passed.reshape(b, 1).copy()
        return TensorDict(
            {
                GROUP: TensorDict(group, batch_size=[b, k], device=dev),
                "merged": torch.as_tensor(merged, device=dev),
                "done": no,
                "terminated": no.clone(),
                "truncated": no.clone(),
            },
            batch_size=[b],
            device=dev,
        )
