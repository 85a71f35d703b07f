"""marlmerge: multi-agent highway on-ramp merging.

A batched traffic simulator compiled with Numba (`marlmerge.sim`), a PettingZoo ParallelEnv over
it (`marlmerge.parallel_env`), torchrl views, and learners built on torchrl.
"""

from marlmerge.config import ScenarioConfig, load_scenario
from marlmerge.env import ENV_NAME, RampMergeParallelEnv, parallel_env
from marlmerge.policies import ScriptedHighwayPolicy
from marlmerge.sim import Profile, TrafficCore

__version__ = "0.2.0"

__all__ = [
    "ENV_NAME",
    "Profile",
    "RampMergeParallelEnv",
    "ScenarioConfig",
    "ScriptedHighwayPolicy",
    "TrafficCore",
    "load_scenario",
    "parallel_env",
]
