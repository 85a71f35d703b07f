"""The simulation core: B ramp-merge worlds in packed arrays, stepped by Numba-compiled kernels.

No RL library is imported here. `TrafficCore` is the entry point; `layout` names every row of its
arrays; `step` and `kernels` hold the compiled dynamics; `drivers` the driver models; `streams`
the seeded random draws; `state` the read-only views and the outputs of a call.
"""

from marlmerge.sim.core import TrafficCore
from marlmerge.sim.drivers import Profile
from marlmerge.sim.layout import (
    EGO,
    LEFT,
    OUTCOME_COLLISION,
    OUTCOME_NAMES,
    OUTCOME_NONE,
    OUTCOME_SUCCESS,
    OUTCOME_TRUNCATED,
    RAMP,
    RIGHT,
)
from marlmerge.sim.state import EgoGaps, Rollout, Roster, StepEvents, TrafficState

__all__ = [
    "EGO",
    "LEFT",
    "OUTCOME_COLLISION",
    "OUTCOME_NAMES",
    "OUTCOME_NONE",
    "OUTCOME_SUCCESS",
    "OUTCOME_TRUNCATED",
    "RAMP",
    "RIGHT",
    "EgoGaps",
    "Profile",
    "Roster",
    "Rollout",
    "StepEvents",
    "TrafficCore",
    "TrafficState",
]
