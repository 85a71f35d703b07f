"""The one configuration schema: frozen dataclasses with defaults in code, loaded strictly.

- `scenario`: what a simulated road is (`ScenarioConfig` and its tables) and its cross-field
  checks; `training` and `cotraining`: what a training run is (`TrainConfig`, `CoTrainConfig`);
- `rules`: the `Bounds` declared beside every number, checked and listed from one table;
- `codec`: dicts and TOML to dataclasses and back, dotted keys;
- `presets`: the one lookup of the presets in `envs/` and `trainers/`, and their loading.

The scenario schema and the codec are re-exported here (`from marlmerge.config import
ScenarioConfig, load_scenario`).
"""

from marlmerge.config.codec import from_dict, get_dotted, read_toml, set_dotted, to_dict, tomllib
from marlmerge.config.rules import (
    Bounds,
    bounds_markdown,
    bounds_table,
    check_count,
    check_values,
    field_bounds,
    num,
    positive,
    require,
)
from marlmerge.config.scenario import (
    EGO_JOINS,
    ENTRANCE_LANES,
    MAX_HIGHWAY_AGENTS,
    MAX_LATENCY_S,
    MAX_WARMUP_S,
    MAX_WEIGHT,
    MPH_TO_MPS,
    OBSERVATION_LAYOUTS,
    RAMP_COOPERATIONS,
    DriverConfig,
    EgoConfig,
    InteractionConfig,
    RampConfig,
    RewardConfig,
    RoadConfig,
    SampleConfig,
    ScenarioConfig,
    SensingConfig,
    SimConfig,
    TrafficConfig,
    VehicleConfig,
    latency_steps,
    load_scenario,
    require_ego,
    validate,
)

__all__ = [
    "EGO_JOINS",
    "ENTRANCE_LANES",
    "RAMP_COOPERATIONS",
    "MAX_HIGHWAY_AGENTS",
    "MAX_LATENCY_S",
    "MAX_WARMUP_S",
    "MAX_WEIGHT",
    "MPH_TO_MPS",
    "OBSERVATION_LAYOUTS",
    "Bounds",
    "DriverConfig",
    "EgoConfig",
    "InteractionConfig",
    "RewardConfig",
    "RoadConfig",
    "SampleConfig",
    "RampConfig",
    "ScenarioConfig",
    "SensingConfig",
    "SimConfig",
    "TrafficConfig",
    "VehicleConfig",
    "bounds_markdown",
    "bounds_table",
    "check_count",
    "check_values",
    "field_bounds",
    "from_dict",
    "get_dotted",
    "latency_steps",
    "load_scenario",
    "require_ego",
    "num",
    "positive",
    "read_toml",
    "require",
    "set_dotted",
    "to_dict",
    "tomllib",
    "validate",
]
