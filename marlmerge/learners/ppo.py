"""PPO for the highway group (IPPO, or MAPPO with a centralised critic) on torchrl.

The K highway agents of every world share one Gaussian policy over the learned adjustment of
`marlmerge.learners.highway.ResidualHighwayPolicy` (an IDM driver plus an offset, m/s^2): a
torchrl `ProbabilisticActor` samples z ~ N(loc(obs), scale(obs)) and the offset is z squashed
into the offset bounds, mid + half * tanh(z). The loss sees z (the squashing is a fixed map that
cancels in PPO's probability ratio, and a Normal has a closed-form entropy); z is stored with
the rollout, so no offset is ever inverted through tanh. `ClipPPOLoss` trains it with advantages
from torchrl's `generalized_advantage_estimate` over each agent's own trajectory.

- **IPPO** (`critic = "local"`): the value function sees the agent's own observation [12].
- **MAPPO** (`critic = "central"`): it sees the agent's own observation, the ego's observation and
  every agent of the world ([12 + d + 12 K], absent agents as zeros): the state the whole group
  acts in. The actor is the same decentralised policy either way.

On-policy (`on_policy = True`): the loop stores one batch's rollout rows (`rollout_rows`) and
`learn` makes `epochs` passes over them in `minibatches` shuffled minibatches, then empties the
buffer. Packed rows: ``[obs (12) | critic_obs (c) | z | log_prob | advantage | value_target]``.

A trajectory is one agent slot of one world: it ends where the agent leaves the road (towed away
after a collision: terminal; drove off downstream: cut, bootstrapped from its own last value, so
that leaving is never worth more than staying), where the world's ego is done (the roster is
redrawn: cut, bootstrapped from the next observation) and at the end of the batch.

No global RNG: exploration noise comes from the loop's generator, minibatch order from the
learner's own generator.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import Tensor, nn
from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value.functional import generalized_advantage_estimate

from marlmerge.learners.base import Learner
from marlmerge.learners.common import make_mlp, seeded_init

CRITICS = ("local", "central")
"""IPPO's per-agent value function, MAPPO's centralised one."""


def critic_size(obs_dim: int, ego_dim: int, n_agents: int, critic: str) -> int:
    """Width of the critic's input for one agent."""
    return obs_dim if critic == "local" else obs_dim + ego_dim + obs_dim * n_agents


def critic_observation(hw_obs: Tensor, ego_obs: Tensor, critic: str) -> Tensor:
    """The critic's input per agent: hw_obs [..., K, 12], ego_obs [..., d] -> [..., K, c]."""
    if critic == "local":
        return hw_obs
    k = hw_obs.shape[-2]
    ego = ego_obs.unsqueeze(-2).expand(*hw_obs.shape[:-1], ego_obs.shape[-1])
    group = hw_obs.flatten(-2).unsqueeze(-2).expand(*hw_obs.shape[:-2], k, -1)
    return torch.cat([hw_obs, ego, group], -1)


def make_actor_net(obs_dim: int, hidden: int, init_std: float) -> nn.Module:
    """obs [..., 12] -> (loc, scale) [..., 1] each of z; the scale starts near `init_std`."""
    return nn.Sequential(
        make_mlp(obs_dim, 2, hidden, 2),
        NormalParamExtractor(scale_mapping=f"biased_softplus_{init_std}"),
    )


def squash(z: Tensor, low: float, high: float) -> Tensor:
    """A pre-squash sample z -> the offset in [low, high]."""
    return (high + low) / 2 + (high - low) / 2 * torch.tanh(z)


def greedy_offset(actor_net: nn.Module, obs: Tensor, low: float, high: float) -> Tensor:
    """The policy's deterministic action: the tanh-squashed mean, [..., 1] in [low, high]."""
    loc, _ = actor_net(obs)
    return squash(loc, low, high)


class PPOHighwayLearner(Learner):
    """The highway group's PPO learner (see the module docstring).

    Args:
        obs_dim: an agent's observation size (12); critic_dim: the critic's input size
            (`critic_size`); low, high: the offset bounds, m/s^2.
        gamma, lmbda: discount and GAE lambda; lr: Adam's step size for actor and critic.
        clip_epsilon, entropy_coeff, critic_coeff: `ClipPPOLoss` settings.
        epochs, minibatches: passes over each rollout and minibatches per pass.
        max_grad_norm: gradient clipping of each update.
        seed: the networks' initialisation; +1: minibatch order.
        device: where the networks, optimiser state and rollout live (initialised on the CPU,
            then moved; noise and minibatch order come from CPU generators).
    """

    algorithm = "ppo"
    on_policy = True

    def __init__(
        self,
        obs_dim: int,
        critic_dim: int,
        hidden: int,
        low: float,
        high: float,
        *,
        gamma: float,
        lmbda: float,
        lr: float,
        clip_epsilon: float,
        entropy_coeff: float,
        critic_coeff: float,
        epochs: int,
        minibatches: int,
        max_grad_norm: float,
        init_std: float,
        seed: int,
        device: torch.device | str = "cpu",
    ) -> None:
        self.obs_dim, self.critic_dim, self.low, self.high = obs_dim, critic_dim, low, high
        self.gamma, self.lmbda = gamma, lmbda
        self.epochs, self.minibatches, self.max_grad_norm = epochs, minibatches, max_grad_norm
        self.device = torch.device(device)
        with seeded_init(seed):  # on the CPU, then moved: the same weights on every device
            self.actor_net = make_actor_net(obs_dim, hidden, init_std).to(self.device)
            self.critic_net = make_mlp(critic_dim, 1, hidden, 2).to(self.device)
        self.actor = ProbabilisticActor(
            TensorDictModule(self.actor_net, ["observation"], ["loc", "scale"]),
            in_keys=["loc", "scale"],
            distribution_class=IndependentNormal,
            return_log_prob=True,
        )
        self.critic = ValueOperator(self.critic_net, in_keys=["critic_observation"])
        self.loss = ClipPPOLoss(
            self.actor,
            self.critic,
            clip_epsilon=clip_epsilon,
            entropy_coeff=entropy_coeff,
            critic_coeff=critic_coeff,
            loss_critic_type="l2",
            normalize_advantage=True,
        )
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=lr)
        self.order_gen = torch.Generator().manual_seed(seed + 1)
        self.num_updates = 0

    # ---- acting ------------------------------------------------------------------------------

    @torch.no_grad()
    def act(self, obs: Tensor, sim_step: int, generator: torch.Generator | None) -> dict:
        """Offsets `"action"` [..., 1] m/s^2, sampled with `generator`'s noise (and the
        pre-squash sample `"z"` [..., 1] the loss needs), or greedy without it."""
        if generator is None:
            return {"action": self.greedy(obs)}
        loc, scale = self.actor_net(obs)
        noise = torch.randn(loc.shape, generator=generator)  # the CPU generator's draws
        z = loc + scale * noise.to(loc.device)
        return {"action": squash(z, self.low, self.high), "z": z}

    @torch.no_grad()
    def greedy(self, obs: Tensor) -> Tensor:
        return greedy_offset(self.actor_net, obs, self.low, self.high)

    def log_prob(self, obs: Tensor, z: Tensor) -> Tensor:
        """log pi(z | obs) [..., 1] of pre-squash samples z [..., 1]."""
        dist = self.actor.get_dist(TensorDict({"observation": obs}, obs.shape[:-1]))
        return dist.log_prob(z).unsqueeze(-1)

    def value(self, critic_obs: Tensor) -> Tensor:
        return self.critic_net(critic_obs)

    def replay_action(self, flat: TensorDictBase) -> Tensor:
        raise NotImplementedError("PPO stores rollout rows (rollout_rows), not replay actions")

    # ---- the rollout -------------------------------------------------------------------------

    @torch.no_grad()
    def rollout_rows(
        self,
        obs: Tensor,
        critic_obs: Tensor,
        z: Tensor,
        reward: Tensor,
        next_critic_obs: Tensor,
        valid: Tensor,
        end: Tensor,
        terminated: Tensor,
        cut_at_own_value: Tensor,
    ) -> Tensor:
        """Packed rows of the valid agent steps of a rollout, with GAE advantages.

        Inputs are [B, T, K, ...] (time is dim 1): obs [.., 12], critic_obs / next_critic_obs
        [.., c], z (the pre-squash sample of `act`) and reward [.., 1]; valid, end (the
        trajectory ends after this step), terminated (it ends in an absorbing state) and
        cut_at_own_value (bootstrap from this step's own value, not the next observation's)
        [B, T, K] bool; on any device (the rows are the learner's).
        """
        obs, critic_obs, z, reward, next_critic_obs, valid, end, terminated, cut_at_own_value = (
            x.to(self.device)
            for x in (
                obs, critic_obs, z, reward, next_critic_obs, valid, end, terminated,
                cut_at_own_value,
            )
        )  # fmt: skip
        value = self.value(critic_obs)  # [B, T, K, 1]
        next_value = torch.where(cut_at_own_value.unsqueeze(-1), value, self.value(next_critic_obs))
        end = end | ~valid
        # [B, K, T, 1]: one trajectory per agent slot, time next to last as GAE wants it
        adv, target = generalized_advantage_estimate(
            self.gamma,
            self.lmbda,
            *(x.transpose(1, 2) for x in (value, next_value, reward * valid.unsqueeze(-1))),
            end.transpose(1, 2).unsqueeze(-1),
            (terminated & valid).transpose(1, 2).unsqueeze(-1),
            time_dim=-2,
        )
        adv, target = adv.transpose(1, 2), target.transpose(1, 2)
        log_prob = self.log_prob(obs, z)
        cols = (obs, critic_obs, z, log_prob, adv, target)
        return torch.cat([c[valid] for c in cols], -1)

    def rows_td(self, rows: Tensor) -> TensorDictBase:
        """Packed rows [M, r] -> the tensordict `ClipPPOLoss` reads."""
        d, c = self.obs_dim, self.critic_dim
        cols = torch.split(rows, [d, c, 1, 1, 1, 1], -1)
        names = ("observation", "critic_observation", "action", "action_log_prob")
        td = TensorDict(dict(zip(names, cols[:4], strict=True)), [rows.shape[0]])
        td.set("action_log_prob", td.get("action_log_prob").squeeze(-1))
        td.set("advantage", cols[4])
        td.set("value_target", cols[5])
        return td

    # ---- learning ----------------------------------------------------------------------------

    def learn(self, replay: Any, owed: int, batch_size: int) -> Tensor:
        """`epochs` passes over the rollout in `replay` (all of it), then empty it; returns the
        loss (objective + critic + entropy) of each update. `owed` and `batch_size` belong to
        the off-policy learners and are not used."""
        n = len(replay)
        if n == 0:
            return torch.empty(0)
        rows = replay[:]
        size = -(-n // self.minibatches)
        losses = []
        for _ in range(self.epochs):
            order = torch.randperm(n, generator=self.order_gen).to(rows.device)
            for i in range(0, n, size):
                losses.append(self.update(rows[order[i : i + size]]))
        replay.empty()
        return torch.stack(losses)

    def update(self, rows: Tensor) -> Tensor:
        out = self.loss(self.rows_td(rows))
        total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
        self.optimizer.zero_grad()
        total.backward()
        nn.utils.clip_grad_norm_(self.loss.parameters(), self.max_grad_norm)
        self.optimizer.step()
        self.num_updates += 1
        return total.detach()

    # ---- checkpoints -------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {  # module weights, copied in place on loading: the loss shares their tensors
            "actor": self.actor_net.state_dict(),
            "critic": self.critic_net.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "order_gen": self.order_gen.get_state(),
            "num_updates": self.num_updates,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.actor_net.load_state_dict(state["actor"])
        self.critic_net.load_state_dict(state["critic"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.order_gen.set_state(state["order_gen"])
        self.num_updates = state["num_updates"]

    def policy_state(self) -> dict[str, Any]:
        return {"net": self.actor_net.state_dict()}
