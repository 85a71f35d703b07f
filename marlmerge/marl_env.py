"""The multi-agent torchrl view of the batched core: the ego plus a group of highway agents.

`MultiAgentMergeEnv` extends `BatchedMergeEnv` (B worlds, one ego each, the ego's keys at the root
exactly as there) with the torchrl agent group `"highway"`: in every world the `K =
sim.n_highway_agents` right-lane vehicles whose arrival time at the merge point is closest to the
ego's when it departs (`TrafficCore.pick_roster`), as in the PettingZoo view. The group has an
agent dimension and a shared policy acts for all its agents; agents that are absent (the lane held
fewer than K vehicles) or done (left the road, or towed away after a collision) are masked out.

Group keys (leading dims [B, K]):
    ("highway", "observation")  [B, K, 12]  layout `marlmerge.observation.HIGHWAY_FEATURES`
                                            (zeros where masked out)
    ("highway", "action")       [B, K, 1]   acceleration in m/s^2, clipped to
                                            `sim.highway_agent_accel_bounds_mps2`;
                                            NaN raises for an agent that acts; masked-out agents
                                            and agents of scripted worlds are ignored
    ("highway", "reward")       [B, K, 1]   own driving terms + interaction terms over the step
    ("highway", "reward_terms", <term>) [B, K, 1]   `marlmerge.reward.LEARNED_HIGHWAY_TERMS`
    ("highway", "mask")         [B, K]      the agent is on the road and acting
    ("highway", "left_road")    [B, K]      the agent was acting and is gone after this step:
                                            towed away after a collision (terminal for it) or ...
    ("highway", "exited")       [B, K]      ... drove off the road's downstream end (not an
                                            outcome: learners drop that transition, since an
                                            absorbing end would pay agents to leave early)
Root additions:
    "opponent"                  [B, 1]      int64: which learned opponent drives the world's
                                            highway agents (0..n-1), or -1 when its agents are
                                            driven by their scripted profiles (actions ignored)

The ego's episode is the world's episode: when the ego is done the world resets (the next ramp
vehicle departs) and a new roster and opponent are drawn. Opponents are drawn per ego from
`set_opponent_mix(n_opponents, scripted_fraction)` with the env's own seeded generator.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Composite, Unbounded

from marlmerge.batched_env import BatchedMergeEnv
from marlmerge.config import ScenarioConfig
from marlmerge.core import EGO, RIGHT, EgoGaps, StepEvents
from marlmerge.observation import HIGHWAY_FEATURES, highway_observation
from marlmerge.reward import EGO_TERMS, LEARNED_HIGHWAY_TERMS, highway_agent_step_terms

GROUP = "highway"


class MultiAgentMergeEnv(BatchedMergeEnv):
    """`BatchedMergeEnv` plus the `"highway"` agent group (see the module docstring)."""

    def __init__(
        self,
        config: ScenarioConfig | str | Path | None = None,
        num_worlds: int = 16,
        seed: int = 0,
        overrides: dict[str, Any] | None = None,
        device: str | torch.device = "cpu",
    ):
        super().__init__(config, num_worlds, seed, overrides, device)
        cfg = self.cfg
        b, k = num_worlds, cfg.sim.n_highway_agents
        if k < 1:
            raise ValueError(f"MultiAgentMergeEnv needs sim.n_highway_agents >= 1, got {k}")
        self.n_agents = k
        self.highway_bounds_mps2 = cfg.sim.highway_agent_accel_bounds_mps2
        dev = device
        group_obs = Composite(
            observation=Unbounded((b, k, len(HIGHWAY_FEATURES)), dtype=torch.float32, device=dev),
            reward_terms=Composite(
                {
                    t: Unbounded((b, k, 1), dtype=torch.float32, device=dev)
                    for t in LEARNED_HIGHWAY_TERMS
                },
                shape=(b, k),
                device=dev,
            ),
            mask=Unbounded((b, k), dtype=torch.bool, device=dev),
            left_road=Unbounded((b, k), dtype=torch.bool, device=dev),
            exited=Unbounded((b, k), dtype=torch.bool, device=dev),
            shape=(b, k),
            device=dev,
        )
        self.observation_spec[GROUP] = group_obs
        self.observation_spec["opponent"] = Unbounded((b, 1), dtype=torch.int64, device=dev)
        lo, hi = cfg.ego.accel_bounds_mps2
        self.full_action_spec = Composite(
            action=Bounded(lo, hi, (b, 1), dtype=torch.float32, device=dev),
            highway=Composite(
                action=Bounded(
                    *self.highway_bounds_mps2, (b, k, 1), dtype=torch.float32, device=dev
                ),
                shape=(b, k),
                device=dev,
            ),
            shape=(b,),
            device=dev,
        )
        self.full_reward_spec = Composite(
            reward=Unbounded((b, 1), dtype=torch.float32, device=dev),
            highway=Composite(
                reward=Unbounded((b, k, 1), dtype=torch.float32, device=dev),
                shape=(b, k),
                device=dev,
            ),
            shape=(b,),
            device=dev,
        )
        self.roster = np.full((b, k), -1, dtype=np.int64)  # [B, K] slots, -1 absent
        self.roster_ids = np.full((b, k), -1, dtype=np.int64)  # [B, K] vehicle ids
        self.mask = np.zeros((b, k), dtype=bool)  # [B, K] on the road and acting
        self.opponent = np.full(b, -1, dtype=np.int64)  # [B] -1 scripted
        self.ego_in_lane_s = np.zeros(b)  # [B] time since the ego joined the right lane
        self.n_opponents = 1
        self.scripted_fraction = 0.0
        self.opponent_rng = np.random.default_rng(seed)

    def set_opponent_mix(self, n_opponents: int, scripted_fraction: float) -> None:
        """From the next departure on, each ego meets scripted highway agents with probability
        `scripted_fraction`, else learned opponent i, uniform over `n_opponents`."""
        if n_opponents < 0 or not 0.0 <= scripted_fraction <= 1.0:
            raise ValueError(
                f"need n_opponents >= 0 and 0 <= scripted_fraction <= 1, "
                f"got {n_opponents}, {scripted_fraction}"
            )
        if n_opponents == 0 and scripted_fraction < 1.0:
            raise ValueError("with no learned opponents, scripted_fraction must be 1")
        self.n_opponents = int(n_opponents)
        self.scripted_fraction = float(scripted_fraction)

    # ------------------------------------------------------------------ torchrl hooks
    def _set_seed(self, seed: int | None) -> None:
        super()._set_seed(seed)
        self.opponent_rng = np.random.default_rng(seed)
        self._new_rosters(np.ones(self.num_worlds, dtype=bool))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        keep = getattr(self, "_keep_on_reset", False)
        out = super()._reset(tensordict, **kwargs)
        if tensordict is not None and "_reset" in tensordict.keys():
            rows = tensordict.get("_reset").reshape(self.num_worlds).cpu().numpy()
        else:
            rows = np.full(self.num_worlds, not keep)
        self._new_rosters(rows)
        zeros = {t: np.zeros((self.num_worlds, self.n_agents)) for t in LEARNED_HIGHWAY_TERMS}
        out.update(self._group_output(zeros, np.zeros_like(self.mask), with_reward=False))
        return out

    def _new_rosters(self, rows: np.ndarray) -> None:
        """Roster and opponent for the egos that just departed in the worlds `rows` ([B] bool)."""
        if not rows.any():
            return
        st = self.core.state
        slots = self.core.pick_roster(self.n_agents)
        self.roster[rows] = slots[rows]
        ids = np.take_along_axis(st.vehicle_id, np.maximum(slots, 0), axis=1)
        self.roster_ids[rows] = np.where(slots >= 0, ids, -1)[rows]
        self.mask[rows] = slots[rows] >= 0
        self.ego_in_lane_s[rows] = 0.0
        n = int(rows.sum())
        scripted = self.opponent_rng.random(n) < self.scripted_fraction
        pick = self.opponent_rng.integers(0, max(self.n_opponents, 1), n)
        self.opponent[rows] = np.where(scripted, -1, pick)

    def _still_on_road(self) -> np.ndarray:
        """[B, K]: the roster vehicle still occupies its slot (not exited, not towed away)."""
        st = self.core.state
        s = np.maximum(self.roster, 0)
        active = np.take_along_axis(st.active, s, axis=1)
        ids = np.take_along_axis(st.vehicle_id, s, axis=1)
        return active & (ids == self.roster_ids) & (self.roster >= 0)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        b, k = self.num_worlds, self.n_agents
        action = tensordict.get("action").reshape(b).to(torch.float64).cpu().numpy()
        bad = ~np.isfinite(action)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"action of world {i} must be finite, got {action[i]}")
        hw = tensordict.get((GROUP, "action"))
        if hw.shape[-3:] != (b, k, 1):
            raise ValueError(f"('highway', 'action') must have shape {(b, k, 1)}, got {hw.shape}")
        hw_action = hw.reshape(b, k).to(torch.float64).cpu().numpy()
        acting = self.mask & (self.opponent >= 0)[:, None]  # [B, K]
        bad = acting & ~np.isfinite(hw_action)
        if bad.any():
            w, a = (int(i[0]) for i in np.nonzero(bad))
            raise ValueError(
                f"action of highway agent {a} in world {w} must be finite, got {hw_action[w, a]}"
            )
        core, cfg = self.core, self.cfg
        st = core.state
        dt = cfg.sim.dt_s
        rows = np.arange(b)[:, None]
        cmd = np.full((b, core.n_slots), np.nan)
        lo, hi = self.highway_bounds_mps2
        cmd[rows, np.maximum(self.roster, 0)] = np.where(acting, np.clip(hw_action, lo, hi), np.nan)
        cmd[:, EGO] = np.nan
        counting = self.mask.copy()  # [B, K] agents whose terms still accumulate
        terms = {t: np.zeros((b, k)) for t in LEARNED_HIGHWAY_TERMS}
        exited = np.zeros((b, k), dtype=bool)  # [B, K] gone by driving off the road's end

        def after_step(ev: StepEvents, g: EgoGaps, live: np.ndarray) -> None:
            self.ego_in_lane_s = np.where(st.lane[:, EGO] == RIGHT, self.ego_in_lane_s + dt, 0.0)
            slots = np.where(counting & live[:, None], self.roster, -1)
            step_terms = highway_agent_step_terms(core, ev, g, slots, self.ego_in_lane_s)
            for t, v in step_terms.items():
                terms[t] += v
            gone = counting & ~self._still_on_road()
            exited[gone & np.take_along_axis(ev.exited, np.maximum(self.roster, 0), axis=1)] = True
            if gone.any():
                counting[gone] = False
                cmd[rows, np.maximum(self.roster, 0)] = np.where(
                    gone, np.nan, cmd[rows, np.maximum(self.roster, 0)]
                )

        summed, outcome = self._simulate(action, cmd, after_step)
        left_road = self.mask & ~counting
        self.mask = counting
        out = self._output(summed, outcome)
        out.update(self._group_output(terms, left_road, with_reward=True, exited=exited))
        return out

    def _group_output(
        self,
        terms: dict[str, np.ndarray],
        left_road: np.ndarray,
        with_reward: bool,
        exited: np.ndarray | None = None,
    ) -> TensorDict:
        b, k, dev = self.num_worlds, self.n_agents, self.device
        obs = highway_observation(self.core, np.maximum(self.roster, 0))
        obs[~self.mask] = 0.0

        def col(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.asarray(a).reshape(b, k, 1), dtype=torch.float32, device=dev)

        group = {
            "observation": torch.as_tensor(obs, device=dev),
            "reward_terms": TensorDict(
                {t: col(terms[t]) for t in LEARNED_HIGHWAY_TERMS}, batch_size=[b, k]
            ),
            "mask": torch.as_tensor(self.mask.copy(), device=dev),
            "left_road": torch.as_tensor(left_road, device=dev),
            "exited": torch.as_tensor(
                np.zeros_like(left_road) if exited is None else exited, device=dev
            ),
        }
        if with_reward:
            group["reward"] = col(sum(terms[t] for t in LEARNED_HIGHWAY_TERMS))
        return TensorDict(
            {
                GROUP: TensorDict(group, batch_size=[b, k], device=dev),
                "opponent": torch.as_tensor(self.opponent.reshape(b, 1).copy(), device=dev),
            },
            batch_size=[b],
            device=dev,
        )


__all__ = ["GROUP", "MultiAgentMergeEnv", "EGO_TERMS"]
