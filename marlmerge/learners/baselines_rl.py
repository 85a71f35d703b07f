"""Peer learners for the ramp merge: DQN over discrete accelerations and TD3, on torchrl.

Both see the same state (``observation`` [B, 7]), reward and env as the paper's quadratic-Q ego
and are trained by the same loop (:func:`marlmerge.train.train`, ``TrainConfig.algorithm``):

* ``"dqn"``: torchrl :class:`~torchrl.objectives.DQNLoss` (target network, optional double DQN)
  on an MLP Q-network over ``n`` acceleration levels evenly spaced in the ego's bounds; the level
  index is the discrete action, ``levels[index]`` (m/s^2) is what the env receives. Exploration is
  epsilon-greedy with a seeded generator (torchrl's ``EGreedyModule`` draws from the global RNG).
  The target is a hard copy every ``p`` updates (torchrl ``HardUpdate``).
* ``"td3"``: torchrl :class:`~torchrl.objectives.TD3Loss` with a tanh-squashed deterministic
  actor, twin Q-networks, target policy smoothing, delayed actor updates and Polyak-averaged
  targets (torchrl ``SoftUpdate``). Exploration is Gaussian noise on the actor's action
  (:class:`~marlmerge.learners.quadq.GaussianExploration`).

A learner here owns its networks, loss, optimiser(s), target updater and counters; the training
loop owns the env, the replay (packed rows ``[obs (d) | action | reward | terminated |
next_obs (d)]``, the action column being what the loss reads: the level index for DQN, the
acceleration for TD3) and the generators for exploration and minibatch sampling.

No global RNG: networks are initialised inside :func:`seeded_init` (which restores the global
state afterwards) and TD3's target-policy noise, which torchrl draws with ``torch.randn_like``, is
drawn from a private stream swapped in around the critic loss (:class:`GlobalRngStream`).

:func:`load_policy` turns any run's ``policy.pt`` (quadq included) into a greedy
``obs [B, 7] -> acceleration [B, 1]`` function.
"""

from __future__ import annotations

import contextlib
import time
import warnings
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn
from torchrl.data import Bounded, Categorical
from torchrl.modules import MLP, Actor, QValueActor, ValueOperator
from torchrl.objectives import DQNLoss, SoftUpdate, TD3Loss

from marlmerge.learners.base import Learner
from marlmerge.learners.quadq import (
    DEFAULT_ACTION_BOUNDS,
    PAPER_GAMMA,
    GaussianExploration,
    PeriodicHardUpdate,
    QuadraticQNet,
    notice_if_slow,
    unpack_rows,
)
from marlmerge.policy_file import ALGORITHMS as POLICY_ALGORITHMS
from marlmerge.policy_file import load_weights, read_policy
from marlmerge.spec.observation import EGO_FEATURES

__all__ = [
    "ALGORITHMS",
    "BaselineLearner",
    "DQNLearner",
    "EpsilonGreedy",
    "GlobalRngStream",
    "ScaledTanh",
    "TD3Learner",
    "TwinInputQNet",
    "dqn_action_levels",
    "load_policy",
    "make_dqn_loss",
    "make_dqn_qnet",
    "make_learner",
    "make_td3_actor",
    "make_td3_loss",
    "make_td3_qnet",
    "seeded_init",
]

ALGORITHMS: tuple[str, ...] = POLICY_ALGORITHMS["ego"]
"""Learners selectable with ``TrainConfig.algorithm``."""

OBS_DIM = len(EGO_FEATURES)


# ----------------------------------------------------------------------------------------------
# Randomness without the global RNG
# ----------------------------------------------------------------------------------------------


@contextlib.contextmanager
def seeded_init(seed: int) -> Iterator[None]:
    """Run a block (network construction) on the global CPU RNG seeded with ``seed``.

    ``torch.nn`` initialisers and torchrl's twin-network re-initialisation draw from the global
    RNG; inside this block they are deterministic, and the caller's global state is restored on
    exit (``torch.random.fork_rng``), so nothing outside sees a change.
    """
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


class GlobalRngStream:
    """A private random stream for library code that can only draw from the global CPU RNG.

    ``with stream.active():`` swaps the stream's state into the global generator and swaps it
    back out afterwards, so draws inside the block continue this stream (deterministic,
    checkpointable via :meth:`get_state`) and the global state outside is left unchanged.
    """

    def __init__(self, seed: int) -> None:
        self.state: Tensor = torch.Generator().manual_seed(seed).get_state()

    @contextlib.contextmanager
    def active(self) -> Iterator[None]:
        outer = torch.get_rng_state()
        torch.set_rng_state(self.state)
        try:
            yield
        finally:
            self.state = torch.get_rng_state()
            torch.set_rng_state(outer)

    def get_state(self) -> Tensor:
        return self.state.clone()

    def set_state(self, state: Tensor) -> None:
        self.state = state.clone()


# ----------------------------------------------------------------------------------------------
# Networks and losses
# ----------------------------------------------------------------------------------------------


def _mlp(in_features: int, out_features: int, hidden: int, layers: int) -> MLP:
    """torchrl MLP, ``layers`` hidden ReLU layers of width ``hidden``."""
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=[hidden] * layers,
        activation_class=nn.ReLU,
    )


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
        mlp = _mlp(obs_dim, n_levels, hidden, layers)
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
        net = nn.Sequential(_mlp(obs_dim, 1, hidden, layers), ScaledTanh(low, high))
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
        net = TwinInputQNet(_mlp(obs_dim + 1, 1, hidden, layers), low, high)
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


# ----------------------------------------------------------------------------------------------
# Learners
# ----------------------------------------------------------------------------------------------


def _maybe_compile(fn: Callable[..., Any], compile: bool) -> Callable[..., Any]:
    """``torch.compile(fn)`` (default mode; graph breaks at backward and the optimiser) or
    ``fn`` itself."""
    return torch.compile(fn) if compile else fn


@contextlib.contextmanager
def _quiet_tracing() -> Iterator[None]:
    """Silence two harmless library warnings raised while dynamo traces the torchrl losses."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Using lock_\(\) inside a compiled graph")
        warnings.filterwarnings("ignore", message=r".*inline_inbuilt_nn_modules is deprecated")
        yield


def _rows_to_td(rows: Tensor, d: int, action: Tensor) -> TensorDictBase:
    """Packed rows [M, 2d + 3] -> the tensordict the torchrl losses read (batch [M])."""
    td = unpack_rows(rows, d)
    td.set("action", action)
    td.set(("next", "done"), td.get(("next", "terminated")))  # the losses need the key to exist
    return td


class BaselineLearner(Learner):
    """A torchrl-loss learner (DQN, TD3): one gradient update per minibatch.

    Attributes:
        num_updates: gradient updates (critic updates for TD3) made so far.
    """

    num_updates: int = 0
    _uncompiled_calls: set[str]
    """Names of compiled steps not called yet (their first call compiles them)."""

    def _timed(self, name: str, fn: Callable[..., Any], *args: Any) -> Any:
        """Call ``fn``; the first call of a compiled step counts as compile time."""
        if name not in self._uncompiled_calls:
            return fn(*args)
        t0 = time.perf_counter()
        with _quiet_tracing(), notice_if_slow():
            out = fn(*args)
        self.compile_time_s = (self.compile_time_s or 0.0) + time.perf_counter() - t0
        self._uncompiled_calls.discard(name)
        return out

    def update(self, rows: Tensor) -> Tensor:
        """One gradient update on packed rows [M, 2d + 3]; returns the (critic) loss, detached."""
        raise NotImplementedError

    def learn(self, replay: Any, owed: int, batch_size: int) -> Tensor:
        """`owed` updates, their minibatches drawn in one sampling call."""
        if owed <= 0:
            return torch.empty(0)
        mbs = replay.sample(owed * batch_size).view(owed, batch_size, -1)
        return torch.stack([self.update(mbs[j]) for j in range(owed)])


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
        u = torch.rand(shape, generator=generator)
        rand_index = torch.randint(0, self.n, shape, generator=generator)
        return torch.where(u < self.epsilon(step), rand_index, greedy_index)


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
    ) -> None:
        self.levels = levels.to(torch.float32)  # [n]
        self.hidden = hidden
        self.layers = layers
        self.qnet = make_dqn_qnet(len(levels), hidden, layers, obs_dim=obs_dim, seed=seed)
        self.q_mlp: nn.Module = self.qnet.module[0].module  # the plain MLP, for fast acting
        self.loss = make_dqn_loss(self.qnet, gamma=gamma, double_dqn=double_dqn)
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=lr)
        self.target_updater = PeriodicHardUpdate(self.loss, period=target_update_period)
        self.exploration = exploration
        self.num_updates = 0
        self._step = _maybe_compile(self._gradient_step, compile)
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
        td = _rows_to_td(rows, d, rows[:, d].round().long())
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
        seed: network initialisation; ``seed + 3`` seeds the target-smoothing noise stream.
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
    ) -> None:
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
        self.actor_optimizer = torch.optim.Adam(
            list(self.loss.actor_network_params.values(True, True)), lr=lr
        )
        self.critic_optimizer = torch.optim.Adam(
            list(self.loss.qvalue_network_params.values(True, True)), lr=lr
        )
        self.target_updater = SoftUpdate(self.loss, tau=tau)
        self.policy_delay = int(policy_delay)
        self.smoothing = GlobalRngStream(seed + 3)
        self.exploration = exploration
        self.num_updates = 0
        self.last_actor_loss = float("nan")
        self._critic = _maybe_compile(self._critic_step, compile)
        self._actor = _maybe_compile(self._actor_step, compile)
        self._soft_update = _maybe_compile(self._target_step, compile)  # 0.5 -> 0.1 ms
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
        q_loss, _ = self.loss.value_loss(_rows_to_td(rows, d, rows[:, d : d + 1]))
        q_loss.backward()
        self.critic_optimizer.step()
        self.critic_optimizer.zero_grad(set_to_none=True)
        return q_loss.detach()

    def _actor_step(self, rows: Tensor) -> Tensor:
        """Actor loss (-Q1(s, pi(s))) on packed rows, backward, Adam; returns the loss."""
        d = (rows.shape[-1] - 3) // 2
        actor_loss, _ = self.loss.actor_loss(_rows_to_td(rows, d, rows[:, d : d + 1]))
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


def make_learner(cfg: Any, low: float, high: float, obs_dim: int = OBS_DIM) -> BaselineLearner:
    """The learner for ``cfg.algorithm`` (``"dqn"`` or ``"td3"``) from a ``TrainConfig`` (its
    ``[dqn]`` / ``[td3]`` table and the shared settings).

    ``cfg.update_path == "compiled"`` wraps the gradient steps in ``torch.compile`` (any other
    path runs them eagerly: "fast" and "torchrl" only mean something for quadq). Exploration
    decays over ``cfg.sigma_decay_fraction * cfg.total_sim_steps`` simulator steps (epsilon for
    DQN, the Gaussian std for TD3). Networks are seeded from ``cfg.seed``.
    """
    decay = max(int(cfg.sigma_decay_fraction * cfg.total_sim_steps), 1)
    compile = cfg.update_path == "compiled"
    if cfg.algorithm == "dqn":
        dqn = cfg.dqn
        levels = dqn_action_levels(dqn.levels, low, high)
        return DQNLearner(
            levels,
            hidden=cfg.hidden,
            layers=dqn.hidden_layers,
            gamma=cfg.gamma,
            lr=cfg.lr,
            target_update_period=cfg.target_update_period,
            double_dqn=dqn.double,
            exploration=EpsilonGreedy(dqn.epsilon_start, dqn.epsilon_end, decay, len(levels)),
            seed=cfg.seed,
            compile=compile,
            obs_dim=obs_dim,
        )
    if cfg.algorithm == "td3":
        td3 = cfg.td3
        return TD3Learner(
            low,
            high,
            hidden=cfg.hidden,
            layers=td3.hidden_layers,
            gamma=cfg.gamma,
            lr=cfg.lr,
            tau=td3.tau,
            policy_delay=td3.policy_delay,
            policy_noise=td3.target_noise,
            noise_clip=td3.target_noise_clip,
            exploration=GaussianExploration(cfg.sigma_start, cfg.sigma_end, decay, low, high),
            seed=cfg.seed,
            compile=compile,
            obs_dim=obs_dim,
        )
    raise ValueError(f"make_learner: unknown algorithm {cfg.algorithm!r} (one of dqn, td3)")


# ----------------------------------------------------------------------------------------------
# Loading a saved policy
# ----------------------------------------------------------------------------------------------


def _scenario(saved: dict):
    from marlmerge.config import ScenarioConfig, from_dict

    return from_dict(ScenarioConfig, saved["scenario"])


def load_scenario_of(path: str | Path):
    """The scenario a saved policy was trained on."""
    return _scenario(read_policy(path, "ego"))


def load_policy(path: str | Path) -> Callable[[Tensor], Tensor]:
    """Greedy policy of a saved run, any algorithm: ``obs [B, 7] -> acceleration [B, 1]`` m/s^2.

    ``path`` is a ``policy.pt`` (`marlmerge.policy_file`) or a run folder holding one. The
    returned function runs without gradients and leaves the global RNG untouched.
    """
    saved = read_policy(path, "ego")
    algorithm, state = saved["algorithm"], saved["policy_state"]
    lo, hi = saved["action_bounds_mps2"]
    obs_dim = saved["observation"]["size"]
    if algorithm == "quadq":
        net = QuadraticQNet(obs_dim, state["hidden"], action_low=lo, action_high=hi)
        load_weights(net, state["net"], path)
        net.eval()

        @torch.no_grad()
        def quadq_policy(obs: Tensor) -> Tensor:
            return net.greedy(obs)

        return quadq_policy
    if algorithm == "dqn":
        levels = state["levels"].to(torch.float32)
        with seeded_init(0):
            mlp = _mlp(obs_dim, len(levels), state["hidden"], state["layers"])
        load_weights(mlp, state["net"], path)
        mlp.eval()

        @torch.no_grad()
        def dqn_policy(obs: Tensor) -> Tensor:
            return levels[mlp(obs).argmax(-1)].unsqueeze(-1)

        return dqn_policy
    if algorithm == "td3":
        with seeded_init(0):
            actor = nn.Sequential(
                _mlp(obs_dim, 1, state["hidden"], state["layers"]), ScaledTanh(lo, hi)
            )
        load_weights(actor, state["net"], path)
        actor.eval()

        @torch.no_grad()
        def td3_policy(obs: Tensor) -> Tensor:
            return actor(obs)

        return td3_policy
    raise ValueError(f"{path}: unknown algorithm {algorithm!r} (one of {', '.join(ALGORITHMS)})")
