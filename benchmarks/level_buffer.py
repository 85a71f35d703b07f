"""What a run's level replay ended with (`[levels]`, marlmerge.training.levels): per run, the
levels in the buffer, how many egos drove them, the most-driven level and its failures, the
levels failed on every one of at least three egos, and the top levels by the run's own score.

    python benchmarks/level_buffer.py runs/peaks3_roads/seed_? [--top 5]

Prints a Markdown table; reads each run's `checkpoint.pt` and `egos.csv`.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from marlmerge.config.codec import from_dict
from marlmerge.config.training import LevelsConfig
from marlmerge.io import files
from marlmerge.training.levels import LevelReplay


def buffer_row(run: Path, top: int) -> str:
    """One run's line of the table."""
    state = files.load(run / "checkpoint.pt")
    saved = json.loads((run / "config.json").read_text())["levels"]
    levels_cfg = from_dict(LevelsConfig, saved)  # the strict loader: defaults for older runs
    replay = LevelReplay(levels_cfg)
    replay.load_state_dict(state["levels"])
    ids = [i for i, lv in replay.levels.items() if lv.episodes > 0]
    eps = np.array([replay.levels[i].episodes for i in ids])
    fails = np.array([replay.levels[i].failures for i in ids])
    with open(run / "egos.csv", newline="") as fh:
        egos = sum(1 for _ in csv.DictReader(fh))
    most = int(np.argmax(eps))
    always = int(((fails == eps) & (eps >= 3)).sum())
    order = np.argsort(-replay.scores(ids), kind="stable")[:top]
    best = ", ".join(f"{fails[j]}/{eps[j]}" for j in order)
    return (
        f"| {run} | {levels_cfg.score}{', roads' if levels_cfg.replay_roads else ''} | "
        f"{len(replay.levels)} | {egos:,} | {eps.sum():,} | {fails[most]}/{eps[most]} "
        f"({eps[most] / egos:.1%} of the egos) | {always} | {best} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="training run folders")
    parser.add_argument("--top", type=int, default=5, help="levels listed by score")
    args = parser.parse_args()
    if args.top < 1:
        parser.error(f"--top must be >= 1, got {args.top}")
    print(
        "| run | levels | in the buffer | egos | egos on them | most-driven level, "
        "failures/egos | always failed (>= 3 egos) | top levels by score, failures/egos |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for run in args.runs:
        if not (run / "checkpoint.pt").is_file():
            parser.error(f"{run}: no checkpoint.pt (not a training run folder?)")
        print(buffer_row(run, args.top))


if __name__ == "__main__":
    main()
