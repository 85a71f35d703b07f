"""Grid throughput on each backend, side by side, printed as JSON.

The same grid (the rule policies and a learned quadratic-Q policy — an untrained network, which
costs what a trained one does — on four conditions; `--episodes` per cell) runs on the serial
backend, the process backend and a local Ray (`ray.init(num_cpus=workers)`), each into a fresh
folder (nothing reused), for `--rounds` rounds taking turns; medians of episodes/s over rounds
and the ratios process / serial and ray / process from the same rounds are reported. Worker start
(importing torch in each process, Ray's start: about 3 s per worker here) is part of what is
measured, as a user meets it, so small grids (`--episodes 40`) show it rather than the scaling.

    python benchmarks/bench_grid.py [--episodes 400] [--rounds 2] [--workers 2] [--rules-only]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time

from marlmerge.evaluation.grid import parse_policy, run_grid

POLICIES = ("hold", "idm", "gap")
CONDITIONS = (
    "grid_light_mixed",
    "grid_moderate_mixed",
    "grid_dense_mixed",
    "grid_moderate_adversarial",
)


def learned_run(folder: str) -> str:
    """A run folder holding an untrained quadratic-Q policy (as `marlmerge train` saves one)."""
    import torch

    from marlmerge.config import ScenarioConfig
    from marlmerge.sim.observation import EGO_FEATURES
    from marlmerge.training.train import TrainConfig, make_learner, save_policy

    cfg, scen = TrainConfig(update_path="fast"), ScenarioConfig()
    learner = make_learner(cfg, scen, torch.Generator().manual_seed(0), len(EGO_FEATURES))
    os.makedirs(folder, exist_ok=True)
    save_policy(os.path.join(folder, "policy.pt"), cfg, scen, learner)
    return folder


def once(backend: str, policies: list[str], episodes: int, workers: int) -> float:
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        res = run_grid(
            [parse_policy(p) for p in policies],
            list(CONDITIONS),
            episodes=episodes,
            worlds=25,
            out_dir=out,
            progress=False,
            backend=backend,
            workers=workers,
        )
        wall = time.perf_counter() - t0
    if backend == "ray":  # as a fresh `marlmerge grid --backend ray` meets it: Ray starts anew
        import ray

        ray.shutdown()
    return len(res.rows) / wall


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--episodes", type=int, default=400, help="episodes per cell")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--workers", type=int, default=os.cpu_count() or 2)
    p.add_argument("--no-ray", action="store_true", help="skip the Ray backend")
    p.add_argument("--rules-only", action="store_true", help="no learned policy")
    args = p.parse_args()
    backends = ["serial", "process"] + ([] if args.no_ray else ["ray"])
    with tempfile.TemporaryDirectory() as runs:
        policies = list(POLICIES)
        if not args.rules_only:
            policies.append("quadq:" + learned_run(os.path.join(runs, "untrained")))
        once("serial", policies, 2, 1)  # compile and warm outside the timed rounds
        rates: dict[str, list[float]] = {b: [] for b in backends}
        for _ in range(args.rounds):
            for b in backends:
                rates[b].append(once(b, policies, args.episodes, args.workers))
    med = {b: statistics.median(v) for b, v in rates.items()}
    result = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "policies": ["hold", "idm", "gap"] + ([] if args.rules_only else ["quadq (untrained)"]),
        "cells": len(policies) * len(CONDITIONS),
        "episodes_per_cell": args.episodes,
        "workers": args.workers,
        "episodes_per_s": med,
        "per_round": rates,
        "process_over_serial": med["process"] / med["serial"],
    }
    if "ray" in med:
        result["ray_over_process"] = med["ray"] / med["process"]
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
