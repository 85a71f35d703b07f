"""A native torchrl view of the batched core: B worlds, one learning ego per world.

`BatchedMergeEnv` is a torchrl `EnvBase` with batch size `[B]`. Every world runs its own traffic
(scripted mainline drivers) and its own sequence of ramp vehicles; the ego of each world is the
agent. One env step holds the action for `sim.action_repeat` simulator steps, like the PettingZoo
view. A world whose ego is done is reset by torchrl's partial reset (`"_reset"` mask): the next ramp
vehicle departs into the same flowing traffic.

Keys (all with leading dim B):
    "observation" [B, 7]   the paper's state, layout in `marlmerge.observation.EGO_FEATURES`
    "action"      [B, 1]   acceleration in m/s^2, clipped to the ego bounds; NaN raises
    "reward"      [B, 1]   sum of the named terms over the env step
    "reward_terms", <term> [B, 1] each named term (`marlmerge.reward.EGO_TERMS`)
    "outcome"     [B, 1]   int64 OUTCOME_* code of the ego (0 while running)
    "ego_time_s"  [B, 1]   time since the ego departed (frozen once its episode ended)
    "done" / "terminated" / "truncated" [B, 1]: terminated on success or collision, truncated when
                           stalled or out of time.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from marlmerge.config import ScenarioConfig
from marlmerge.core import (
    EGO,
    OUTCOME_COLLISION,
    OUTCOME_NONE,
    OUTCOME_SUCCESS,
    OUTCOME_TRUNCATED,
    EgoGaps,
    StepEvents,
    TrafficCore,
)
from marlmerge.env import resolve_config
from marlmerge.observation import EGO_FEATURES, ego_observation
from marlmerge.reward import EGO_TERMS, ego_reward_terms


class BatchedMergeEnv(EnvBase):
    """torchrl env over `TrafficCore`: `num_worlds` independent worlds stepped at once."""

    batch_locked = True

    def __init__(
        self,
        config: ScenarioConfig | str | Path | None = None,
        num_worlds: int = 16,
        seed: int = 0,
        overrides: dict[str, Any] | None = None,
        device: str | torch.device = "cpu",
    ):
        super().__init__(device=device, batch_size=torch.Size([num_worlds]))
        self.cfg = resolve_config(config, **(overrides or {}))
        self.num_worlds = num_worlds
        self.core = TrafficCore(self.cfg, batch_size=num_worlds, seed=seed)
        self.recorder: Callable[[TrafficCore, StepEvents, EgoGaps], None] | None = None
        """Called after every simulator step (evaluation records trajectories with it)."""
        b = num_worlds
        lo, hi = self.cfg.ego.accel_bounds_mps2
        self.observation_spec = Composite(
            observation=Unbounded((b, len(EGO_FEATURES)), dtype=torch.float32, device=device),
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
        self.action_spec = Bounded(lo, hi, (b, 1), dtype=torch.float32, device=device)
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
        zeros = np.zeros(self.num_worlds)
        out = self._output({t: zeros for t in EGO_TERMS}, np.zeros(self.num_worlds, np.int64))
        del out["reward"]
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").reshape(self.num_worlds).to(torch.float64).cpu().numpy()
        bad = ~np.isfinite(action)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"action of world {i} must be finite, got {action[i]}")
        summed, outcome = self._simulate(action)
        return self._output(summed, outcome)

    def _simulate(
        self,
        action: np.ndarray,
        highway_cmd: np.ndarray | None = None,
        after_step: Callable[[StepEvents, EgoGaps, np.ndarray], None] | None = None,
    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """Hold the ego accelerations `action` [B] (and the mainline commands `highway_cmd`
        [B, N], NaN = scripted) for `action_repeat` simulator steps. Returns the ego's reward
        terms summed over the steps its episode still ran ([B] each) and its outcome [B].
        `after_step(events, gaps, live)` runs after every simulator step; `live` [B] marks the
        worlds whose ego was still running before that step."""
        lo, hi = self.cfg.ego.accel_bounds_mps2
        action = np.clip(action, lo, hi)
        core, cfg = self.core, self.cfg
        st = core.state
        k = cfg.sim.action_repeat
        b = self.num_worlds
        # per simulator step: the ego quantities the reward depends on, and whether it still counts
        trace = np.zeros((6, k, b))
        counts = np.zeros((k, b), dtype=bool)
        outcome = np.zeros(b, dtype=np.int64)
        for i in range(k):
            live = outcome == OUTCOME_NONE
            if not live.any():
                break
            ev = core.step(action, highway_cmd)
            g = core.ego_gaps()
            if self.recorder is not None:
                self.recorder(core, ev, g)
            if after_step is not None:
                after_step(ev, g, live)
            trace[:, i] = (
                st.v_mps[:, EGO],
                st.x_m[:, EGO],
                g.d_front_m,
                g.d_back_m,
                g.v_back_mps,
                ev.collided[:, EGO],
            )
            counts[i] = live
            outcome = np.where(live, ev.ego_outcome, outcome)
        v, x, d_f, d_b, v_b, hit = trace
        terms = ego_reward_terms(
            cfg.reward,
            np.broadcast_to(action, v.shape),
            v,
            x,
            d_f,
            d_b,
            v_b,
            hit > 0.5,
            core.v_limit,
        )
        summed = {t: (terms[t] * counts).sum(axis=0) for t in EGO_TERMS}
        return summed, outcome

    def _output(self, terms: dict[str, np.ndarray], outcome: np.ndarray) -> TensorDictBase:
        b = self.num_worlds
        dev = self.device

        def col(a: np.ndarray, dtype: torch.dtype = torch.float32) -> torch.Tensor:
            return torch.as_tensor(np.asarray(a).reshape(b, 1), dtype=dtype, device=dev)

        terminated = (outcome == OUTCOME_SUCCESS) | (outcome == OUTCOME_COLLISION)
        truncated = outcome == OUTCOME_TRUNCATED
        reward = sum(terms[t] for t in EGO_TERMS)
        return TensorDict(
            {
                "observation": torch.as_tensor(ego_observation(self.core), device=dev),
                "reward": col(reward),
                "reward_terms": TensorDict({t: col(terms[t]) for t in EGO_TERMS}, batch_size=[b]),
                "outcome": col(outcome, torch.int64),
                "ego_time_s": col(self.core.state.ego_time_s),
                "done": col(terminated | truncated, torch.bool),
                "terminated": col(terminated, torch.bool),
                "truncated": col(truncated, torch.bool),
            },
            batch_size=[b],
            device=dev,
        )
