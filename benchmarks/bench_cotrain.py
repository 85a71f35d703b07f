"""Co-training's speed over seeds, printed as JSON: one seed, S seeds in one process, and S
seeds one process each, side by side in one run.

- `one`: one seed (`marlmerge cotrain PRESET --seeds 0`, the same run as `marlmerge cotrain`);
- `vec`: S seeds in one process (`marlmerge cotrain PRESET --seeds 0-S`), with
  `seeds_wall_ratio` (its schedule's wall time over one seed's) and `sweep_throughput_ratio`
  (S / that);
- `workers`: S seeds on `--workers` processes, each co-training its group of seeds in one
  process (`marlmerge sweep PRESET --vectorized --workers W`);
- `sweep`: S seeds one process each on `--workers` workers (`marlmerge sweep PRESET`), and
  its wall time over `vec`'s (`vec_speedup_over_sweep`) and over `workers`'
  (`workers_speedup_over_sweep`), all with their evaluations.

`wall_s` is the schedule (every phase); `with_evaluation_s` adds the ego selection and the
evaluations, which run seed after seed. The default budget is a small one of the `cotrain`
recipe (`BUDGET`); `--own-budget` keeps the recipe's; `--set` changes any key:

    python benchmarks/bench_cotrain.py --seeds 4
    python benchmarks/bench_cotrain.py --seeds 4 --modes one,vec,workers,sweep
    python benchmarks/bench_cotrain.py --seeds 4 --set highway_algorithm=ppo
    python benchmarks/bench_cotrain.py --preset adversary --own-budget --seeds 3 \
        --set ego_init=runs/paper/policy.pt
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import tempfile
import time

from bench_train import seed_ratios, timed_sweep  # the same ratios and sweep

from marlmerge.cli import _parse_sets
from marlmerge.training.cotrain import CoTrainConfig, cotrain_seeds, load_cotrain_config

BUDGET = {
    "ego_pretrain_sim_steps": 100_000,
    "rounds": 1,
    "adversary_sim_steps": 100_000,
    "ego_sim_steps": 100_000,
    "select_episodes": 50,
    "eval_episodes": 100,
}
"""The recipe's schedule cut to 300,000 simulator steps per seed (a phase of each kind)."""


def seeds_run(cfg: CoTrainConfig, seeds: list[int]) -> dict:
    """One `cotrain --seeds` run: its schedule's wall time and each seed's success."""
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        results = cotrain_seeds(cfg, seeds, out, progress=False)
        total = time.perf_counter() - t0
    return {
        "seeds": seeds,
        "wall_s": results[0].wall_s,
        "with_evaluation_s": total,
        "success_rate": [r.evaluation["scripted"]["success_rate"] for r in results],
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--preset", default="cotrain")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--seeds", type=int, default=4, help="S: seeds of the `vec` and `sweep` runs")
    p.add_argument("--workers", type=int, default=2, help="processes of the `sweep` run")
    p.add_argument("--modes", default="one,vec", help="of one, vec, workers, sweep")
    p.add_argument("--own-budget", action="store_true", help="the recipe's schedule, not BUDGET")
    args = p.parse_args()
    logging.getLogger("torchrl").setLevel(logging.WARNING)
    sets = {**({} if args.own_budget else BUDGET), **_parse_sets(args.set)}
    cfg = load_cotrain_config(args.preset, **sets)
    modes = args.modes.split(",")
    if unknown := set(modes) - {"one", "vec", "workers", "sweep"}:
        raise SystemExit(
            f"--modes: unknown {sorted(unknown)}; choose from one, vec, workers, sweep"
        )
    seeds = list(range(cfg.seed, cfg.seed + args.seeds))
    out: dict = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "preset": cfg.name,
        "highway_algorithm": cfg.highway_algorithm,
        "sim_steps_per_seed": sum(n for _, n in cfg.phases()),
    }
    if "one" in modes:
        out["one_seed"] = seeds_run(cfg, seeds[:1])
    if "vec" in modes:
        out["vectorized"] = seeds_run(cfg, seeds)
    if "one" in modes and "vec" in modes:
        out.update(seed_ratios(out["one_seed"], out["vectorized"], len(seeds)))
    if "workers" in modes:
        out["workers"] = timed_sweep(args.preset, sets, seeds, args.workers, vectorized=True)
    if "sweep" in modes:
        out["sweep"] = timed_sweep(args.preset, sets, seeds, args.workers, vectorized=False)
        sweep_s = out["sweep"]["with_evaluation_s"]
        if "vec" in modes:
            out["vec_speedup_over_sweep"] = sweep_s / out["vectorized"]["with_evaluation_s"]
        if "workers" in modes:
            out["workers_speedup_over_sweep"] = sweep_s / out["workers"]["with_evaluation_s"]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
