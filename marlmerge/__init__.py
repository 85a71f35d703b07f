"""marlmerge: multi-agent highway on-ramp merging.

A batched traffic simulator (`marlmerge.core`), a PettingZoo ParallelEnv over it
(`marlmerge.parallel_env`), and learners built on torchrl.
"""

from marlmerge.config import ScenarioConfig, load_scenario
from marlmerge.core import TrafficCore
from marlmerge.drivers import Profile
from marlmerge.env import ENV_NAME, RampMergeParallelEnv, parallel_env
from marlmerge.policies import ScriptedHighwayPolicy

__version__ = "0.1.0"

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
