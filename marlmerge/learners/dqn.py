"""DQN over discrete accelerations, the quadratic-Q learner's discrete peer, on torchrl.

torchrl :class:`~torchrl.objectives.DQNLoss` (target network, optional double DQN) on an MLP
Q-network over ``n`` acceleration levels evenly spaced in the ego's bounds; the level index is the
discrete action, ``levels[index]`` (m/s^2) is what the env receives. Exploration is
epsilon-greedy with a seeded generator (torchrl's ``EGreedyModule`` draws from the global RNG).
The target is a hard copy every ``p`` updates (torchrl ``HardUpdate``). Trained by the one loop
(:func:`marlmerge.training.train.train`, ``TrainConfig.algorithm = "dqn"``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn
from torchrl.data import Categorical
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss

from marlmerge.config.training import PAPER_GAMMA
from marlmerge.learners.common import (
    OBS_DIM,
    BaselineLearner,
    make_mlp,
    maybe_compile,
    rows_to_td,
    seeded_init,
)
from marlmerge.learners.quadq import DEFAULT_ACTION_BOUNDS, PeriodicHardUpdate


def dqn_action_levels(
    n: int,
    low: float = DEFAULT_ACTION_BOUNDS[0],
    high: float = DEFAULT_ACTION_BOUNDS[1],
) -> Tensor:
    """``n`` accelerations evenly spaced in ``[low, high]`` (both ends included): [n], m/s^2.

    7 levels on the default bounds are -4.5, -3.33, -2.17, -1.0, 0.17, 1.33, 2.5 m/s^2.
    """
    if n < 2:
        raise ValueError(f"need at least 2 action levels, got {n}")
    if not low < high:
        raise ValueError(f"need low < high, got {low}, {high}")
    return torch.linspace(low, high, n, dtype=torch.float32)


def make_dqn_qnet(
    n_levels: int, hidden: int = 64, layers: int = 2, *, obs_dim: int = OBS_DIM, seed: int = 0
) -> QValueActor:
    """Q-network ``observation [..., obs_dim] -> action_value [..., n_levels]`` as a torchrl
    ``QValueActor`` (categorical action: the greedy level index, int64 [...])."""
    with seeded_init(seed):
        mlp = make_mlp(obs_dim, n_levels, hidden, layers)
    return QValueActor(mlp, in_keys=["observation"], spec=Categorical(n_levels))


def make_dqn_loss(
    qnet: QValueActor, *, gamma: float = PAPER_GAMMA, double_dqn: bool = False
) -> DQNLoss:
    """torchrl ``DQNLoss`` (target network, squared TD error, TD(0) with ``gamma``).

    Reads ``observation``, ``action`` (level index, int64 [B]), ``("next", "reward")`` [B, 1],
    ``("next", "terminated")`` / ``("next", "done")`` [B, 1] bool, ``("next", "observation")``.
    Only ``terminated`` stops the bootstrap (TD(0) ignores ``done``).
    """
    loss = DQNLoss(
        qnet,
        delay_value=True,
        double_dqn=double_dqn,
        loss_function="l2",
        action_space="categorical",
    )
    loss.make_value_estimator(gamma=gamma)
    return loss


class EpsilonGreedy:
    """Epsilon-greedy over ``n`` discrete actions with a linearly decaying epsilon.

    ``eps(step) = eps_start + (eps_end - eps_start) * min(step / decay_steps, 1)``. Each call
    draws one uniform and one random index per row from the generator (a fixed amount, so the
    stream is reproducible whatever the greedy choices were).
    """

    def __init__(self, eps_start: float, eps_end: float, decay_steps: int, n: int) -> None:
        self.eps_start = float(eps_start)
        self.eps_end = float(eps_end)
        self.decay_steps = max(int(decay_steps), 1)
        self.n = int(n)

    def epsilon(self, step: int) -> float:
        frac = min(max(step, 0) / self.decay_steps, 1.0)
        return self.eps_start + (self.eps_end - self.eps_start) * frac

    def __call__(self, greedy_index: Tensor, step: int, generator: torch.Generator) -> Tensor:
        """greedy_index int64 [B] -> explored index int64 [B]."""
        shape = greedy_index.shape
        u = torch.rand(shape, generator=generator)  # on the generator's device (the CPU)
        rand_index = torch.randint(0, self.n, shape, generator=generator)
        dev = greedy_index.device
        return torch.where(u.to(dev) < self.epsilon(step), rand_index.to(dev), greedy_index)


class DQNLearner(BaselineLearner):
    """DQN over discrete acceleration levels (torchrl ``DQNLoss`` + ``HardUpdate`` + Adam).

    Args:
        levels: accelerations of the discrete actions, [n] m/s^2 (:func:`dqn_action_levels`).
        hidden, layers: MLP width and number of hidden layers.
        gamma, lr: discount and Adam learning rate.
        target_update_period: hard copy online -> target every this many updates.
        double_dqn: double DQN target (online argmax, target value).
        exploration: epsilon-greedy schedule over simulator steps.
        seed: network initialisation.
        compile: ``torch.compile`` the gradient step (loss, backward, Adam).
        device: where the networks, the action levels and Adam's state live (initialised on
            the CPU, then moved).
    """

    algorithm = "dqn"

    def __init__(
        self,
        levels: Tensor,
        *,
        hidden: int = 64,
        layers: int = 2,
        gamma: float = PAPER_GAMMA,
        lr: float = 1e-3,
        target_update_period: int = 500,
        double_dqn: bool = False,
        exploration: EpsilonGreedy,
        seed: int = 0,
        compile: bool = False,
        obs_dim: int = OBS_DIM,
        device: torch.device | str = "cpu",
    ) -> None:
        self.device = torch.device(device)
        self.levels = levels.to(self.device, torch.float32)  # [n]
        self.hidden = hidden
        self.layers = layers
        self.qnet = make_dqn_qnet(len(levels), hidden, layers, obs_dim=obs_dim, seed=seed)
        self.q_mlp: nn.Module = self.qnet.module[0].module  # the plain MLP, for fast acting
        self.loss = make_dqn_loss(self.qnet, gamma=gamma, double_dqn=double_dqn)
        self.loss.to(self.device)  # before Adam sees the parameters; q_mlp stays aliased
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=lr)
        self.target_updater = PeriodicHardUpdate(self.loss, period=target_update_period)
        self.exploration = exploration
        self.num_updates = 0
        self._step = maybe_compile(self._gradient_step, compile)
        self.compile_time_s = None
        self._uncompiled_calls = {"step"} if compile else set()

    @torch.no_grad()
    def greedy_index(self, obs: Tensor) -> Tensor:
        """argmax_i Q(s, i): [..., d] -> int64 [...]."""
        return self.q_mlp(obs).argmax(-1)

    @torch.no_grad()
    def act(self, obs: Tensor, sim_step: int, generator: torch.Generator | None) -> dict:
        index = self.greedy_index(obs)
        if generator is not None:
            index = self.exploration(index, sim_step, generator)
        return {"action": self.levels[index].unsqueeze(-1), "action_index": index}

    def greedy(self, obs: Tensor) -> Tensor:
        return self.levels[self.greedy_index(obs)].unsqueeze(-1)

    def replay_action(self, flat: TensorDictBase) -> Tensor:
        return flat.get("action_index").reshape(-1, 1).to(torch.float32)

    def _gradient_step(self, rows: Tensor) -> Tensor:
        """DQNLoss on packed rows [M, 2d + 3], backward, Adam step; returns the loss."""
        d = (rows.shape[-1] - 3) // 2
        td = rows_to_td(rows, d, rows[:, d].round().long())
        loss = self.loss(td)["loss"]
        loss.backward()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        return loss.detach()

    def update(self, rows: Tensor) -> Tensor:
        loss = self._timed("step", self._step, rows)
        self.target_updater.step()
        self.num_updates += 1
        return loss

    def state_dict(self) -> dict[str, Any]:
        return {
            "loss": self.loss.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "target_updater": self.target_updater.state_dict(),
            "num_updates": self.num_updates,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.loss.load_state_dict(state["loss"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.target_updater.load_state_dict(state["target_updater"])
        self.num_updates = int(state["num_updates"])

    def policy_state(self) -> dict[str, Any]:
        return {
            "net": {k: v.clone() for k, v in self.q_mlp.state_dict().items()},
            "levels": self.levels.clone(),
            "hidden": self.hidden,
            "layers": self.layers,
        }
