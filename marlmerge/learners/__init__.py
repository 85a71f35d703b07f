"""Learners built on torchrl, all behind the one protocol of `base.Learner`:

- `quadq` (the paper's quadratic-in-action Q-function and its loss), `quadq_fast` (its
  engineered update path), `quadq_fused` (S seeds in one update) and
  `quadq_learner` (the protocol over it);
- `dqn` and `td3`, its peers over torchrl losses, sharing `common`;
- `highway`, the learned highway driver (a residual on the scripted profile), and `ppo`, the
  highway group's PPO learner (IPPO / MAPPO);
- `loading`: `make_learner` by algorithm name and the one `load_policy` of a saved ego.
"""

from marlmerge.learners.dqn import DQNLearner, dqn_action_levels
from marlmerge.learners.loading import ALGORITHMS, load_policy, make_learner
from marlmerge.learners.packed_replay import TransitionReplay
from marlmerge.learners.quadq import (
    DEFAULT_ACTION_BOUNDS,
    GaussianExploration,
    PeriodicHardUpdate,
    QuadraticQLoss,
    QuadraticQNet,
    noisy_greedy_action,
)
from marlmerge.learners.quadq_fast import FastQuadQUpdater
from marlmerge.learners.td3 import TD3Learner

__all__ = [
    "DEFAULT_ACTION_BOUNDS",
    "FastQuadQUpdater",
    "GaussianExploration",
    "PeriodicHardUpdate",
    "QuadraticQLoss",
    "QuadraticQNet",
    "TransitionReplay",
    "noisy_greedy_action",
    "ALGORITHMS",
    "DQNLearner",
    "TD3Learner",
    "dqn_action_levels",
    "load_policy",
    "make_learner",
]
