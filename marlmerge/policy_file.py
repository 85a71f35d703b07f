"""The one policy file format: `policy.pt`, `highway_policy.pt` and the co-training pool.

A policy file is a `marlmerge.files` file (tensors and plain data only, never code) holding:

    format             "marlmerge-policy"
    version            1
    group              "ego" (the ramp vehicle) or "highway" (learned mainline drivers)
    algorithm          "quadq", "dqn" or "td3" (ego); "quadq-residual" (highway: IDM plus a
                       learned adjustment)
    observation        {"features": [names], "size": n}: the layout the network reads
                       (`marlmerge.spec.observation`; an ego's is the layout of its scenario's
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

from pathlib import Path
from typing import Any

from marlmerge import files
from marlmerge.spec.observation import EGO_FEATURES, EGO_LAYOUTS, HIGHWAY_FEATURES

FORMAT = "marlmerge-policy"
VERSION = 1
GROUPS = {"ego": EGO_FEATURES, "highway": HIGHWAY_FEATURES}
"""Each group's default layout (the ego's: the paper's state)."""
DEFAULT_FILE = {"ego": "policy.pt", "highway": "highway_policy.pt"}
V0_HIGHWAY_BOUNDS_MPS2 = (-3.0, 3.0)
"""The residual bounds every highway network of marlmerge 0.2 was trained with."""


def feature_names(group: str, scenario: dict[str, Any] | None = None) -> list[str]:
    """The feature names a `group` network reads in `scenario` (a config dict; the ego's layout
    is its `ego.observation`, "paper" when absent)."""
    if group == "ego" and scenario is not None:
        layout = scenario.get("ego", {}).get("observation", "paper")
        if layout not in EGO_LAYOUTS:
            raise ValueError(f"unknown ego observation layout {layout!r}")
        return [f.name for f in EGO_LAYOUTS[layout]]
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


def read_policy(path: str | Path, group: str) -> dict[str, Any]:
    """A policy file of `group` (a file, or a run folder holding the group's default file),
    upgraded to the current version and checked against this version's observation tables."""
    path = Path(path)
    if path.is_dir():
        path = path / DEFAULT_FILE[group]
    saved = files.load(path, f"saved {group} policy")
    if "format" not in saved:
        saved = _from_v0(saved, group)
    elif saved["format"] != FORMAT:
        raise ValueError(f"{path}: not a marlmerge policy file (format {saved['format']!r})")
    if saved["version"] > VERSION:
        raise ValueError(
            f"{path}: written by a newer marlmerge (policy format version {saved['version']}, "
            f"this one reads up to {VERSION})"
        )
    if saved["group"] != group:
        raise ValueError(f"{path}: a {saved['group']} policy, not a {group} policy")
    names = feature_names(group, saved.get("scenario"))
    if list(saved["observation"]["features"]) != names:
        raise ValueError(
            f"{path}: trained on the observation {saved['observation']['features']}, but this "
            f"version's {group} observation is {names}: retrain it"
        )
    return saved


def _from_v0(saved: dict[str, Any], group: str) -> dict[str, Any]:
    """A marlmerge 0.2 file (no `format`) in the current layout."""
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
