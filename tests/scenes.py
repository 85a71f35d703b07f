"""Hand-built scenes for tests: an empty road, one ego, the vehicles a test places."""

from __future__ import annotations

from typing import Any

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.sim import EGO, TrafficCore

EMPTY_ROAD = {
    "traffic.flow_vph_per_lane": 0.0,
    "traffic.warmup_s": 0.0,
    "driver.lane_change_threshold_mps2": 1.0e6,  # nobody changes lanes
}


def empty_road(overrides: dict[str, Any] | None = None, batch_size: int = 1) -> TrafficCore:
    """A core whose roads hold only a fresh ego at the ramp start (no arrivals)."""
    cfg = ScenarioConfig().replace(**{**EMPTY_ROAD, **(overrides or {})})
    core = TrafficCore(cfg, batch_size=batch_size, seed=0)
    core.clear_traffic()
    core.next_ego(np.ones(batch_size, dtype=bool))
    return core


def scene(
    ego: tuple[float, float],
    right: list[tuple[float, float]] = (),
    left: list[tuple[float, float]] = (),
    overrides: dict[str, Any] | None = None,
) -> TrafficCore:
    """One world: the ego at (x_m, v_mps), and neutral vehicles at (x_m, v_mps) in each lane,
    driving at their speed (desired speed = that speed)."""
    core = empty_road(overrides)
    for lane, vehicles in ((0, right), (1, left)):
        for x, v in vehicles:
            core.add_vehicle(0, x, v, lane, v0_mps=max(v, 1.0))
    core.place(0, EGO, ego[0], ego[1])
    return core


def same_with_and_without_jit(code: str, tmp_path: Any) -> bool:
    """Run `code` (a script saving an array to `sys.argv[1]`) compiled and as plain Python
    (`NUMBA_DISABLE_JIT=1`); True if both save the same array."""
    import os
    import subprocess
    import sys

    results = []
    for disable in ("0", "1"):
        path = tmp_path / f"jit_{disable}.npy"
        env = dict(os.environ, NUMBA_DISABLE_JIT=disable)
        subprocess.run([sys.executable, "-c", code, str(path)], env=env, check=True, timeout=600)
        results.append(np.load(path))
    return bool(np.array_equal(results[0], results[1]))
