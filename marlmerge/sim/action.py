"""What an action is: a finite number (m/s^2), one per agent or world. Every view checks the
actions it is given here, before the core runs, with an error naming the agent or world.

The core itself takes NaN as "drive by IDM" (`TrafficCore.rollout`); a view never passes that on
from a user: a NaN, an infinity, None, a string or a wrongly shaped array is an error.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def as_actions(
    value: Any, shape: tuple[int, ...], who: str = "action", exact: bool = False
) -> np.ndarray:
    """`value` as a flat float64 array of `shape`'s size (any array of that size; with `exact`,
    only `shape` itself or a scalar), every entry finite; `who` names the agent in errors
    ("action of 'ramp_0'"), and a bad entry of a batch names its world."""
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError):  # ragged nested lists
        raw = np.asarray(None)
    if raw.dtype.kind not in "iuf":  # None, strings, booleans, objects
        raise ValueError(f"{who} must be a number or an array of shape {shape}, got {value!r}")
    a = raw.astype(np.float64)
    if a.size != math.prod(shape) or (exact and a.shape not in (shape, ())):
        raise ValueError(f"{who} must have shape {shape}, got shape {a.shape} ({value!r})")
    a = a.reshape(shape[0])
    if not (math.isfinite(a[0]) if a.size == 1 else np.isfinite(a).all()):
        bad = ~np.isfinite(a)
        where = f" of world {int(np.argmax(bad))}" if a.size > 1 else ""
        raise ValueError(f"{who}{where} must be finite, got {a[bad][0]}")
    return a


def agent_actions(
    actions: Any, possible_agents: list[str], live_agents: list[str]
) -> dict[str, float]:
    """A PettingZoo step's actions {agent: action} as {live agent: m/s^2}: a dict, no unknown
    agent, an action for every live agent, each one number (`as_actions`); the action of a
    possible agent that is not live is checked the same way, then dropped (torchrl's PettingZoo
    wrapper sends one for every agent of a group)."""
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
        val = float(as_actions(act, (1,), who, exact=True)[0])
        if live:
            out[agent] = val  # the core clips to the agent's bounds
    return out
