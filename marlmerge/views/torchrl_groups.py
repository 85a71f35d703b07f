"""The multi-agent torchrl view of the batched core: the ego plus a group of highway agents.

`MultiAgentMergeEnv` extends `BatchedMergeEnv` (B worlds, one ego each, the ego's keys at the root
exactly as there) with the torchrl agent group `"highway"`: in every world the `K =
sim.n_highway_agents` right-lane vehicles whose arrival time at the merge point is closest to the
ego's when it departs (`TrafficCore.pick_roster`), as in the PettingZoo view. The group has an
agent dimension and a shared policy acts for all its agents; agents that are absent (the lane held
fewer than K vehicles) or done (left the road, or towed away after a collision) are masked out.

Group keys (leading dims [B, K]):
    ("highway", "observation")  [B, K, 12]  layout `marlmerge.sim.observation.HIGHWAY_FEATURES`
                                            (zeros where masked out)
    ("highway", "action")       [B, K, 1]   acceleration in m/s^2, clipped to
                                            `sim.highway_agent_accel_bounds_mps2`;
                                            NaN raises for an agent that acts; masked-out agents
                                            and agents of scripted worlds are ignored
    ("highway", "reward")       [B, K, 1]   own driving terms + interaction terms over the step
    ("highway", "reward_terms", <term>) [B, K, 1]   `marlmerge.sim.reward.LEARNED_HIGHWAY_TERMS`
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
`set_opponent_mix(n_opponents, scripted_fraction)` with the env's own seeded generator; an env of
several seeds (`group_seeds`) draws each seed's worlds' opponents with that seed's env's generator.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Composite, Unbounded

from marlmerge.config import ScenarioConfig
from marlmerge.config.rules import check_count
from marlmerge.sim import Roster
from marlmerge.sim.observation import HIGHWAY_FEATURES
from marlmerge.sim.reward import EGO_TERMS, LEARNED_HIGHWAY_TERMS, total_reward
from marlmerge.views.torchrl_env import (
    BatchedMergeEnv,
    ego_action_spec,
    required_key,
    seed_worlds,
)

GROUP = "highway"


def _opponent_seed(seed: int | Sequence[Any]) -> np.random.SeedSequence:
    """The seed of the opponent draws: the env's int seed, or one number from each world's."""
    if isinstance(seed, int | np.integer):
        return np.random.SeedSequence(int(seed))
    return np.random.SeedSequence(
        [
            int(s.generate_state(1)[0]) if isinstance(s, np.random.SeedSequence) else int(s)
            for s in seed
        ]
    )


class MultiAgentMergeEnv(BatchedMergeEnv):
    """`BatchedMergeEnv` plus the `"highway"` agent group (see the module docstring)."""

    def __init__(
        self,
        config: ScenarioConfig | str | Path | None = None,
        num_worlds: int = 16,
        seed: int | Sequence[int] = 0,
        overrides: dict[str, Any] | None = None,
        device: str | torch.device = "cpu",
        group_seeds: Sequence[int] | None = None,
    ):
        """group_seeds: S seeds in one env of S x `num_worlds` worlds (`seed` is then unused):
        the worlds of seed s and their opponents run bit for bit as an env of `num_worlds`
        worlds seeded with s (`BatchedMergeEnv`'s `world_groups`)."""
        groups = None
        if group_seeds is not None:
            b = check_count("num_worlds", num_worlds)
            seed, groups = seed_worlds(group_seeds, b)  # type: ignore[assignment]
            num_worlds = len(group_seeds) * b
        super().__init__(config, num_worlds, seed, overrides, device, world_groups=groups)
        cfg = self.cfg
        b, k = num_worlds, cfg.sim.n_highway_agents
        if k < 1:
            raise ValueError(f"MultiAgentMergeEnv needs sim.n_highway_agents >= 1, got {k}")
        self.n_agents = k
        self.highway_bounds_mps2 = cfg.sim.highway_agent_accel_bounds_mps2
        group_obs, self.full_action_spec, self.full_reward_spec = _group_specs(cfg, b, k, device)
        self.observation_spec[GROUP] = group_obs
        self.observation_spec["opponent"] = Unbounded((b, 1), dtype=torch.int64, device=device)
        self.roster: Roster = self.core.make_roster(np.full((b, k), -1, dtype=np.int64))
        """[B, K] the highway agents of each world's current merge (the core keeps the mask)."""
        self.opponent = np.full(b, -1, dtype=np.int64)  # [B] -1 scripted
        self.n_opponents = 1
        self.scripted_fraction = 0.0
        seeds = [seed] if group_seeds is None else list(group_seeds)
        self.opponent_worlds = (
            [np.ones(b, dtype=bool)]
            if groups is None
            else list(groups[None, :] == np.arange(len(seeds))[:, None])
        )
        """[B] masks: the worlds each opponent generator draws for (one generator per seed)."""
        self.opponent_rngs = [np.random.default_rng(_opponent_seed(s)) for s in seeds]

    def sim_state(self) -> dict[str, Any]:
        state = super().sim_state()
        state.update(
            roster=self.roster.rows.copy(),
            opponent=self.opponent.copy(),
            opponent_rng=[r.bit_generator.state for r in self.opponent_rngs],
        )
        return state

    def load_sim_state(self, saved: dict[str, Any]) -> None:
        super().load_sim_state(saved)
        self.roster.rows[:] = saved["roster"]
        self.opponent[:] = saved["opponent"]
        states = saved["opponent_rng"]
        for rng, state in zip(
            self.opponent_rngs, states if isinstance(states, list) else [states], strict=True
        ):
            rng.bit_generator.state = state

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
        if len(self.opponent_rngs) > 1:
            raise ValueError("an env of several seeds (group_seeds) is seeded when it is made")
        super()._set_seed(seed)
        self.opponent_rngs = [np.random.default_rng(_opponent_seed(seed))]
        self._new_rosters(np.ones(self.num_worlds, dtype=bool))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        keep = getattr(self, "_keep_on_reset", False)
        out = super()._reset(tensordict, **kwargs)
        if tensordict is not None and "_reset" in tensordict.keys():
            rows = tensordict.get("_reset").reshape(self.num_worlds).cpu().numpy()
        else:
            rows = np.full(self.num_worlds, not keep)
        self._new_rosters(rows)
        _, hw_obs = self.core.observe(self.roster)
        zeros = np.zeros((self.num_worlds, self.n_agents, len(LEARNED_HIGHWAY_TERMS)))
        no = np.zeros((self.num_worlds, self.n_agents), dtype=bool)
        out.update(self._group_output(hw_obs, zeros, no, no, with_reward=False))
        return out

    @property
    def mask(self) -> np.ndarray:
        """[B, K] bool: the agent is on the road and taking part."""
        return self.roster.mask

    def _new_rosters(self, rows: np.ndarray) -> None:
        """Roster and opponent for the egos that just departed in the worlds `rows` ([B] bool)."""
        if not rows.any():
            return
        fresh = self.core.make_roster(self.core.pick_roster(self.n_agents))
        self.roster.rows[:, rows] = fresh.rows[:, rows]
        for rng, worlds in zip(self.opponent_rngs, self.opponent_worlds, strict=True):
            drawn = rows & worlds
            n = int(drawn.sum())
            scripted = rng.random(n) < self.scripted_fraction
            pick = rng.integers(0, max(self.n_opponents, 1), n)
            self.opponent[drawn] = np.where(scripted, -1, pick)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        b, k = self.num_worlds, self.n_agents
        action = self._actions(tensordict)
        hw = required_key(tensordict, (GROUP, "action"))
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
        out = self._simulate(action, self.roster, np.where(acting, hw_action, np.nan))
        result = self._output(out.ego_obs, out.ego_terms, out.ego_outcome)
        result.update(self._group_output(out.hw_obs, out.hw_terms, out.left_road, out.exited, True))
        return result

    def _group_output(
        self,
        hw_obs: np.ndarray,
        terms: np.ndarray,
        left_road: np.ndarray,
        exited: np.ndarray,
        with_reward: bool,
    ) -> TensorDict:
        """The group keys from the core's highway outputs: observations [B, K, 12] (zeros where
        masked), summed terms [B, K, 8], who left the road and how."""
        b, k, dev = self.num_worlds, self.n_agents, self.device

        def col(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(np.asarray(a).reshape(b, k, 1), dtype=torch.float32, device=dev)

        group = {
            "observation": torch.as_tensor(hw_obs, device=dev),
            "reward_terms": TensorDict(
                {t: col(terms[..., i]) for i, t in enumerate(LEARNED_HIGHWAY_TERMS)},
                batch_size=[b, k],
            ),
            "mask": torch.as_tensor(self.mask.copy(), device=dev),
            "left_road": torch.as_tensor(left_road, device=dev),
            "exited": torch.as_tensor(exited & left_road, device=dev),
        }
        if with_reward:
            group["reward"] = col(total_reward(terms))
        return TensorDict(
            {
                GROUP: TensorDict(group, batch_size=[b, k], device=dev),
                "opponent": torch.as_tensor(self.opponent.reshape(b, 1).copy(), device=dev),
            },
            batch_size=[b],
            device=dev,
        )


def _group_specs(
    cfg: ScenarioConfig, b: int, k: int, dev: str | torch.device
) -> tuple[Composite, Composite, Composite]:
    """The highway group's observation keys and the full action and reward specs of B worlds
    with K highway agents each (the ego's keys are `BatchedMergeEnv`'s)."""

    def column() -> Unbounded:  # [B, K, 1]
        return Unbounded((b, k, 1), dtype=torch.float32, device=dev)

    group_obs = Composite(
        observation=Unbounded((b, k, len(HIGHWAY_FEATURES)), dtype=torch.float32, device=dev),
        reward_terms=Composite(
            {t: column() for t in LEARNED_HIGHWAY_TERMS},
            shape=(b, k),
            device=dev,
        ),
        mask=Unbounded((b, k), dtype=torch.bool, device=dev),
        left_road=Unbounded((b, k), dtype=torch.bool, device=dev),
        exited=Unbounded((b, k), dtype=torch.bool, device=dev),
        shape=(b, k),
        device=dev,
    )
    bounds = cfg.sim.highway_agent_accel_bounds_mps2
    action = Composite(
        action=ego_action_spec(cfg, b, dev),
        highway=Composite(
            action=Bounded(*bounds, (b, k, 1), dtype=torch.float32, device=dev),
            shape=(b, k),
            device=dev,
        ),
        shape=(b,),
        device=dev,
    )
    reward = Composite(
        reward=Unbounded((b, 1), dtype=torch.float32, device=dev),
        highway=Composite(
            reward=column(),
            shape=(b, k),
            device=dev,
        ),
        shape=(b,),
        device=dev,
    )
    return group_obs, action, reward


__all__ = ["GROUP", "MultiAgentMergeEnv", "EGO_TERMS"]
