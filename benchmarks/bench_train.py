"""Training-loop speed, printed as JSON: runs a training preset and reports its timing.

- `updates_per_s`: gradient updates per second of update time (sampling from the torchrl replay
  buffer included), `env_steps_per_s`: env steps (per world) per second of collection time,
- `wall_s`: the training loop, compilation included; evaluation and plots are timed apart
  (`eval_and_plots_s`).

With `--seeds S`, the same run measures, one after the other (`--modes`, default `one,vec`):

- `one`: one seed (`marlmerge train --seeds 0`, the same run as `marlmerge train`);
- `vec`: S seeds in one process (`marlmerge train --seeds 0-S`), with `seeds_wall_ratio`, its
  training loop's wall time over one seed's (the target is <= 2.5 at S = 8), and
  `sweep_throughput_ratio` (S / that);
- `workers`: S seeds in `--workers` processes, each training its group of seeds in one process
  (`marlmerge sweep --vectorized --workers W`), evaluations included, with `workers_wall_ratio`
  against one seed's run with its evaluation;
- `sweep`: today's sweep of the S seeds, one process per seed on `--workers` workers, and
  `vectorized_speedup`: its wall time over the `workers` run's (both with evaluations).

    python benchmarks/bench_train.py [--preset quick] [--set key=value ...]
    python benchmarks/bench_train.py --preset paper --seeds 8
    python benchmarks/bench_train.py --preset paper --seeds 8 --workers 2 --modes one,vec,workers
    python benchmarks/bench_train.py --preset paper --seeds 5 --workers 2 --modes workers,sweep

With `--devices cpu,cuda` the run is measured on each device in turn (`device` of the recipe),
with `speedup` against the first device's training loop; with `--seeds S`, one seed and S seeds
in one process on each device, with each device's `seeds_wall_ratio`:

    python benchmarks/bench_train.py --preset paper --devices cpu,cuda [--seeds 8]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import platform
import tempfile
import time
from pathlib import Path

from marlmerge.cli import _parse_sets
from marlmerge.training.train import TrainConfig, load_train_config, train


def machine() -> str:
    return f"{platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}"


def single_run(cfg: TrainConfig) -> dict:
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        result = train(cfg, out, progress=False)
        total = time.perf_counter() - t0
        timing = json.loads(open(os.path.join(out, "timing.json")).read())
    return {
        "machine": machine(),
        "preset": cfg.name,
        "total_sim_steps": result.sim_steps,
        "updates": result.updates,
        "update_path": cfg.update_path,
        "updates_per_s": timing["updates_per_s"],
        "env_steps_per_s": timing["env_steps_per_s"],
        "compile_s": timing["compile_s"],
        "wall_s": timing["wall_s"],
        "eval_and_plots_s": total - timing["wall_s"],
        "evaluation": result.evaluation,
    }


def seeds_run(cfg: TrainConfig, seeds: list[int]) -> dict:
    """One `train --seeds` run: its loop's wall time and each seed's evaluation."""
    from marlmerge.training.seeds import train_seeds

    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        results = train_seeds(cfg, seeds, out, progress=False)
        total = time.perf_counter() - t0
    r = results[0]
    return {
        "seeds": seeds,
        "wall_s": r.wall_s,
        "update_s": r.update_s,
        "collect_s": r.collect_s,
        "compile_s": r.compile_s,
        "with_evaluation_s": total,
        "updates_per_s": sum(x.updates for x in results) / max(r.update_s, 1e-9),
        "success_rate": [x.evaluation and x.evaluation["success_rate"] for x in results],
    }


def seed_ratios(one: dict, vec: dict, n_seeds: int) -> dict:
    """S seeds in one process against one seed: `seeds_wall_ratio` (their loops' wall times)
    and `sweep_throughput_ratio` (S / that)."""
    ratio = vec["wall_s"] / one["wall_s"]
    return {"seeds_wall_ratio": ratio, "sweep_throughput_ratio": n_seeds / ratio}


def timed_sweep(preset: str, sets: dict, seeds: list[int], workers: int, vectorized: bool) -> dict:
    from marlmerge.training.sweep import sweep

    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        summary = sweep(
            preset, seeds, Path(out), sets, "process", workers, progress=False,
            vectorized=vectorized,
        )  # fmt: skip
        wall = time.perf_counter() - t0
    success = [summary["per_seed"][str(s)]["success_rate"] for s in seeds]
    return {"workers": workers, "with_evaluation_s": wall, "success_rate": success}


def on_devices(cfg: TrainConfig, devices: list[str], n_seeds: int | None) -> dict:
    """The run on each device, one after the other; every device is checked before the first
    run starts. With `n_seeds`, each device runs one seed and then `n_seeds` in one process,
    with `seeds_wall_ratio` (S seeds' training loop over one seed's) per device."""
    from marlmerge.learners.common import resolve_device

    cfgs = [dataclasses.replace(cfg, device=d) for d in devices]  # checks the values
    try:
        for c in cfgs:
            resolve_device(c.device)
    except ValueError as e:
        raise SystemExit(f"--devices: {e}") from None
    out: dict = {"machine": machine(), "preset": cfg.name, "update_path": cfg.update_path}
    seeds = list(range(cfg.seed, cfg.seed + (n_seeds or 1)))
    for c in cfgs:
        if n_seeds is None:
            out[c.device] = single_run(c)
            out[c.device]["speedup"] = out[devices[0]]["wall_s"] / out[c.device]["wall_s"]
            continue
        one, vec = seeds_run(c, seeds[:1]), seeds_run(c, seeds)
        first = out.get(devices[0], {"one_seed": one, "vectorized": vec})
        out[c.device] = {
            "one_seed": one,
            "vectorized": vec,
            "seeds_wall_ratio": vec["wall_s"] / one["wall_s"],
            "speedup_one_seed": first["one_seed"]["wall_s"] / one["wall_s"],
            "speedup_vectorized": first["vectorized"]["wall_s"] / vec["wall_s"],
        }
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--preset", default="quick")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--seeds", type=int, default=None, help="compare S seeds in one run to 1")
    p.add_argument("--workers", type=int, default=2, help="processes of `workers` and `sweep`")
    p.add_argument("--modes", default="one,vec", help="of one, vec, workers, sweep")
    p.add_argument("--devices", default=None, help="e.g. cpu,cuda: the run on each device")
    args = p.parse_args()
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # its INFO lines go to stdout
    sets = _parse_sets(args.set)
    cfg = load_train_config(args.preset, **sets)
    if args.devices is not None:
        print(json.dumps(on_devices(cfg, args.devices.split(","), args.seeds), indent=2))
        return
    if args.seeds is None:
        print(json.dumps(single_run(cfg), indent=2))
        return
    modes = args.modes.split(",")
    unknown = sorted(set(modes) - {"one", "vec", "workers", "sweep"})
    if unknown:
        raise SystemExit(f"--modes: unknown {unknown}; choose from one, vec, workers, sweep")
    seeds = list(range(cfg.seed, cfg.seed + args.seeds))
    out: dict = {"machine": machine(), "preset": cfg.name, "update_path": cfg.update_path}
    if "one" in modes:
        out["one_seed"] = seeds_run(cfg, seeds[:1])
    if "vec" in modes:
        out["vectorized"] = seeds_run(cfg, seeds)
    if "one" in modes and "vec" in modes:
        out.update(seed_ratios(out["one_seed"], out["vectorized"], args.seeds))
    if "workers" in modes:
        out["workers"] = timed_sweep(args.preset, sets, seeds, args.workers, vectorized=True)
        if "one" in modes:
            one = out["one_seed"]["with_evaluation_s"]
            out["workers_wall_ratio"] = out["workers"]["with_evaluation_s"] / one
    if "sweep" in modes:
        out["sweep"] = timed_sweep(args.preset, sets, seeds, args.workers, vectorized=False)
        if "workers" in modes:
            vec = out["workers"]["with_evaluation_s"]
            out["vectorized_speedup"] = out["sweep"]["with_evaluation_s"] / vec
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
