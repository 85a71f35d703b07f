"""The simulation against committed trajectories: a change of the simulator's numbers fails here.

Refactors of the core (`marlmerge.sim`) must leave every reported result as it is. The other
tests check behaviour and that a run repeats itself; this one checks that a run repeats the
committed one, for the paper's mode, `hardened_mix` (traffic drawn per road: flows, limits,
drivers, adversaries; the extended observation), `lapses` (drivers' attention lapses) and ramp
flow: every 10 calls of `rollout`, each world's traffic (sum of positions and speeds of its
vehicles, and how many), and the ego's observations, reward terms and outcomes summed so far.

A change that is meant to change the simulation bumps the env version and regenerates every
result (`docs/results.md#remaking-every-result`); then the reference is rewritten with

    python tests/test_golden_trajectories.py --write

The comparison allows a relative 1e-7: the reference is meant to catch a changed model (a
default, a rule, an order of updates), and a trajectory that is the same but for the last bits
of a sum would still agree.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from marlmerge.config import ScenarioConfig
from marlmerge.config.presets import resolve_config
from marlmerge.sim import OUTCOME_NONE, TrafficCore
from marlmerge.sim import layout as L

REFERENCE = Path(__file__).with_name("golden_trajectories.json")
WORLDS, CALLS, EVERY, SEED = 3, 200, 10, 0
RTOL, ATOL = 1e-7, 1e-6


def scenarios() -> dict[str, ScenarioConfig]:
    return {
        "paper": ScenarioConfig(),
        "hardened_mix": resolve_config("hardened_mix"),
        "lapses": resolve_config("lapses"),
        "ramp_flow": ScenarioConfig().replace(**{"ramp.flow_vph": 600.0}),
    }


def trajectory(cfg: ScenarioConfig) -> np.ndarray:
    """[CALLS // EVERY, WORLDS, 6] after every EVERY-th call, per world: the sum of the
    vehicles' x (m) and v (m/s) and their count; and summed over all calls so far, the ego's
    observation, its reward terms and its outcomes (`OUTCOME_*` codes)."""
    core = TrafficCore(cfg, batch_size=WORLDS, seed=SEED)
    rng = np.random.default_rng(SEED)
    lo, hi = cfg.ego.accel_bounds_mps2
    rows, ego = [], np.zeros((WORLDS, 3))  # [B, 3] the ego's sums so far
    for call in range(CALLS):
        out = core.rollout(rng.uniform(lo, hi, size=WORLDS))
        ego += np.stack(
            [out.ego_obs.astype(np.float64).sum(1), out.ego_terms.sum(1), out.ego_outcome], 1
        )
        if (call + 1) % EVERY == 0:
            on = core.vi[:, L.VI_ACTIVE, :] == 1  # [B, slots]
            traffic = [np.where(on, core.vf[:, row, :], 0.0).sum(1) for row in (L.VF_X, L.VF_V)]
            rows.append(np.column_stack([*traffic, on.sum(1), ego]))
        done = out.ego_outcome != OUTCOME_NONE
        if not cfg.ramp.flowing and done.any():
            core.next_ego(done)
    return np.stack(rows)


def first_difference(got: np.ndarray, want: np.ndarray) -> str:
    bad = ~np.isclose(got, want, rtol=RTOL, atol=ATOL)
    row, world, col = (int(i) for i in np.argwhere(bad)[0])
    names = ("sum of x", "sum of v", "vehicles", "ego observation", "ego terms", "outcomes")
    ours, theirs = float(got[row, world, col]), float(want[row, world, col])
    return (
        f"call {(row + 1) * EVERY}, world {world}, {names[col]}: {ours!r} against the "
        f"reference's {theirs!r} ({int(bad.sum())} values differ)"
    )


@pytest.mark.parametrize("name", list(scenarios()))
def test_the_simulation_repeats_the_committed_trajectory(name):
    want = np.asarray(json.loads(REFERENCE.read_text())[name])
    got = trajectory(scenarios()[name])
    assert got.shape == want.shape
    assert np.allclose(got, want, rtol=RTOL, atol=ATOL), (
        f"{name}: the simulation changed ({first_difference(got, want)}). If that is meant, bump "
        "the env version, regenerate the results and rewrite the reference (module docstring)."
    )


def test_a_changed_driver_default_fails_the_comparison():
    """The comparison sees a small change of the model: the drivers' time headways drawn up to
    1.81 s instead of 1.8 s."""
    want = np.asarray(json.loads(REFERENCE.read_text())["paper"])
    changed = ScenarioConfig().replace(**{"driver.time_headway_s": (1.0, 1.81)})
    got = trajectory(changed)
    assert not np.allclose(got, want, rtol=RTOL, atol=ATOL)


if __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    data = {name: trajectory(cfg).tolist() for name, cfg in scenarios().items()}
    REFERENCE.write_text(json.dumps(data, separators=(",", ":")) + "\n")
    print(f"wrote {REFERENCE}")
