"""The paper's learner behind the one learner protocol: the quadratic-Q network, its loss, and
one of two update paths — the fast path (`FastQuadQUpdater`, `update_path` "fast" or
"compiled") or the plain torchrl loop (`LossModule` + `torch.optim.Adam` +
`PeriodicHardUpdate`, `update_path` "torchrl"). Both compute the same loss."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

from marlmerge.learners.base import Learner
from marlmerge.learners.common import sample_uniform
from marlmerge.learners.packed_replay import unpack_rows
from marlmerge.learners.quadq import (
    GaussianExploration,
    PeriodicHardUpdate,
    QuadraticQLoss,
    QuadraticQNet,
)
from marlmerge.learners.quadq_fast import FastQuadQUpdater
from marlmerge.learners.quadq_flat import Teacher


class QuadQLearner(Learner):
    """Q(s, a) = A(s) (B(s) - a)^2 + C(s); greedy action B(s), Gaussian exploration around it.

    Args:
        obs_dim: observation size; hidden: width of the A, B, C networks.
        low, high: action bounds, m/s^2 (B is squashed strictly inside them).
        extra_bounds: (low, high) of each further action component (the join of
            `ego.join = "chosen"`); the network then has one A and one B head per component.
        gamma, lr, target_update_period: the paper's Q-learning settings.
        exploration: the Gaussian noise schedule of the collector's actions.
        update_path: "fast" (hand-written gradients and Adam), "compiled" (the same, compiled)
            or "torchrl" (the plain LossModule loop).
        updates_per_call: updates per fast-path call (must divide the target period).
        seed: initialises the networks; sample_generator: draws the minibatches.
        init_weights: start from these network weights (a trained policy's `net`) instead.
        device: where the networks and the optimiser state live (initialised on the CPU,
            then moved, so every device starts from the same weights).
        expectile: tau of the TD loss (`marlmerge.learners.quadq_flat.td_weights`; fast paths only);
            0.5: the paper's squared error.
        peaks: K quadratic pieces, Q the largest (`QuadraticQNet`); 1: the paper's network.
        peak_share: with several peaks, the weight of each losing piece's own TD error
            (`marlmerge.learners.quadq_peaks.fast_chunk_peaks`; fast paths only); 0: none.
        peak_bands: with several peaks, piece k's B in the k-th band of the command range.
        peak_share_heads: the losing pieces' heads their share reaches ("abc" or "c").
        lr_schedule: (end fraction, updates): the learning rate falls linearly to lr x the
            fraction over that many updates (`FastQuadQUpdater`; fast paths only); (1.0, 1):
            constant.
    """

    algorithm = "quadq"

    def __init__(
        self,
        obs_dim: int,
        hidden: int,
        low: float,
        high: float,
        *,
        gamma: float,
        lr: float,
        target_update_period: int,
        exploration: GaussianExploration,
        update_path: str,
        updates_per_call: int,
        seed: int,
        sample_generator: torch.Generator,
        init_weights: Mapping[str, Tensor] | None = None,
        device: torch.device | str = "cpu",
        extra_bounds: tuple[tuple[float, float], ...] = (),
        expectile: float = 0.5,
        peaks: int = 1,
        peak_share: float = 0.0,
        peak_bands: bool = False,
        peak_share_heads: str = "abc",
        lr_schedule: tuple[float, int] = (1.0, 1),
        flush_denormals: bool = False,
    ) -> None:
        checked = (
            ("expectile", expectile, 0.5),
            ("peak_share", peak_share, 0.0),
            ("lr_end_fraction", lr_schedule[0], 1.0),
            ("flush_denormals", flush_denormals, False),
        )
        for name, value, plain in checked:
            if value != plain and update_path == "torchrl":
                raise ValueError(
                    f"{name} = {value} is a setting of the fast path's update: update_path "
                    "'fast' or 'compiled', not 'torchrl'"
                )
        init = torch.Generator().manual_seed(seed)
        self.obs_dim, self.hidden = obs_dim, hidden
        self.device = torch.device(device)
        self.net = QuadraticQNet(
            obs_dim, hidden, action_low=low, action_high=high, generator=init,
            extra_bounds=extra_bounds, peaks=peaks, peak_bands=peak_bands,
        )  # fmt: skip
        if init_weights is not None:  # before the loss module copies them into its target
            self.net.load_state_dict(init_weights)
        self.net.to(self.device)  # before the loss copies it and the fast path aliases it
        self.loss_module = QuadraticQLoss(self.net, gamma=gamma)
        self.exploration = exploration
        self.update_path = update_path
        self._settings = dict(
            lr=lr, target_update_period=target_update_period, updates_per_call=updates_per_call
        )
        self.expectile = float(expectile)
        self.peak_share = float(peak_share)
        self.peak_share_heads = peak_share_heads
        self.lr_schedule = lr_schedule
        self.flush_denormals = bool(flush_denormals)
        self.sample_generator = sample_generator
        self._imitation: tuple[Teacher, float] | None = None
        self._build_updater()

    def imitate(self, teacher: Teacher, weight: float) -> None:
        """Add an imitation term to the fast path's loss (`FastQuadQUpdater.imitate`), kept
        when the updater is rebuilt (loading a checkpoint)."""
        if self.fast is None:
            raise ValueError("imitation needs update_path 'fast' or 'compiled', not 'torchrl'")
        self._imitation = (teacher, weight)
        self.fast.imitate(teacher, weight)

    def _build_updater(self) -> None:
        """The update path over the loss module's current weights (the fast path aliases them
        into flat buffers, so it is rebuilt after weights are loaded)."""
        s = self._settings
        self.fast: FastQuadQUpdater | None = None
        if self.update_path == "torchrl":
            self.optimizer = torch.optim.Adam(self.loss_module.parameters(), lr=s["lr"])
            self.target_updater = PeriodicHardUpdate(
                self.loss_module, period=s["target_update_period"]
            )
            return
        self.fast = FastQuadQUpdater(
            self.loss_module,
            None,
            generator=self.sample_generator,
            lr=s["lr"],
            batch_size=1,  # minibatches are passed in by `learn`
            updates_per_call=s["updates_per_call"],
            target_update_period=s["target_update_period"],
            compile=self.update_path == "compiled",
            expectile=self.expectile,
            peak_share=self.peak_share,
            peak_share_heads=self.peak_share_heads,
            lr_end_fraction=self.lr_schedule[0],
            lr_decay_updates=self.lr_schedule[1],
            flush_denormals=self.flush_denormals,
        )
        if self._imitation is not None:
            self.fast.imitate(*self._imitation)

    @property
    def compile_time_s(self) -> float | None:  # type: ignore[override]
        return None if self.fast is None else self.fast.compile_time_s

    @torch.no_grad()
    def act(self, obs: Tensor, sim_step: int, generator: torch.Generator | None) -> dict:
        action = self.net.greedy(obs)  # [B, m]
        if generator is not None:
            action = self.exploration(action, sim_step, generator)
        return {"action": action}

    def greedy(self, obs: Tensor) -> Tensor:
        return self.net.greedy(obs)

    def replay_action(self, flat: TensorDictBase) -> Tensor:
        return flat.get("action")

    def learn(self, replay: Any, owed: int, batch_size: int) -> Tensor:
        """The fast path updates `updates_per_call` at a time (a call's minibatches drawn in one
        sampling call; the rest of `owed` waits for the next call); the torchrl path one by one."""
        losses: list[Tensor] = []
        if self.fast is not None:
            for _ in range(owed // self.fast.k):
                losses.append(self.fast.step(self.sample_chunk(replay, batch_size)))
            return torch.cat(losses) if losses else torch.empty(0)
        for _ in range(owed):
            rows = sample_uniform(replay, batch_size)
            out = self.loss_module(unpack_rows(rows, self.obs_dim, action_dim=self.net.action_dim))
            self.optimizer.zero_grad()
            out["loss_value"].backward()
            self.optimizer.step()
            self.target_updater.step()
            losses.append(out["loss_value"].detach())
        return torch.stack(losses) if losses else torch.empty(0)

    def sample_chunk(self, replay: Any, batch_size: int) -> Tensor:
        """The minibatches of one fast-path call, drawn in one sampling call: [k, batch, row]."""
        assert self.fast is not None
        k = self.fast.k
        return sample_uniform(replay, k * batch_size).view(k, batch_size, -1)

    def state_dict(self) -> dict[str, Any]:
        torchrl_path = self.fast is None
        return {
            "loss": self.loss_module.state_dict(),
            "optimizer": self.optimizer.state_dict() if torchrl_path else self.fast.state_dict(),
            "target_updater": self.target_updater.state_dict() if torchrl_path else None,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.loss_module.load_state_dict(state["loss"])
        self._build_updater()
        if self.fast is not None:
            self.fast.load_state_dict(state["optimizer"])
        else:
            self.optimizer.load_state_dict(state["optimizer"])
            self.target_updater.load_state_dict(state["target_updater"])

    def policy_state(self) -> dict[str, Any]:
        # copies: the weights are views of the fast path's flat buffer (of S seeds' stacked
        # buffer in a vectorised run), which a policy file must not carry
        state = {
            "net": {k: v.clone() for k, v in self.net.state_dict().items()},
            "hidden": self.hidden,
        }
        if self.net.extra_bounds:
            state["extra_bounds"] = [list(b) for b in self.net.extra_bounds]
        if self.net.peaks > 1:
            state["peaks"] = self.net.peaks
        if self.net.peak_bands:
            state["peak_bands"] = True
        return state
