"""Importance sampling against plain Monte Carlo, side by side, printed as JSON.

For each pair (a policy as `marlmerge evaluate` names it, and a scenario preset), the same
request runs twice through `marlmerge.evaluation.estimate`: plain Monte Carlo over
`--mc-episodes` episodes, and importance sampling (cross-entropy rounds, then batches until the
95 % half-width is `--rel-ci` times the rate, at most `--is-max-episodes`). Printed per pair:
both rates and intervals, whether the intervals overlap (the unbiasedness check), the episodes
each used, and the efficiency: the Monte Carlo episodes that importance sampling's interval
would have needed (rate (1 - rate) / se^2), over the episodes it used, fitting rounds included.
Every estimate is written to `--out` as it goes and reused by a rerun (resumable).

    python benchmarks/rare_events.py [--pair POLICY,SCENARIO ...] [--mc-episodes 1000000]
        [--rel-ci 0.2] [--out runs/rare_events]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.estimate import EstimateSettings, Estimator
from marlmerge.evaluation.registry import policy_for_evaluation

PAIRS = (
    "gap@filter,grid_moderate_neutral",
    "gap,grid_moderate_neutral",
    "gap,grid_dense_adversarial",
    "gap,lapses",
    "gap,lapses_heldout",
    "gap,lapses_heldout2",
    "gap,lapses_heldout3",
    "gap,lapses_heldout4",
    "gap,lapses_rare",
)
"""Rule policies (nothing to train): rates near 1e-2, 3e-4 and lower on the grid's roads, where
collisions come from how the drawn drivers line up; near 1e-3 to 1e-5 with drivers who lapse
(`envs/lapses*.toml`; the four `lapses_heldout*` drawn from fixed seeds, each committed before
the change of the estimator it first checked), where they come from lapses the proposal can aim
at."""


def estimate(pair: str, method: str, args: argparse.Namespace) -> dict:
    spec, _, scenario = pair.partition(",")
    if not scenario:
        raise ValueError(f"--pair {pair!r}: give POLICY,SCENARIO")
    policy, cfg = policy_for_evaluation(spec, resolve_config(scenario))
    if method == "mc":
        settings = EstimateSettings(method="mc", episodes=args.mc_episodes, seed=args.seed)
    else:
        settings = EstimateSettings(
            method="is", rel_ci=args.rel_ci, max_episodes=args.is_max_episodes, seed=args.seed
        )
    folder = Path(args.out) / pair.replace("/", "_").replace(",", "__") / method
    return Estimator(policy, spec, cfg, settings, folder).run()


def compare(pair: str, args: argparse.Namespace) -> dict:
    start = time.perf_counter()
    mc = estimate(pair, "mc", args)
    mc_s = time.perf_counter() - start
    imp = estimate(pair, "is", args)
    is_s = time.perf_counter() - start - mc_s
    overlap = mc["ci95"][0] <= imp["ci95"][1] and imp["ci95"][0] <= mc["ci95"][1]
    return {
        "pair": pair,
        "mc": {k: mc[k] for k in ("rate", "ci95", "events", "episodes")} | {"wall_s": mc_s},
        "is": {
            k: imp[k]
            for k in (
                "rate",
                "ci95",
                "events",
                "episodes",
                "fitting_episodes",
                "ess",
                "mean_weight",
                "trusted",
                "precise_enough",
                "mc_equivalent_episodes",
            )
        }
        | {"wall_s": is_s},
        "intervals_overlap": bool(overlap),
        "efficiency": imp["mc_equivalent_episodes"] / imp["episodes"],
        "wall_ratio_per_episode_is_over_mc": (is_s / imp["episodes_run"])
        / (mc_s / mc["episodes_run"])
        if imp["episodes_run"] and mc["episodes_run"]
        else None,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pair", action="append", help="POLICY,SCENARIO (repeatable)")
    p.add_argument("--mc-episodes", type=int, default=1_000_000)
    p.add_argument("--rel-ci", type=float, default=0.2)
    p.add_argument("--is-max-episodes", type=int, default=200_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="runs/rare_events")
    args = p.parse_args()
    for pair in args.pair or PAIRS:
        row = compare(pair, args)
        row["machine"] = platform.node()
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
