"""The one learner protocol every ego learner implements (quadq, DQN, TD3).

The training loop (`marlmerge.training.train`) only ever calls these methods, so it has no branch
per algorithm: it acts with `act`, stores `replay_action`, learns with `learn`, checkpoints with
`state_dict` / `load_state_dict` and saves `policy_state` in the policy file.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor


class Learner:
    """What the training loop needs from a learner.

    Attributes:
        algorithm: `"quadq"`, `"dqn"`, `"td3"` or `"ppo"` (the highway group's PPO).
        compile_time_s: seconds spent in the first (compiling) calls of compiled update steps;
            `None` when they run eagerly.
    """

    algorithm: str = ""
    compile_time_s: float | None = None
    device: torch.device = torch.device("cpu")
    """Where the networks live; `act` and `greedy` take and return tensors on it (the
    learning group moves observations there and actions back: `LearningGroup`)."""
    on_policy: bool = False
    """True: `learn` consumes the rollout stored since its last call (PPO), whatever is owed."""

    def act(self, obs: Tensor, sim_step: int, generator: torch.Generator | None) -> dict:
        """Exploring (`generator` given) or greedy action: `{"action": [B, 1] m/s^2, ...}`."""
        raise NotImplementedError

    def greedy(self, obs: Tensor) -> Tensor:
        """Greedy acceleration [..., 1], m/s^2, inside the bounds."""
        raise NotImplementedError

    def replay_action(self, flat: TensorDictBase) -> Tensor:
        """The replay's action column [N, 1] (float) from a flat collector batch [N]."""
        raise NotImplementedError

    def learn(self, replay: Any, owed: int, batch_size: int) -> Tensor:
        """Make up to `owed` gradient updates on minibatches of `batch_size` sampled from
        `replay`; returns the losses [n] of the n updates made (n <= owed: a learner that
        updates in chunks leaves the rest for its next call)."""
        raise NotImplementedError

    def state_dict(self) -> dict[str, Any]:
        """Everything a checkpoint needs to continue bit for bit (weights, targets, optimisers,
        counters, the learner's own generators)."""
        raise NotImplementedError

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        raise NotImplementedError

    def policy_state(self) -> dict[str, Any]:
        """What the policy file needs to rebuild the greedy policy (`load_policy`)."""
        raise NotImplementedError


def host_greedy(learner: Learner) -> Callable[[Tensor], Tensor]:
    """`learner.greedy` for observations on the CPU (the simulator's side): moved to the
    learner's device and the actions back."""
    if learner.device.type == "cpu":
        return learner.greedy
    return lambda obs: learner.greedy(obs.to(learner.device)).to(obs.device)
