"""TD3, the quadratic-Q learner's continuous-action peer, on torchrl.

torchrl :class:`~torchrl.objectives.TD3Loss` with a tanh-squashed deterministic actor, twin
Q-networks, target policy smoothing, delayed actor updates and Polyak-averaged targets (torchrl
``SoftUpdate``). Exploration is Gaussian noise on the actor's action
(:class:`~marlmerge.learners.quadq.GaussianExploration`). Trained by the one loop
(:func:`marlmerge.training.train.train`, ``TrainConfig.algorithm = "td3"``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn
from torchrl.data import Bounded
from torchrl.modules import Actor, ValueOperator
from torchrl.objectives import SoftUpdate, TD3Loss

from marlmerge.config.training import PAPER_GAMMA
from marlmerge.learners.common import (
    OBS_DIM,
    BaselineLearner,
    GlobalRngStream,
    make_mlp,
    maybe_compile,
    rows_to_td,
    seeded_init,
)
from marlmerge.learners.quadq import GaussianExploration


class ScaledTanh(nn.Module):
    """``low + (high - low) * (tanh(z) + 1) / 2``: [..., 1] -> [..., 1] inside ``[low, high]``."""

    def __init__(self, low: float, high: float) -> None:
        super().__init__()
        self.low = float(low)
        self.high = float(high)

    def forward(self, z: Tensor) -> Tensor:
        return self.low + (self.high - self.low) * 0.5 * (torch.tanh(z) + 1.0)


class TwinInputQNet(nn.Module):
    """``Q(obs, action)``: obs [..., d], action [..., 1] m/s^2 -> [..., 1].

    The action is rescaled to [-1, 1] over the bounds before it meets the MLP.
    """

    def __init__(self, mlp: nn.Module, low: float, high: float) -> None:
        super().__init__()
        self.mlp = mlp
        self.mid = 0.5 * (float(low) + float(high))
        self.half = 0.5 * (float(high) - float(low))

    def forward(self, observation: Tensor, action: Tensor) -> Tensor:
        return self.mlp(torch.cat([observation, (action - self.mid) / self.half], -1))


def make_td3_actor(
    low: float,
    high: float,
    hidden: int = 64,
    layers: int = 2,
    *,
    obs_dim: int = OBS_DIM,
    seed: int = 0,
) -> Actor:
    """Deterministic actor ``observation [..., d] -> action [..., 1]`` in ``[low, high]`` m/s^2
    (tanh-squashed MLP) as a torchrl ``Actor``."""
    with seeded_init(seed):
        net = nn.Sequential(make_mlp(obs_dim, 1, hidden, layers), ScaledTanh(low, high))
    return Actor(net, in_keys=["observation"], spec=Bounded(low, high, (1,)))


def make_td3_qnet(
    low: float,
    high: float,
    hidden: int = 64,
    layers: int = 2,
    *,
    obs_dim: int = OBS_DIM,
    seed: int = 0,
) -> ValueOperator:
    """Critic ``(observation, action) -> state_action_value [..., 1]`` as a torchrl
    ``ValueOperator`` (TD3Loss makes the twin copy)."""
    with seeded_init(seed):
        net = TwinInputQNet(make_mlp(obs_dim + 1, 1, hidden, layers), low, high)
    return ValueOperator(net, in_keys=["observation", "action"])


def make_td3_loss(
    actor: Actor,
    qnet: ValueOperator,
    low: float,
    high: float,
    *,
    gamma: float = PAPER_GAMMA,
    policy_noise: float = 0.7,
    noise_clip: float = 1.75,
    seed: int = 0,
) -> TD3Loss:
    """torchrl ``TD3Loss``: two Q-networks (the second re-initialised by torchrl, under
    :func:`seeded_init`), target actor and critics, target policy smoothing with Gaussian noise
    of std ``policy_noise`` clipped to ``+-noise_clip`` (m/s^2; defaults are TD3's 0.2 and 0.5
    scaled by the half-range 3.5 m/s^2), squared TD error, TD(0) with ``gamma``."""
    with seeded_init(seed):
        loss = TD3Loss(
            actor,
            qnet,
            bounds=(low, high),
            num_qvalue_nets=2,
            policy_noise=policy_noise,
            noise_clip=noise_clip,
            loss_function="l2",
        )
    loss.make_value_estimator(gamma=gamma)
    return loss


class TD3Learner(BaselineLearner):
    """TD3 (torchrl ``TD3Loss`` + ``SoftUpdate``, Adam for actor and critics).

    Each :meth:`update` is one critic step; every ``policy_delay``-th also takes an actor step
    and a Polyak step of all targets (``tau``), as in TD3 and torchrl's reference script.

    Args:
        low, high: action bounds, m/s^2.
        hidden, layers: MLP width and number of hidden layers (actor and each critic).
        gamma, lr: discount and Adam learning rate (actor and critic).
        tau: Polyak factor of the target update.
        policy_delay: critic steps per actor step.
        policy_noise, noise_clip: target policy smoothing, m/s^2.
        exploration: Gaussian noise schedule on the actor's action.
        seed: network initialisation; ``seed + 3`` seeds the target-smoothing noise stream
            (drawn by torchrl on the networks' device: on CUDA from that device's generator).
        device: where the networks and Adam's state live (initialised on the CPU, then moved).
        compile: ``torch.compile`` the critic and the actor steps (loss, backward, Adam).
    """

    algorithm = "td3"

    def __init__(
        self,
        low: float,
        high: float,
        *,
        hidden: int = 64,
        layers: int = 2,
        gamma: float = PAPER_GAMMA,
        lr: float = 1e-3,
        tau: float = 0.005,
        policy_delay: int = 2,
        policy_noise: float = 0.7,
        noise_clip: float = 1.75,
        exploration: GaussianExploration,
        seed: int = 0,
        compile: bool = False,
        obs_dim: int = OBS_DIM,
        device: torch.device | str = "cpu",
    ) -> None:
        self.device = torch.device(device)
        self.low, self.high = float(low), float(high)
        self.hidden = hidden
        self.layers = layers
        self.actor = make_td3_actor(low, high, hidden, layers, obs_dim=obs_dim, seed=seed)
        self.actor_net: nn.Module = self.actor.module  # MLP + ScaledTanh, for fast acting
        qnet = make_td3_qnet(low, high, hidden, layers, obs_dim=obs_dim, seed=seed + 1)
        self.loss = make_td3_loss(
            self.actor,
            qnet,
            low,
            high,
            gamma=gamma,
            policy_noise=policy_noise,
            noise_clip=noise_clip,
            seed=seed + 2,
        )
        self.loss.to(self.device)  # before Adam sees the parameters; actor_net stays aliased
        self.actor_optimizer = torch.optim.Adam(
            list(self.loss.actor_network_params.values(True, True)), lr=lr
        )
        self.critic_optimizer = torch.optim.Adam(
            list(self.loss.qvalue_network_params.values(True, True)), lr=lr
        )
        self.target_updater = SoftUpdate(self.loss, tau=tau)
        self.policy_delay = int(policy_delay)
        self.smoothing = GlobalRngStream(seed + 3, self.device)
        self.exploration = exploration
        self.num_updates = 0
        self.last_actor_loss = float("nan")
        self._critic = maybe_compile(self._critic_step, compile)
        self._actor = maybe_compile(self._actor_step, compile)
        self._soft_update = maybe_compile(self._target_step, compile)  # 0.5 -> 0.1 ms
        self.compile_time_s = None
        self._uncompiled_calls = {"critic", "actor", "target"} if compile else set()

    @torch.no_grad()
    def act(self, obs: Tensor, sim_step: int, generator: torch.Generator | None) -> dict:
        action = self.actor_net(obs)
        if generator is not None:
            action = self.exploration(action, sim_step, generator)
        return {"action": action}

    @torch.no_grad()
    def greedy(self, obs: Tensor) -> Tensor:
        return self.actor_net(obs)

    def replay_action(self, flat: TensorDictBase) -> Tensor:
        return flat.get("action").reshape(-1, 1)

    def _critic_step(self, rows: Tensor) -> Tensor:
        """Twin-critic TD loss on packed rows [M, 2d + 3], backward, Adam; returns the loss."""
        d = (rows.shape[-1] - 3) // 2
        q_loss, _ = self.loss.value_loss(rows_to_td(rows, d, rows[:, d : d + 1]))
        q_loss.backward()
        self.critic_optimizer.step()
        self.critic_optimizer.zero_grad(set_to_none=True)
        return q_loss.detach()

    def _actor_step(self, rows: Tensor) -> Tensor:
        """Actor loss (-Q1(s, pi(s))) on packed rows, backward, Adam; returns the loss."""
        d = (rows.shape[-1] - 3) // 2
        actor_loss, _ = self.loss.actor_loss(rows_to_td(rows, d, rows[:, d : d + 1]))
        actor_loss.backward()
        self.actor_optimizer.step()
        self.actor_optimizer.zero_grad(set_to_none=True)
        return actor_loss.detach()

    def _target_step(self) -> None:
        """Polyak step of the target actor and critics (torchrl ``SoftUpdate``)."""
        self.target_updater.step()

    def update(self, rows: Tensor) -> Tensor:
        with self.smoothing.active():  # torchrl draws the smoothing noise with randn_like
            q_loss = self._timed("critic", self._critic, rows)
        self.num_updates += 1
        if self.num_updates % self.policy_delay == 0:
            self.last_actor_loss = float(self._timed("actor", self._actor, rows))
            self._timed("target", self._soft_update)
        return q_loss

    def state_dict(self) -> dict[str, Any]:
        return {
            "loss": self.loss.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "target_updater": self.target_updater.state_dict(),
            "smoothing_rng": self.smoothing.get_state(),
            "num_updates": self.num_updates,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.loss.load_state_dict(state["loss"])
        self.actor_optimizer.load_state_dict(state["actor_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.target_updater.load_state_dict(state["target_updater"])
        self.smoothing.set_state(state["smoothing_rng"])
        self.num_updates = int(state["num_updates"])

    def policy_state(self) -> dict[str, Any]:
        return {
            "net": {k: v.clone() for k, v in self.actor_net.state_dict().items()},
            "critic": {  # the two Q-networks, stacked on dim 0 (not needed to act)
                k: v.detach().clone()
                for k, v in self.loss.qvalue_network_params.flatten_keys(".").items()
            },
            "hidden": self.hidden,
            "layers": self.layers,
        }
