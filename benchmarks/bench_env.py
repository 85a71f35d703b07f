"""Simulator speed against libsumo on the same road, measured side by side, printed as JSON.

Each measurement runs for `--seconds` of wall time, and all of them take turns for `--rounds`
rounds (libsumo, then every marlmerge measurement, then libsumo again, ...), so that the shared
host's load drifts the same for every one; medians over rounds are reported, and ratios to
libsumo from the same rounds.

- `libsumo`: SUMO on the scenario's road with its ramp (`marlmerge.validation.sumo.RampRoad`):
  the mainline fed marlmerge's drawn arrivals, a ramp vehicle at a time; simulator steps/s and
  vehicle-steps/s (vehicles in the network summed over steps).
- `pettingzoo_ego` / `pettingzoo_all`: the PettingZoo env (`control="ego"`, random ego; default
  `control="all"` with scripted highway policies); simulator steps/s as the core counts them
  (an env step is up to `action_repeat` of them), episode resets included.
- `core_B1_rollout` / `core_B1_step`: the core at B = 1, `rollout` (one env step) or `step`
  (one simulator step) per call, random ego, finished egos replaced at once.
- `core_B{256,1024,4096}`: the batched core, one `rollout` per call; vehicle-steps/s and the
  cost per vehicle-step; `core_B1024_flow{400,2000}`: the same at other flows.
- `torchrl_B256`: `BatchedMergeEnv` with 256 worlds, random actions, `step_and_maybe_reset`.

    python benchmarks/bench_env.py [--seconds 3] [--rounds 3] [--quick]

`--cold` instead measures a cold start: a fresh process with an empty kernel cache creates a
core and runs one call of each kernel (compilation included), then a second process with the
cache filled does the same.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable

import numpy as np

import marlmerge
from marlmerge.config import ScenarioConfig
from marlmerge.sim import OUTCOME_NONE, TrafficCore
from marlmerge.views.pettingzoo_env import EGO_AGENT

Measure = Callable[[float], dict[str, float]]


def pettingzoo(control: str, seed: int = 0) -> Measure:
    env = marlmerge.parallel_env(control=control)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    lo, hi = env.cfg.ego.accel_bounds_mps2
    policy = marlmerge.ScriptedHighwayPolicy("neutral", env.cfg)
    obs = {}

    def run(seconds: float) -> dict[str, float]:
        nonlocal obs
        st = env.core.state  # type: ignore[union-attr]
        steps0, env_steps = int(st.steps[0]), 0
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            actions = {}
            for a in env.agents:
                if a == EGO_AGENT:
                    actions[a] = rng.uniform(lo, hi, size=1)
                else:
                    actions[a] = policy(obs[a]) if a in obs else np.zeros(1)
            obs, *_ = env.step(actions)
            env_steps += 1
            if not env.agents:
                obs, _ = env.reset()
        wall = time.perf_counter() - t0
        return {
            "sim_steps_per_s": (int(st.steps[0]) - steps0) / wall,
            "env_steps_per_s": env_steps / wall,
        }

    return run


def core(batch: int, k: int | None, flow: float | None = None, seed: int = 0) -> Measure:
    cfg = ScenarioConfig()
    if flow is not None:
        cfg = cfg.replace(**{"traffic.flow_vph_per_lane": flow})
    c = TrafficCore(cfg, batch_size=batch, seed=seed)
    rng = np.random.default_rng(seed)
    lo, hi = cfg.ego.accel_bounds_mps2

    def run(seconds: float) -> dict[str, float]:
        st = c.state
        v0, s0 = int(st.vehicle_steps.sum()), int(st.steps.sum())
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            a = rng.uniform(lo, hi, size=batch)
            out = c.step(a) if k == 1 else c.rollout(a)
            done = out.ego_outcome != OUTCOME_NONE
            if done.any():
                c.next_ego(done)
        wall = time.perf_counter() - t0
        vs, ss = int(st.vehicle_steps.sum()) - v0, int(st.steps.sum()) - s0
        return {
            "vehicle_steps_per_s": vs / wall,
            "world_steps_per_s": ss / wall,
            "ns_per_vehicle_step": wall / max(vs, 1) * 1e9,
            "vehicles_per_world": vs / max(ss, 1),
        }

    return run


def torchrl_env(worlds: int, seed: int = 0) -> Measure:
    import torch

    from marlmerge.views.torchrl_env import BatchedMergeEnv

    env = BatchedMergeEnv(num_worlds=worlds, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    td = env.reset()

    def run(seconds: float) -> dict[str, float]:
        nonlocal td
        steps = 0
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            td.set("action", torch.rand(worlds, 1, generator=gen) * 7.0 - 4.5)
            _, td = env.step_and_maybe_reset(td)
            steps += 1
        wall = time.perf_counter() - t0
        return {"env_steps_per_s": steps * worlds / wall}

    return run


def libsumo_road(seconds_total: float) -> tuple[Measure | None, Callable[[], None]]:
    from marlmerge.validation import sumo

    if not sumo.available():
        return None, lambda: None
    # simulated time to cover every round at up to ~20,000 steps/s
    road = sumo.RampRoad(ScenarioConfig(), duration_s=seconds_total * 2000.0).__enter__()

    def run(seconds: float) -> dict[str, float]:
        steps = vehicles = 0
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            road.step()
            vehicles += road.vehicle_count()
            steps += 1
        wall = time.perf_counter() - t0
        return {"sim_steps_per_s": steps / wall, "vehicle_steps_per_s": vehicles / wall}

    return run, lambda: road.__exit__(None, None, None)


def measure_all(seconds: float, rounds: int, quick: bool) -> dict[str, object]:
    sumo_run, sumo_close = libsumo_road(seconds * rounds)
    ours: dict[str, Measure] = {
        "pettingzoo_ego": pettingzoo("ego"),
        "pettingzoo_all": pettingzoo("all"),
        "core_B1_rollout": core(1, None),
        "core_B1_step": core(1, 1),
        "core_B256": core(256, None),
        "core_B1024": core(1024, None),
        "torchrl_B256": torchrl_env(256),
    }
    if not quick:
        ours["core_B4096"] = core(4096, None)
        ours["core_B1024_flow400"] = core(1024, None, 400.0)
        ours["core_B1024_flow2000"] = core(1024, None, 2000.0)
    samples: dict[str, list[dict[str, float]]] = {k: [] for k in ours}
    sumo_samples: list[dict[str, float]] = []
    for fn in ours.values():  # compile and warm every kernel outside the timed rounds
        fn(0.2)
    for _ in range(rounds):
        if sumo_run is not None:
            sumo_samples.append(sumo_run(seconds))
        for name, fn in ours.items():
            samples[name].append(fn(seconds))
    sumo_close()

    def med(rows: list[dict[str, float]]) -> dict[str, float]:
        return {k: statistics.median(r[k] for r in rows) for k in rows[0]}

    result: dict[str, object] = {k: med(v) for k, v in samples.items()}
    if sumo_samples:
        s = med(sumo_samples)
        result["libsumo"] = s
        result["ratios_to_libsumo"] = {
            "pettingzoo_ego_sim_steps": result["pettingzoo_ego"]["sim_steps_per_s"]
            / s["sim_steps_per_s"],
            "pettingzoo_all_sim_steps": result["pettingzoo_all"]["sim_steps_per_s"]
            / s["sim_steps_per_s"],
            "core_B1_rollout_vehicle_steps": result["core_B1_rollout"]["vehicle_steps_per_s"]
            / s["vehicle_steps_per_s"],
            "core_B1_step_vehicle_steps": result["core_B1_step"]["vehicle_steps_per_s"]
            / s["vehicle_steps_per_s"],
        }
    return result


COLD_CODE = """
import time, numpy as np
t0 = time.perf_counter()
from marlmerge.config import ScenarioConfig
from marlmerge.sim import TrafficCore
t1 = time.perf_counter()
for parallel in (False, True):
    c = TrafficCore(ScenarioConfig(), batch_size=2, seed=0, parallel=parallel)
    out = c.rollout(np.zeros(2)); c.next_ego(np.ones(2, bool)); c.observe(); c.pick_roster(4)
    c.step(np.zeros(2))
print(t1 - t0, time.perf_counter() - t1)
"""


def cold_start() -> dict[str, float]:
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for label in ("cold", "warm"):
            t = time.perf_counter()
            res = subprocess.run(
                [sys.executable, "-c", COLD_CODE],
                env=env,
                capture_output=True,
                text=True,
                check=True,
            )
            imp, first = map(float, res.stdout.split())
            out[f"{label}_import_s"] = imp
            out[f"{label}_first_calls_s"] = first
            out[f"{label}_process_s"] = time.perf_counter() - t
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seconds", type=float, default=3.0, help="wall time per measurement")
    p.add_argument("--rounds", type=int, default=3, help="rounds of all measurements")
    p.add_argument("--quick", action="store_true", help="skip B = 4096 and the flow variants")
    p.add_argument("--cold", action="store_true", help="measure the cold start instead")
    args = p.parse_args()
    result: dict[str, object] = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, "
        f"python {platform.python_version()}"
    }
    if args.cold:
        result["cold_start"] = cold_start()
    else:
        result.update(measure_all(args.seconds, args.rounds, args.quick))
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
