"""What an action is: finite numbers, one action per agent or world. Every view checks the
actions it is given here, before the core runs, with an error naming the agent or world.

A ramp vehicle's action is its acceleration (m/s^2) and, with `ego.join = "chosen"`, a second
component `join` in [-1, 1] (> 0: change into the right lane now, inside the merge zone): its
`action_size` is 1 or 2. A highway agent's action is its acceleration.

The core itself takes NaN as "drive by IDM" (`TrafficCore.rollout`); a view never passes that on
from a user: a NaN, an infinity, None, a string or a wrongly shaped array is an error.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from marlmerge.config import ScenarioConfig

JOIN_BOUNDS = (-1.0, 1.0)
"""The join component's range (`ego.join = "chosen"`): > 0 joins."""


def component_bounds(cfg: ScenarioConfig) -> tuple[tuple[float, float], ...]:
    """(low, high) of each component of a ramp vehicle's action: the acceleration's
    (`ego.accel_bounds_mps2`, m/s^2), then, with `ego.join = "chosen"`, the join's
    (`JOIN_BOUNDS`)."""
    accel = tuple(cfg.ego.accel_bounds_mps2)
    return (accel, JOIN_BOUNDS) if cfg.ego.chooses_join else (accel,)


def action_size(cfg: ScenarioConfig) -> int:
    """Components of a ramp vehicle's action: 1 (acceleration), 2 with `ego.join = "chosen"`
    (acceleration, join)."""
    return len(component_bounds(cfg))


def action_bounds(cfg: ScenarioConfig) -> tuple[np.ndarray, np.ndarray]:
    """A ramp vehicle's action bounds, (low, high) [action_size] float32 (`component_bounds`)."""
    low, high = zip(*component_bounds(cfg), strict=True)
    return np.array(low, np.float32), np.array(high, np.float32)


def split_actions(a: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Ramp vehicles' actions [N] or [N, 2] (`as_actions`) -> (acceleration [N], join [N] or
    None when there is no join component)."""
    if a.ndim == 1:
        return a, None
    return np.ascontiguousarray(a[:, 0]), np.ascontiguousarray(a[:, 1])


def as_actions(
    value: Any,
    shape: tuple[int, ...],
    who: str = "action",
    exact: bool = False,
    shown: tuple[int, ...] | None = None,
) -> np.ndarray:
    """`value` as a float64 array of `shape`'s size (any array of that size; with `exact`, only
    `shape` itself or a scalar), every entry finite, returned flat [shape[0]] when `shape` holds
    one number per row, else as `shape`; `who` names the agent in errors ("action of
    'ramp_0'"), a bad entry of a batch names its world, and errors name the shape `shown`
    (default `shape`: a view whose action space has another shape of the same size gives it)."""
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError):  # ragged nested lists
        raw = np.asarray(None)
    shown = shape if shown is None else shown
    if raw.dtype.kind not in "iuf":  # None, strings, booleans, objects
        raise ValueError(f"{who} must be a number or an array of shape {shown}, got {value!r}")
    a = raw.astype(np.float64)
    if a.size != math.prod(shape) or (exact and a.shape not in (shape, ())):
        raise ValueError(f"{who} must have shape {shown}, got shape {a.shape} ({value!r})")
    a = a.reshape(shape[0]) if a.size == shape[0] else a.reshape(shape)
    if not (math.isfinite(a.flat[0]) if a.size == 1 else np.isfinite(a).all()):
        bad = ~np.isfinite(a)
        where = f" of world {int(np.argmax(bad.any(-1) if a.ndim > 1 else bad))}"
        where = where if shape[0] > 1 else ""
        raise ValueError(f"{who}{where} must be finite, got {a[bad][0]}")
    return a


def check_can_step(live_agents: list[str], started: bool) -> None:
    """A PettingZoo step needs live agents: before the first reset, or after the episode has
    ended, it is refused, saying which."""
    if not live_agents:
        when = "on a finished episode" if started else "before reset()"
        raise RuntimeError(f"step() called {when}: call reset() first")


def agent_actions(
    actions: Any,
    possible_agents: list[str],
    live_agents: list[str],
    sizes: Mapping[str, int] | None = None,
) -> dict[str, np.ndarray]:
    """A PettingZoo step's actions {agent: action} as {live agent: [size] float64}: a dict, no
    unknown agent, an action for every live agent, each `sizes[agent]` numbers (default 1;
    `as_actions`); the action of a possible agent that is not live is checked the same way,
    then dropped (torchrl's PettingZoo wrapper sends one for every agent of a group)."""
    if not isinstance(actions, dict):
        raise ValueError(f"actions must be a dict of agent -> action, got {type(actions)}")
    unknown = [a for a in actions if a not in possible_agents]
    if unknown:
        raise ValueError(
            f"unknown agent {unknown[0]!r} in actions (possible agents: {possible_agents})"
        )
    missing = [a for a in live_agents if a not in actions]
    if missing:
        raise ValueError(f"no action for live agent {missing[0]!r}")
    out = {}
    for agent, act in actions.items():
        live = agent in live_agents
        who = f"action of {agent!r}" + ("" if live else " (not live this step)")
        size = 1 if sizes is None else sizes.get(agent, 1)
        val = as_actions(act, (size,), who, exact=True).reshape(size)
        if live:
            out[agent] = val  # the core clips to the agent's bounds
    return out
