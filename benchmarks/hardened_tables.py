"""The hardened recipe against its targets (docs/stress.md), from grids' episodes.csv.

    python benchmarks/hardened_tables.py runs/hardened_grid/episodes.csv \
        [runs/hardened_seeded_grid/episodes.csv ...]

Prints, in Markdown, one table per condition set (the grid's 12 cells and each held-out set
the grids ran: `heldout`, `heldout2`, ...) and one over all of them: per policy, success,
collisions with their Wilson 95 % interval, the lowest and highest of the seeds' collision
rates (the interval counts roads; two draws of a recipe's seeds differ by more,
docs/stress.md), the worst condition pooled over seeds, the worst seed in any condition, time
to merge and max jerk. Then the targets of issue "hardening": the hardened ego unshielded
(<= 0.1 % collisions, >= 99.5 % success, no condition below 99 %, no seed below 98 % in any
condition, merge time <= gap acceptance's, max jerk <= the paper recipe's; not judged where
the grids have no `gap` or `paper` policy) on every set, and behind the shield
(`POLICY@shield` or `POLICY@shield-left`) 0 collisions in the held-out episodes. Last, the
roads by how many of the policy's seeds collide there, against the count expected if the
seeds collided independently (each at its own rate in each condition), and what gap
acceptance did on them.
"""

from __future__ import annotations

import argparse
import re
from collections import Counter

import numpy as np
from robustness_tables import load, merge_time, pct, subset, worst

from marlmerge.evaluation.metrics import wilson_interval


def set_of(condition: str) -> str:
    m = re.match(r"(heldout\d*)[ _]", condition)
    return m.group(1) if m else "grid"


def number(name: str) -> int:
    """A set's place: the grid 0, `heldout` 1, `heldoutK` K."""
    return 0 if name == "grid" else int(name.removeprefix("heldout") or 1)


def sets_in(g: dict[str, dict[str, np.ndarray]]) -> list[str]:
    """The condition sets the grids ran, the grid first, then the held-out sets in order."""
    return sorted({set_of(c) for d in g.values() for c in d["condition"]}, key=number)


def title(name: str) -> str:
    return "the grid (12 cells)" if name == "grid" else f"held-out {number(name)}"


def restrict(d: dict[str, np.ndarray], name: str | None) -> dict[str, np.ndarray]:
    """`d` restricted to one condition set (None: all of it)."""
    if name is None:
        return d
    return subset(d, np.array([set_of(c) == name for c in d["condition"]]))


def table(g: dict[str, dict[str, np.ndarray]], name: str | None) -> list[str]:
    out = [
        "| policy | episodes | success | collisions [95 %] | seeds' collisions | worst condition | "
        "worst seed in a condition | time to merge | max jerk |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for policy, full in g.items():
        d = restrict(full, name)
        n = len(d["success"])
        if n == 0:
            continue
        k = float(d["collision"].sum())
        lo, hi = wilson_interval(k, n)
        w = worst(d)
        seed = "(one policy)" if len(np.unique(d["run"])) == 1 else (
            f"{w.run.rsplit('_', 1)[-1]}: {100 * w.run_success:.1f} %")  # fmt: skip
        out.append(
            f"| {policy} | {n:,} | {pct(d['success'])} | {100 * k / n:.2f} % "
            f"[{100 * lo:.2f}, {100 * hi:.2f}] ({int(k)}) | {seed_spread(d)} | "
            f"{w.cond} {100 * w.success:.1f} % | {seed} | {merge_time(d):.1f} s | "
            f"{np.nanmean(d['max_abs_jerk_mps3']):.1f} m/s³ |"
        )
    return out


def seed_spread(d: dict[str, np.ndarray]) -> str:
    """The lowest and highest collision rate of a policy's training runs (one run: "-")."""
    runs = np.unique(d["run"])
    if len(runs) == 1:
        return "-"
    rates = [100 * d["collision"][d["run"] == r].mean() for r in runs]
    return f"{min(rates):.2f}-{max(rates):.2f} %"


def targets(g: dict[str, dict[str, np.ndarray]], policy: str) -> list[str]:
    """Each target of the hardened ego (unshielded) on each set, and behind the shield."""
    out = ["| set | collisions ≤ 0.1 % | success ≥ 99.5 % | no condition < 99 % | "
           "no seed < 98 % in a condition | merge time ≤ gap's | max jerk ≤ paper's |",
           "|---|---|---|---|---|---|---|"]  # fmt: skip
    sets = sets_in(g)
    for name in sets:
        d = restrict(g[policy], name)
        if not len(d["success"]):
            continue
        gap = restrict(g["gap"], name) if "gap" in g else None
        w, jerk = worst(d), np.nanmean(d["max_abs_jerk_mps3"])
        paper = restrict(g["paper"], name)["max_abs_jerk_mps3"] if "paper" in g else []
        paper_jerk = np.nanmean(paper) if len(paper) else None
        checks = [
            (d["collision"].mean() <= 0.001, pct(d["collision"])),
            (d["success"].mean() >= 0.995, pct(d["success"])),
            (w.success >= 0.99, f"{100 * w.success:.1f} %"),
            (w.run_success >= 0.98, f"{100 * w.run_success:.1f} %"),
            (
                None if gap is None else merge_time(d) <= merge_time(gap),
                f"{merge_time(d):.1f} vs {'-' if gap is None else f'{merge_time(gap):.1f}'} s",
            ),
            (
                None if paper_jerk is None else jerk <= paper_jerk,
                f"{jerk:.1f} vs {'-' if paper_jerk is None else f'{paper_jerk:.1f}'}",
            ),
        ]
        verdict = {True: "met", False: "missed", None: "not judged"}
        cells = " | ".join(f"{verdict[ok]} ({v})" for ok, v in checks)
        out.append(f"| {title(name)} | {cells} |")
    for shield in (f"{policy}@shield", f"{policy}@shield-left"):
        if shield not in g:
            continue
        held = [restrict(g[shield], s) for s in sets if s != "grid"]
        k = int(sum(h["collision"].sum() for h in held))
        n = sum(len(h["collision"]) for h in held)
        out += ["", f"Behind `@{shield.split('@')[1]}`, the held-out sets: {k} collisions in "
                f"{n:,} episodes (target: 0 in ≥ 10,000)."]  # fmt: skip
    return out


def roads(d: dict[str, np.ndarray]) -> np.ndarray:
    """Each episode's road, "condition#episode": the grids drive every policy on the same ones."""
    return np.char.add(np.char.add(d["condition"].astype(str), "#"), d["episode"].astype(str))


def exactly(rates: list[float]) -> np.ndarray:
    """P(exactly c of independent events with these probabilities), c = 0..len(rates)."""
    p = np.array([1.0])
    for r in rates:
        p = np.concatenate([p * (1 - r), [0.0]]) + np.concatenate([[0.0], p * r])
    return p


def shared(g: dict[str, dict[str, np.ndarray]], policy: str) -> list[str]:
    """Roads by how many of `policy`'s seeds collide there, against the count expected if the
    seeds collided independently, each at its own rate in each condition (so hard conditions
    alone do not count as shared), and what gap acceptance did on those roads."""
    d = g[policy]
    runs, run = np.unique(d["run"], return_inverse=True)
    keys, road = np.unique(roads(d), return_inverse=True)
    pairs = np.unique(road * len(runs) + run)  # each (road, seed) driven
    if len(runs) < 2 or not len(pairs) == len(d["run"]) == len(runs) * len(keys):
        return []  # one seed, or seeds that did not all drive every road once
    seeds = np.bincount(road, weights=d["collision"], minlength=len(keys)).astype(int)
    expected = np.zeros(len(runs) + 1)  # each condition's roads at each seed's rate there
    for cond in np.unique(d["condition"]):
        here = d["condition"] == cond
        rates = [d["collision"][here & (d["run"] == r)].mean() for r in runs]
        expected += here.sum() / len(runs) * exactly(rates)
    gap = None
    if "gap" in g:
        outcome = 2 * g["gap"]["collision"] + g["gap"]["truncation"]  # 0 merged, 1 out of time
        gap = dict(zip(roads(g["gap"]), outcome, strict=True))
    out = ["| seeds colliding | roads | expected if independent | gap acceptance there: "
           "merged / out of time / collided |", "|---|---|---|---|"]  # fmt: skip
    for c in range(1, len(runs) + 1):
        there = keys[seeds == c]
        there_gap = "-" if gap is None else " / ".join(
            str(sum(gap.get(k, -1) == o for k in there)) for o in (0, 1, 2))  # fmt: skip
        out.append(f"| {c} of {len(runs)} | {len(there):,} | {expected[c]:.3g} | {there_gap} |")
    most = keys[2 * seeds > len(runs)]  # roads where most of the seeds collide
    where = Counter(k.rsplit("#", 1)[0] for k in most).most_common()
    listed = ", ".join(f"{cond} ({n})" for cond, n in where)
    return [*out, "", f"Where most of the seeds collide, by condition: {listed or 'nowhere'}."]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument(
        "episodes",
        nargs="+",
        help="grids' episodes.csv (their policies merged, a policy's episodes pooled)",
    )
    p.add_argument(
        "--policy",
        default=None,
        help="the policy the targets are for (default: hardened, where the grids have it)",
    )
    args = p.parse_args()
    g: dict[str, dict[str, np.ndarray]] = {}
    for path in args.episodes:  # a policy in several grids: their episodes together
        for policy, d in load(path).items():
            old = g.get(policy)
            g[policy] = d if old is None else {k: np.concatenate([old[k], d[k]]) for k in d}
    if args.policy is not None and args.policy not in g:
        p.error(f"--policy {args.policy!r}: not in the grids (their policies: {', '.join(g)})")
    args.policy = args.policy or "hardened"
    for name in (None, *sets_in(g)):
        rows = table(g, name)
        if len(rows) > 2:
            print(f"\n### {'all sets' if name is None else title(name)}\n")
            print("\n".join(rows))
    for policy in (args.policy, *(q for q in g if q != args.policy and q.startswith(args.policy)
                                  and "@" not in q)):  # fmt: skip
        if policy not in g:  # the default's targets, and a grid without it
            continue
        print(f"\n### Targets: `{policy}`\n")
        print("\n".join(targets(g, policy)))
        rows = shared(g, policy)
        if rows:
            print(f"\n### Roads by how many of `{policy}`'s seeds collide there\n")
            print("\n".join(rows))


if __name__ == "__main__":
    main()
