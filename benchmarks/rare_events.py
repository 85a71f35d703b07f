"""Importance sampling and splitting against plain Monte Carlo, side by side, printed as JSON.

For each pair (a policy as `marlmerge evaluate` names it, and a scenario preset), the same
request runs through `marlmerge.evaluation.estimate`: plain Monte Carlo over `--mc-episodes`
episodes, then each of `--methods`: importance sampling (`is`: cross-entropy rounds, then
batches until the 95 % half-width is `--rel-ci` times the rate, at most `--is-max-episodes`)
and splitting at the attention lapses (`split`, scenarios whose drivers lapse; at most
`--is-max-episodes` trunks). Printed per pair: the rates and intervals, whether each interval
overlaps Monte Carlo's (the unbiasedness check), the episodes each used, and the efficiency:
the Monte Carlo episodes that the method's interval would have needed (rate (1 - rate) / se^2),
over the episodes it simulated (fitting rounds and branches included).
Every estimate is written to `--out` as it goes and reused by a rerun (resumable).

    python benchmarks/rare_events.py [--pair POLICY,SCENARIO ...] [--mc-episodes 1000000]
        [--rel-ci 0.2] [--methods is,split] [--out runs/rare_events]
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
    "gap,lapses_heldout5",
    "gap,lapses_heldout6",
    "gap,lapses_rare",
)
"""Rule policies (nothing to train): rates near 1e-2, 3e-4 and lower on the grid's roads, where
collisions come from how the drawn drivers line up; near 1e-3 to 1e-5 with drivers who lapse
(`envs/lapses*.toml`; the six `lapses_heldout*` drawn from fixed seeds, each committed before
the change of the estimator it first checked), where they come from lapses the proposal can aim
at and splitting can branch on."""


def estimate(pair: str, method: str, args: argparse.Namespace) -> dict:
    spec, _, scenario = pair.partition(",")
    if not scenario:
        raise ValueError(f"--pair {pair!r}: give POLICY,SCENARIO")
    policy, cfg = policy_for_evaluation(spec, resolve_config(scenario))
    if method == "mc":
        settings = EstimateSettings(method="mc", episodes=args.mc_episodes, seed=args.seed)
    else:
        settings = EstimateSettings(
            method=method, rel_ci=args.rel_ci, max_episodes=args.is_max_episodes, seed=args.seed
        )
    folder = Path(args.out) / pair.replace("/", "_").replace(",", "__") / method
    return Estimator(policy, spec, cfg, settings, folder).run()


REPORTED = (
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
    "trunk_episodes",
    "branch_episodes",
    "replay_mismatches",
)


def compare(pair: str, args: argparse.Namespace) -> dict:
    start = time.perf_counter()
    mc = estimate(pair, "mc", args)
    mc_s = time.perf_counter() - start
    row: dict = {
        "pair": pair,
        "mc": {k: mc[k] for k in ("rate", "ci95", "events", "episodes")} | {"wall_s": mc_s},
    }
    lapses = resolve_config(pair.partition(",")[2]).driver.lapse_rate_per_h > 0
    for method in args.methods.split(","):
        if method == "split" and not lapses:
            row[method] = None  # nothing to split without lapses
            continue
        t0 = time.perf_counter()
        est = estimate(pair, method, args)
        wall_s = time.perf_counter() - t0
        overlap = mc["ci95"][0] <= est["ci95"][1] and est["ci95"][0] <= mc["ci95"][1]
        row[method] = {k: est[k] for k in REPORTED if k in est} | {
            "wall_s": wall_s,
            "intervals_overlap": bool(overlap),
            "efficiency": est["mc_equivalent_episodes"] / est["episodes"],
            "wall_ratio_per_episode_over_mc": (wall_s / est["episodes_run"])
            / (mc_s / mc["episodes_run"])
            if est["episodes_run"] and mc["episodes_run"]
            else None,
        }
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pair", action="append", help="POLICY,SCENARIO (repeatable)")
    p.add_argument("--mc-episodes", type=int, default=1_000_000)
    p.add_argument("--rel-ci", type=float, default=0.2)
    p.add_argument("--is-max-episodes", type=int, default=200_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--methods", default="is,split", help="beside Monte Carlo, comma-separated")
    p.add_argument("--out", default="runs/rare_events")
    args = p.parse_args()
    for pair in args.pair or PAIRS:
        row = compare(pair, args)
        row["machine"] = platform.node()
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
