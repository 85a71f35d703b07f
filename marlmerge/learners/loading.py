"""The ego learners by name: `make_learner` builds the torchrl-loss peers for a training run, and
`load_policy` turns any run's ``policy.pt`` (quadq, DQN or TD3) into a greedy
``obs [B, F] -> acceleration [B, 1]`` function."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from marlmerge.config.training import ALGORITHMS
from marlmerge.io.policy_file import load_weights, read_policy
from marlmerge.learners.common import OBS_DIM, BaselineLearner, make_mlp, seeded_init
from marlmerge.learners.dqn import DQNLearner, EpsilonGreedy, dqn_action_levels
from marlmerge.learners.quadq import GaussianExploration, QuadraticQNet
from marlmerge.learners.td3 import ScaledTanh, TD3Learner

__all__ = ["ALGORITHMS", "load_policy", "load_quadq_net", "load_scenario_of", "make_learner"]


def make_learner(cfg: Any, low: float, high: float, obs_dim: int = OBS_DIM) -> BaselineLearner:
    """The learner for ``cfg.algorithm`` (``"dqn"`` or ``"td3"``) from a ``TrainConfig`` (its
    ``[dqn]`` / ``[td3]`` table and the shared settings).

    ``cfg.update_path == "compiled"`` wraps the gradient steps in ``torch.compile`` (any other
    path runs them eagerly: "fast" and "torchrl" only mean something for quadq). Exploration
    decays over ``cfg.sigma_decay_fraction * cfg.total_sim_steps`` simulator steps (epsilon for
    DQN, the Gaussian std for TD3). Networks are seeded from ``cfg.seed`` and live on
    ``cfg.device``.
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
            device=cfg.device,
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
            device=cfg.device,
        )
    raise ValueError(f"make_learner: unknown algorithm {cfg.algorithm!r} (one of dqn, td3)")


# ----------------------------------------------------------------------------------------------
# Loading a saved policy
# ----------------------------------------------------------------------------------------------


def scenario_of_saved(saved: dict):
    from marlmerge.config import ScenarioConfig, from_dict

    return from_dict(ScenarioConfig, saved["scenario"])


def load_scenario_of(path: str | Path):
    """The scenario a saved policy was trained on."""
    return scenario_of_saved(read_policy(path, "ego"))


def quadq_net(saved: dict, path: str | Path) -> QuadraticQNet:
    """The quadratic-Q network of a read quadq policy file (`read_policy`), its weights loaded,
    in eval mode: its action components and pieces as saved."""
    state, (lo, hi) = saved["policy_state"], saved["action_bounds_mps2"]
    extra = tuple(tuple(b) for b in state.get("extra_bounds", ()))  # the join, if chosen
    net = QuadraticQNet(
        saved["observation"]["size"], state["hidden"], action_low=lo, action_high=hi,
        extra_bounds=extra, peaks=state.get("peaks", 1),  # the envelope's pieces, if several
        peak_bands=state.get("peak_bands", False),  # each piece in its band of commands
    )  # fmt: skip
    load_weights(net, state["net"], path)
    return net.eval()


def load_quadq_net(path: str | Path) -> QuadraticQNet:
    """The network of a saved quadq policy (a ``policy.pt`` or a run folder holding one), for
    reading its heads A, B and C; another algorithm is a `ValueError` naming the file."""
    saved = read_policy(path, "ego")
    if saved["algorithm"] != "quadq":
        raise ValueError(f"{path}: a quadq policy is needed, got {saved['algorithm']!r}")
    return quadq_net(saved, path)


def load_policy(path: str | Path) -> Callable[[Tensor], Tensor]:
    """Greedy policy of a saved run, any algorithm: ``obs [B, 7] -> acceleration [B, 1]`` m/s^2
    (a quadq policy of `ego.join = "chosen"`: [B, 2], acceleration and join).

    ``path`` is a ``policy.pt`` (`marlmerge.io.policy_file`) or a run folder holding one. The
    returned function runs without gradients and leaves the global RNG untouched.
    """
    saved = read_policy(path, "ego")
    algorithm, state = saved["algorithm"], saved["policy_state"]
    lo, hi = saved["action_bounds_mps2"]
    obs_dim = saved["observation"]["size"]
    if algorithm == "quadq":
        net = quadq_net(saved, path)

        @torch.no_grad()
        def quadq_policy(obs: Tensor) -> Tensor:
            return net.greedy(obs)

        return quadq_policy
    if algorithm == "dqn":
        levels = state["levels"].to(torch.float32)
        with seeded_init(0):
            mlp = make_mlp(obs_dim, len(levels), state["hidden"], state["layers"])
        load_weights(mlp, state["net"], path)
        mlp.eval()

        @torch.no_grad()
        def dqn_policy(obs: Tensor) -> Tensor:
            return levels[mlp(obs).argmax(-1)].unsqueeze(-1)

        return dqn_policy
    if algorithm == "td3":
        with seeded_init(0):
            actor = nn.Sequential(
                make_mlp(obs_dim, 1, state["hidden"], state["layers"]), ScaledTanh(lo, hi)
            )
        load_weights(actor, state["net"], path)
        actor.eval()

        @torch.no_grad()
        def td3_policy(obs: Tensor) -> Tensor:
            return actor(obs)

        return td3_policy
    raise ValueError(f"{path}: unknown algorithm {algorithm!r} (one of {', '.join(ALGORITHMS)})")
