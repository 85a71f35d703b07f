"""Training-loop speed, printed as JSON: runs a training preset and reports its timing.

- `updates_per_s`: gradient updates per second of update time (sampling from the torchrl replay
  buffer included), `env_steps_per_s`: env steps (per world) per second of collection time,
- `wall_s`: the training loop, compilation included; evaluation and plots are timed apart
  (`eval_and_plots_s`).

    python benchmarks/bench_train.py [--preset quick] [--set key=value ...]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time

from marlmerge.cli import _parse_sets
from marlmerge.training.train import load_train_config, train


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--preset", default="quick")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args()
    cfg = load_train_config(args.preset, **_parse_sets(args.set))
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        result = train(cfg, out, progress=False)
        total = time.perf_counter() - t0
        timing = json.loads(open(os.path.join(out, "timing.json")).read())
    print(
        json.dumps(
            {
                "machine": f"{platform.machine()}, {os.cpu_count()} cores, "
                f"python {platform.python_version()}",
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
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
