"""The tables of docs/robustness.md from the two grids' episodes.csv.

    python benchmarks/robustness_tables.py runs/robustness_grid/episodes.csv \
        runs/robustness_sensing/episodes.csv

Prints, in Markdown: the main table (36 conditions, perfect sensing; collisions by set), the
second held-out set alone, realistic sensing, the core's safety filter and the targets of the
best configuration. Conditions are grouped by their label: `heldout ...` is the first
held-out set, `heldout2 ...` the second, the rest the grid.
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from marlmerge.evaluation.grid import run_name

NAMES = {
    "gap": "gap acceptance",
    "paper": "quadratic Q, paper recipe",
    "paper@shield": "paper recipe behind the shield",
    "robust": "`robust`",
    "robust@shield": "`robust` behind the shield",
    "robust2": "`robust2` (tuned on the grid)",
    "robust_dqn": "DQN, `robust_dqn`",
    "robust_td3": "TD3, `robust_td3`",
    "robust3": "`robust3`",
    "robust3@shield": "`robust3` behind the shield",
    "robust4": "`robust4`",
    "robust4@shield": "**`robust4` behind the shield**",
}
"""The policies of the tables, in order, and how the tables name them (the `@filter` variants
are reported in one sentence)."""
OUTCOMES = ("success", "collision", "truncation")
SECOND_ROUND = ("robust3", "robust3@shield", "robust4", "robust4@shield")
BEST = "robust4@shield"


def load(path: str) -> dict[str, dict[str, np.ndarray]]:
    """policy -> column -> values [n] (run, condition, episode as strings; the rest as floats)."""
    cols: dict[str, dict[str, list]] = defaultdict(lambda: defaultdict(list))
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            c = cols[r["policy"]]
            c["run"].append(run_name(r["run"]))
            c["condition"].append(r["condition"])
            c["episode"].append(r["episode"])
            for k in ("success", "collision", "truncation", "time_to_merge_s", "max_abs_jerk_mps3"):
                c[k].append(float(r[k]))
    return {p: {k: np.array(v) for k, v in c.items()} for p, c in cols.items()}


def subset(d: dict[str, np.ndarray], keep: np.ndarray) -> dict[str, np.ndarray]:
    return {k: v[keep] for k, v in d.items()}


def which_set(conditions: np.ndarray) -> np.ndarray:
    """'grid', 'heldout' or 'heldout2' for each condition label."""
    first = np.char.partition(conditions.astype(str), " ")[:, 0]
    return np.where(np.isin(first, ("heldout", "heldout2")), first, "grid")


def in_set(d: dict[str, np.ndarray] | None, name: str | None) -> dict[str, np.ndarray] | None:
    """`d` restricted to one condition set (None: all of it)."""
    if d is None or name is None:
        return d
    return subset(d, which_set(d["condition"]) == name)


def nice(cond: str) -> str:
    return cond.replace("heldout2 ", "held-out 2 ").replace("heldout ", "held-out ")


@dataclass(frozen=True)
class Worst:
    """A policy's worst condition pooled over its runs, and its worst (run, condition)."""

    cond: str
    success: float
    run: str
    run_cond: str
    run_success: float

    @property
    def cell(self) -> str:
        return f"{nice(self.cond)} {100 * self.success:.1f} %"

    def seed(self, single: bool) -> str:
        if single:
            return "(one policy)"
        where = "there" if self.run_cond == self.cond else f"in {nice(self.run_cond)}"
        return f"{self.run.rsplit('_', 1)[-1]} {where}: {100 * self.run_success:.1f} %"


def worst(d: dict[str, np.ndarray]) -> Worst:
    conds = np.unique(d["condition"])
    pooled = {c: d["success"][d["condition"] == c].mean() for c in conds}
    wc = min(pooled, key=pooled.get)
    runs = {
        (run, c): d["success"][(d["run"] == run) & (d["condition"] == c)].mean()
        for run in np.unique(d["run"])
        for c in conds
    }
    (run, c), s = min(runs.items(), key=lambda kv: kv[1])
    return Worst(wc, float(pooled[wc]), run, c, float(s))


def pct(x: np.ndarray, digits: int = 2) -> str:
    return f"{100 * x.mean():.{digits}f} %"


def collisions_by_set(d: dict[str, np.ndarray]) -> str:
    """'grid | held-out 1 | held-out 2' collision rates."""
    sets = which_set(d["condition"])
    return " | ".join(pct(d["collision"][sets == x]) for x in ("grid", "heldout", "heldout2"))


def merge_time(d: dict[str, np.ndarray]) -> float:
    return float(np.nanmean(d["time_to_merge_s"]))


def jerk(d: dict[str, np.ndarray]) -> float:
    return float(np.nanmean(d["max_abs_jerk_mps3"]))


def main_table(g: dict) -> list[str]:
    out = [
        "| policy | grid | held-out 1 | held-out 2 | all 36: success / collision / truncation "
        "| worst cell | worst seed in a cell | time to merge | max jerk |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for p, name in NAMES.items():
        if p not in g:
            continue
        d = g[p]
        rates = " / ".join(f"{100 * d[k].mean():.2f}" for k in OUTCOMES)
        w = worst(d)
        out.append(
            f"| {name} | {collisions_by_set(d)} | {rates} % | {w.cell} | "
            f"{w.seed(p.startswith('gap'))} | "
            f"{merge_time(d):.1f} s | {jerk(d):.1f} m/s³ |"
        )
    return out


def second_set_table(g: dict) -> list[str]:
    two = {p: in_set(d, "heldout2") for p, d in g.items()}
    out = [
        f"On the second held-out set alone, against gap acceptance's merge time there "
        f"({merge_time(two['gap']):.1f} s) and the paper recipe's max jerk "
        f"({jerk(g['paper']):.1f} m/s³):",
        "",
        "| policy | success | collision | worst cell | worst seed in a cell | time to merge | "
        "max jerk |",
        "|---|---|---|---|---|---|---|",
    ]
    for p in SECOND_ROUND:
        if p in two:
            d = two[p]
            w = worst(d)
            out.append(
                f"| {NAMES[p]} | {pct(d['success'])} | {pct(d['collision'])} | {w.cell} | "
                f"{w.seed(False)} | "
                f"{merge_time(d):.1f} s | {jerk(d):.1f} m/s³ |"
            )
    return out


def sensing_table(s: dict) -> list[str]:
    out = [
        "| policy | success | collision | truncation | worst cell | worst seed in a cell |",
        "|---|---|---|---|---|---|",
    ]
    for p, name in NAMES.items():
        if p in s:
            d = s[p]
            w = worst(d)
            out.append(
                f"| {name} | {pct(d['success'])} | {pct(d['collision'])} | "
                f"{pct(d['truncation'])} | {w.cell} | {w.seed(p.startswith('gap'))} |"
            )
    return out


def filter_sentence(g: dict) -> list[str]:
    pairs = [(p, f"{p}@filter") for p in ("gap", "paper", "robust", "robust2")]
    parts = [
        f"{pct(g[a]['collision'])} → {pct(g[b]['collision'])} ({a})"
        for a, b in pairs
        if a in g and b in g
    ]
    trunc = pct(g["gap@filter"]["truncation"], 1) if "gap@filter" in g else "?"
    return [
        "The core's safety filter, all 36 conditions, perfect sensing: collisions "
        + ", ".join(parts)
        + f"; gap acceptance behind it is truncated in {trunc}."
    ]


def targets(g: dict, s: dict) -> list[str]:
    """The targets of the best configuration, each marked met or not."""
    if BEST not in g:
        return []
    cols = []
    for keep in (None, "heldout2"):
        d, gap, sd = (in_set(x, keep) for x in (g[BEST], g["gap"], s.get(BEST)))
        w = worst(d)
        rows = [
            (d["collision"].mean() <= 0.001, pct(d["collision"])),
            (d["success"].mean() >= 0.995, pct(d["success"])),
            (w.success >= 0.99, w.cell),
            (w.run_success >= 0.98, w.seed(False)),
            (merge_time(d) <= merge_time(gap), f"{merge_time(d):.1f} vs {merge_time(gap):.1f} s"),
            (jerk(d) <= jerk(g["paper"]), f"{jerk(d):.1f} vs {jerk(g['paper']):.1f} m/s³"),
            (
                sd is not None and sd["collision"].mean() <= 0.005,
                pct(sd["collision"]) if sd is not None else "-",
            ),
        ]
        cols.append([f"**met**: {v}" if ok else f"not met: {v}" for ok, v in rows])
    names = (
        "pooled collisions ≤ 0.1 %",
        "success ≥ 99.5 %",
        "no cell below 99 % (pooled policy)",
        "no seed below 98 % in any cell",
        "merge time no longer than gap acceptance's",
        "max jerk no worse than the paper recipe's",
        "realistic sensing ≤ 0.5 % collisions",
    )
    out = ["| target | all 36 conditions | second held-out set only |", "|---|---|---|"]
    for i, n in enumerate(names):
        out.append(f"| {n} | {cols[0][i]} | {cols[1][i]} |")
    return out


RESULTS_NAMES = {
    "gap": "gap acceptance",
    "paper": "quadratic Q, paper recipe",
    "paper@shield": "quadratic Q, paper recipe, shielded",
    "robust": "quadratic Q, `robust`",
    "robust3": "quadratic Q, `robust3`",
    "robust3@shield": "quadratic Q, `robust3`, shielded",
    "robust4@shield": "quadratic Q, `robust4`, shielded",
    "robust_dqn": "DQN, `robust_dqn`",
    "robust_td3": "TD3, `robust_td3`",
}
"""The rows of the short table in docs/results.md."""


def results_table(g: dict, s: dict) -> list[str]:
    out = [
        "| policy | grid | held-out 1 | held-out 2 | worst seed in a cell | max jerk | "
        "with realistic sensing |",
        "|---|---|---|---|---|---|---|",
    ]
    for p, name in RESULTS_NAMES.items():
        if p in g and p in s:
            d = g[p]
            out.append(  # one run (gap acceptance): its worst cell is its worst run's
                f"| {name} | {collisions_by_set(d)} | {100 * worst(d).run_success:.1f} % | "
                f"{jerk(d):.1f} m/s³ | {pct(s[p]['collision'])} |"
            )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("grid", help="the perfect-sensing grid's episodes.csv")
    ap.add_argument("sensing", help="the realistic-sensing grid's episodes.csv")
    args = ap.parse_args()
    g, s = load(args.grid), load(args.sensing)
    for block in (
        main_table(g),
        second_set_table(g),
        sensing_table(s),
        filter_sentence(g),
        targets(g, s),
        results_table(g, s),
    ):
        print("\n".join(block), end="\n\n")


if __name__ == "__main__":
    main()
