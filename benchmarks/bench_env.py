"""Simulator speed, printed as JSON.

- `pettingzoo_env_steps_per_s`: the PettingZoo env with a random ego (uniform accelerations in the
  action bounds) in scripted traffic at the default flow; one env step = `action_repeat` simulator
  steps; episode resets included.
- `core_vehicle_steps_per_s[B]`: the batched core at batch size B, ego random, finished egos
  replaced at once; counts active vehicles advanced per second of wall time.
- `multi_agent_env_steps_per_s`: the torchrl `MultiAgentMergeEnv` (B = 32 worlds, the ego and the
  4 highway agents of each acting, partial resets included), env steps summed over worlds.

    python benchmarks/bench_env.py [--seconds 5]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

import marlmerge
from marlmerge.config import ScenarioConfig
from marlmerge.env import EGO_AGENT
from marlmerge.sim import OUTCOME_NONE, TrafficCore


def bench_pettingzoo(seconds: float, control: str, seed: int = 0) -> dict[str, float]:
    env = marlmerge.parallel_env(control=control)
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    lo, hi = env.cfg.ego.accel_bounds_mps2
    steps = episodes = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        actions = {}
        for a in env.agents:
            if a == EGO_AGENT:
                actions[a] = rng.uniform(lo, hi, size=1)
            else:
                actions[a] = np.zeros(1)
        env.step(actions)
        steps += 1
        if not env.agents:
            env.reset()
            episodes += 1
    wall = time.perf_counter() - t0
    return {"env_steps_per_s": steps / wall, "episodes": episodes, "env_steps": steps}


def bench_core(batch_size: int, seconds: float, seed: int = 0) -> dict[str, float]:
    cfg = ScenarioConfig()
    core = TrafficCore(cfg, batch_size=batch_size, seed=seed)
    rng = np.random.default_rng(seed)
    lo, hi = cfg.ego.accel_bounds_mps2
    vehicle_steps = steps = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        ev = core.step(rng.uniform(lo, hi, size=batch_size))
        vehicle_steps += int(core.state.active.sum())
        steps += 1
        done = ev.ego_outcome != OUTCOME_NONE
        if done.any():
            core.next_ego(done)
    wall = time.perf_counter() - t0
    return {
        "vehicle_steps_per_s": vehicle_steps / wall,
        "world_steps_per_s": steps * batch_size / wall,
        "mean_active_vehicles": vehicle_steps / max(steps * batch_size, 1),
    }


def bench_multi_agent(seconds: float, worlds: int = 32, seed: int = 0) -> dict[str, float]:
    import torch

    from marlmerge.marl_env import GROUP, MultiAgentMergeEnv

    env = MultiAgentMergeEnv(num_worlds=worlds, seed=seed)
    env.set_opponent_mix(1, 0.0)
    gen = torch.Generator().manual_seed(seed)
    td = env.reset()
    steps = 0
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        td.set("action", torch.rand(worlds, 1, generator=gen) * 7.0 - 4.5)
        td.set((GROUP, "action"), torch.rand(worlds, 4, 1, generator=gen) * 2.0 - 1.0)
        _, td = env.step_and_maybe_reset(td)
        steps += 1
    wall = time.perf_counter() - t0
    return {"env_steps_per_s": steps * worlds / wall}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seconds", type=float, default=5.0, help="wall time per measurement")
    args = p.parse_args()
    result = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, "
        f"python {platform.python_version()}",
        "pettingzoo_env_steps_per_s": bench_pettingzoo(args.seconds, "ego")["env_steps_per_s"],
        "pettingzoo_env_steps_per_s_all_agents": bench_pettingzoo(args.seconds, "all")[
            "env_steps_per_s"
        ],
        "core": {str(b): bench_core(b, args.seconds) for b in (1, 64, 1024)},
        "multi_agent_env_steps_per_s": bench_multi_agent(args.seconds)["env_steps_per_s"],
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
