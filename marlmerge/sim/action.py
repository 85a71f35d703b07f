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
