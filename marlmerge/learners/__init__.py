"""Learners built on torchrl: the quadratic-in-action Q-function of Wang & Chan."""

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
]
