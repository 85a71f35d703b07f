"""Learners built on torchrl: the quadratic-in-action Q-function of Wang & Chan, and its peers
(DQN over discrete accelerations, TD3) in `baselines_rl`."""

from marlmerge.learners.baselines_rl import (
    ALGORITHMS,
    DQNLearner,
    TD3Learner,
    dqn_action_levels,
    load_policy,
    make_learner,
)
from marlmerge.learners.quadq import (
    DEFAULT_ACTION_BOUNDS,
    FastQuadQUpdater,
    GaussianExploration,
    PeriodicHardUpdate,
    QuadraticQLoss,
    QuadraticQNet,
    TransitionReplay,
    noisy_greedy_action,
)

__all__ = [
    "DEFAULT_ACTION_BOUNDS",
    "FastQuadQUpdater",
    "GaussianExploration",
    "PeriodicHardUpdate",
    "QuadraticQLoss",
    "QuadraticQNet",
    "TransitionReplay",
    "noisy_greedy_action",
    # peers of the quadratic-Q learner (baselines_rl)
    "ALGORITHMS",
    "DQNLearner",
    "TD3Learner",
    "dqn_action_levels",
    "load_policy",
    "make_learner",
]
