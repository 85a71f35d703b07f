"""marlmerge: multi-agent highway on-ramp merging.

A batched traffic simulator compiled with Numba (`marlmerge.sim`), a PettingZoo ParallelEnv over
it (`marlmerge.parallel_env`), torchrl views, and learners built on torchrl.
"""

from marlmerge.config import ScenarioConfig, load_scenario
from marlmerge.gym_env import ENV_ID, RampMergeEnv, RampMergeVectorEnv, register
from marlmerge.pettingzoo_env import ENV_NAME, RampMergeParallelEnv, env, parallel_env, raw_env
from marlmerge.policies import ScriptedHighwayPolicy
from marlmerge.sim import Profile, TrafficCore

register()  # gymnasium.make("marlmerge/RampMerge-v1")

__version__ = "0.3.0"

__all__ = [
    "ENV_ID",
    "ENV_NAME",
    "RampMergeEnv",
    "RampMergeVectorEnv",
    "env",
    "raw_env",
    "Profile",
    "RampMergeParallelEnv",
    "ScenarioConfig",
    "ScriptedHighwayPolicy",
    "TrafficCore",
    "load_scenario",
    "parallel_env",
]
