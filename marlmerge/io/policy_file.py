"""The one policy file format: `policy.pt`, `highway_policy.pt` and the co-training pool.

A policy file is a `marlmerge.io.files` file (tensors and plain data only, never code) holding:

    format             "marlmerge-policy"
    version            1
    group              "ego" (the ramp vehicle) or "highway" (learned mainline drivers)
    algorithm          "quadq", "dqn" or "td3" (ego); "quadq-residual" or "ppo-residual"
                       (highway: IDM plus a learned adjustment), "ppo-speed" (highway: IDM
                       at a learned desired speed), "quadq-pace" or "ppo-pace" (highway: the
                       pacing driver plus a learned adjustment)
    observation        {"features": [names], "size": n}: the layout the network reads
                       (`marlmerge.sim.observation`; an ego's is the layout of its scenario's
                       `ego.observation`)
    action_bounds_mps2 [low, high]: what the network's greedy action is squashed into
    policy_state       the algorithm's tensors and sizes (`load_policy` rebuilds from them)
    config, scenario   the training config that made it and the scenario it trained on

`write_policy` writes one, `read_policy` reads one back and checks it: a file of another group,
of a newer version, or whose observation layout differs from this version's table for its
scenario is an error naming the file. Files written by marlmerge 0.2 (no `format` key) are read
as version 0: the ego's layout was the paper's state, its bounds the scenario's, a highway
network's bounds the residual bounds it was trained with.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from marlmerge.config import ScenarioConfig, from_dict
from marlmerge.config.training import ALGORITHMS as EGO_ALGORITHMS
from marlmerge.io import files
from marlmerge.sim.observation import (
    EGO_FEATURES,
    EGO_LAYOUTS,
    HIGHWAY_FEATURES,
    ego_layout,
)

FORMAT = "marlmerge-policy"
VERSION = 1
GROUPS = {"ego": EGO_FEATURES, "highway": HIGHWAY_FEATURES}
"""Each group's default layout (the ego's: the paper's state)."""
DEFAULT_FILE = {"ego": "policy.pt", "highway": "highway_policy.pt"}
V0_HIGHWAY_BOUNDS_MPS2 = (-3.0, 3.0)
"""The residual bounds every highway network of marlmerge 0.2 was trained with."""


def feature_names(group: str, scenario: dict[str, Any] | None = None) -> list[str]:
    """The feature names a `group` network reads in `scenario` (a config dict; the ego's layout
    is its `ego.observation`, "paper" when absent, then `on_ramp` with `ego.join = "chosen"`)."""
    if group == "ego" and scenario is not None:
        ego = scenario.get("ego", {})
        layout = ego.get("observation", "paper")
        if layout not in EGO_LAYOUTS:
            raise ValueError(f"unknown ego observation layout {layout!r}")
        return [f.name for f in ego_layout(layout, ego.get("join") == "chosen")]
    return [f.name for f in GROUPS[group]]


def write_policy(
    path: str | Path,
    group: str,
    algorithm: str,
    action_bounds_mps2: tuple[float, float],
    policy_state: dict[str, Any],
    config: dict[str, Any],
    scenario: dict[str, Any],
) -> None:
    """Write a policy file of `group` (see the module docstring)."""
    names = feature_names(group, scenario)
    files.save(
        {
            "format": FORMAT,
            "version": VERSION,
            "group": group,
            "algorithm": algorithm,
            "observation": {"features": names, "size": len(names)},
            "action_bounds_mps2": [float(action_bounds_mps2[0]), float(action_bounds_mps2[1])],
            "policy_state": policy_state,
            "config": config,
            "scenario": scenario,
        },
        path,
    )


ALGORITHMS: dict[str, tuple[str, ...]] = {
    "ego": EGO_ALGORITHMS,
    "highway": ("quadq-residual", "ppo-residual", "ppo-speed", "quadq-pace", "ppo-pace"),
}
"""The algorithms a policy file of each group may name (the ego's: what `marlmerge train` can
train, `TrainConfig.algorithm`)."""
STATE_KEYS = {
    "quadq": ("net", "hidden"),
    "dqn": ("net", "hidden", "layers", "levels"),
    "td3": ("net", "hidden", "layers"),
    "quadq-residual": ("net", "hidden"),
    "ppo-residual": ("net", "hidden"),
    "ppo-speed": ("net", "hidden"),
    "quadq-pace": ("net", "hidden"),
    "ppo-pace": ("net", "hidden"),
}
"""What `policy_state` must hold for each algorithm (its loader rebuilds the network from it)."""
TOP_KEYS = {
    "format": str,
    "version": int,
    "group": str,
    "algorithm": str,
    "observation": dict,
    "action_bounds_mps2": list | tuple,
    "policy_state": dict,
    "config": dict,
    "scenario": dict,
}
"""Every key of a policy file and its type."""


def read_policy(path: str | Path, group: str) -> dict[str, Any]:
    """A policy file of `group` (a file, or a run folder holding the group's default file),
    upgraded to the current version and checked against this version's observation tables.
    A file that lacks a key, holds a value of the wrong type, names an unknown algorithm or
    whose scenario is not a valid one is a `ValueError` naming the file and the key."""
    path = Path(path)
    if path.is_dir():
        path = path / DEFAULT_FILE[group]
    saved = files.load(path, f"saved {group} policy")
    if "format" not in saved:
        saved = _from_v0(saved, group, path)
    elif saved["format"] != FORMAT:
        raise ValueError(f"{path}: not a marlmerge policy file (format {saved['format']!r})")
    _check_keys(saved, path)
    if saved["version"] > VERSION:
        raise ValueError(
            f"{path}: written by a newer marlmerge (policy format version {saved['version']}, "
            f"this one reads up to {VERSION})"
        )
    if saved["group"] != group:
        raise ValueError(f"{path}: a {saved['group']} policy, not a {group} policy")
    names = feature_names(group, saved.get("scenario"))
    if list(saved["observation"].get("features", [])) != names:
        raise ValueError(
            f"{path}: trained on the observation {saved['observation'].get('features')}, but "
            f"this version's {group} observation is {names}: retrain it"
        )
    _check_contents(saved, path, group)
    return saved


def _check_keys(saved: dict[str, Any], path: Path) -> None:
    for key, kind in TOP_KEYS.items():
        if key not in saved:
            raise ValueError(f"{path}: not a whole policy file (no {key!r} key)")
        if not isinstance(saved[key], kind) or isinstance(saved[key], bool):
            raise ValueError(
                f"{path}: policy file key {key!r} holds a {type(saved[key]).__name__}, "
                f"not a {getattr(kind, '__name__', 'list')}"
            )


def _check_contents(saved: dict[str, Any], path: Path, group: str) -> None:
    """The algorithm, its state, the bounds and the scenario are what a loader can use."""
    algorithm = saved["algorithm"]
    if algorithm not in ALGORITHMS[group]:
        raise ValueError(
            f"{path}: unknown {group} algorithm {algorithm!r} (one of "
            f"{', '.join(ALGORITHMS[group])})"
        )
    missing = [k for k in STATE_KEYS[algorithm] if k not in saved["policy_state"]]
    if missing:
        raise ValueError(f"{path}: policy_state of a {algorithm} policy lacks {missing[0]!r}")
    state = saved["policy_state"]
    for key in ("hidden", "layers"):
        if key in STATE_KEYS[algorithm] and not (
            isinstance(state[key], int) and not isinstance(state[key], bool) and state[key] >= 1
        ):
            raise ValueError(
                f"{path}: policy_state.{key} must be an integer >= 1, got {state[key]!r}"
            )
    net = state.get("net")
    for name, value in net.items() if isinstance(net, dict) else ():
        if hasattr(value, "is_floating_point") and value.is_floating_point():
            if not bool(value.isfinite().all()):
                raise ValueError(
                    f"{path}: weight {name!r} of policy_state.net holds NaN or infinite "
                    "values: the policy would command NaN"
                )
    peaks = state.get("peaks", 1)  # quadq's pieces (`QuadraticQNet.peaks`)
    if not (isinstance(peaks, int) and not isinstance(peaks, bool) and peaks >= 1):
        raise ValueError(f"{path}: policy_state.peaks must be an integer >= 1, got {peaks!r}")
    bands = state.get("peak_bands", False)  # each piece's B in its band (`peak_bands`)
    if not (isinstance(bands, bool) and (not bands or peaks > 1)):
        raise ValueError(
            f"{path}: policy_state.peak_bands must be true or false, and true only with "
            f"peaks > 1; got {bands!r} with peaks = {peaks}"
        )
    extra = state.get("extra_bounds", [])  # the join's, with ego.join = "chosen"
    if not isinstance(extra, list | tuple):
        raise ValueError(f"{path}: policy_state.extra_bounds must be a list, got {extra!r}")
    for bounds in (saved["action_bounds_mps2"], *extra):
        if not _is_bounds(bounds):
            key = "action_bounds_mps2" if bounds is saved["action_bounds_mps2"] else "extra_bounds"
            raise ValueError(f"{path}: {key} must be [low, high], got {bounds!r}")
    try:
        from_dict(ScenarioConfig, saved["scenario"])
    except ValueError as err:
        raise ValueError(f"{path}: the policy's scenario is not valid: {err}") from None


@contextmanager
def weights_of(path: str | Path) -> Iterator[None]:
    """Around building a network from a policy file's state: weights that do not fit it are a
    `ValueError` naming the file."""
    try:
        yield
    except (RuntimeError, TypeError, KeyError, AttributeError) as e:
        raise ValueError(f"{path}: the saved weights do not fit the network: {e}") from None


def load_weights(module: Any, state: Any, path: str | Path) -> None:
    """`module.load_state_dict(state)` within `weights_of(path)`."""
    with weights_of(path):
        module.load_state_dict(state)


def _from_v0(saved: dict[str, Any], group: str, path: Path) -> dict[str, Any]:
    """A marlmerge 0.2 file (no `format`) in the current layout."""
    needed = ("scenario", "net") + (("hidden",) if group == "highway" else ())
    missing = [k for k in needed if k not in saved]
    if missing:
        raise ValueError(
            f"{path}: not a marlmerge policy file (no 'format' key, and not a file of 0.2 "
            f"either: it has no {missing[0]!r})"
        )
    if group == "ego" and saved.get("algorithm", "quadq") == "quadq":
        if not isinstance(saved.get("config"), dict) or "hidden" not in saved["config"]:
            raise ValueError(f"{path}: a 0.2 quadq policy file without config.hidden")
    if group == "ego":
        algorithm = saved.get("algorithm", "quadq")
        bounds = saved["scenario"]["ego"]["accel_bounds_mps2"]
        state = {k: v for k, v in saved.items() if k not in ("algorithm", "config", "scenario")}
        if algorithm == "quadq":  # 0.2 kept the width in the config only
            state["hidden"] = saved["config"]["hidden"]
    else:
        algorithm = "quadq-residual"
        bounds = saved.get("action_bounds", V0_HIGHWAY_BOUNDS_MPS2)
        state = {"net": saved["net"], "hidden": saved["hidden"]}
    names = feature_names(group)
    return {
        "format": FORMAT,
        "version": 0,
        "group": group,
        "algorithm": algorithm,
        "observation": {"features": names, "size": len(names)},
        "action_bounds_mps2": list(bounds),
        "policy_state": state,
        "config": saved.get("config", {}),
        "scenario": saved["scenario"],
    }


def _is_bounds(bounds: Any) -> bool:
    """[low, high]: two finite numbers, low < high."""
    ok = isinstance(bounds, list | tuple) and len(bounds) == 2
    ok = ok and all(isinstance(b, int | float) and not isinstance(b, bool) for b in bounds)
    return ok and all(math.isfinite(b) for b in bounds) and bounds[0] < bounds[1]
