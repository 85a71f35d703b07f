"""What slow mainline drivers do to an ego, printed as JSON: the whole stream slow, or only the
learned-agent roster (the K right-lane vehicles nearest the ego's merge) slow.

The stress test's worst regions for the paper's recipe are slow, dense mainline traffic. This
asks whether highway agents can make that failure themselves: at moderate mixed flow
(`grid_moderate_mixed`, 1,200 veh/h/lane), each case drives the same roads with

- `stream`: every mainline driver's desired speed at FACTOR x the limit (a scenario change);
- `roster_K`: only the K roster agents at FACTOR x the limit (`DesiredSpeedHighwayPolicy` with
  a constant choice: what a speed-choosing adversary does at its most extreme), the rest of the
  traffic as usual.

    python benchmarks/slow_drivers.py [--run runs/paper_s0] [--episodes 300] [--factors 0.55 0.7]
"""

from __future__ import annotations

import argparse
import json

import torch

from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.registry import policy_for_evaluation
from marlmerge.evaluation.rollout import evaluate_policy
from marlmerge.learners.highway import DesiredSpeedHighwayPolicy

SEED = 1_000_000
KEYS = ("success_rate", "collision_rate", "truncation_rate", "mean_merge_time_s")


def constant_speed(factor: float, scen) -> DesiredSpeedHighwayPolicy:
    return DesiredSpeedHighwayPolicy(lambda obs: torch.full((*obs.shape[:-1], 1), factor), scen)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--run", default="runs/paper_s0", help="the ego: a run folder or policy spec")
    p.add_argument("--episodes", type=int, default=300)
    p.add_argument("--factors", type=float, nargs="+", default=[0.55, 0.7])
    p.add_argument("--roster", type=int, nargs="+", default=[4, 16])
    args = p.parse_args()
    base = resolve_config("grid_moderate_mixed")
    rows = []
    for spec in (args.run, "gap"):
        for factor in args.factors:
            slow = base.replace(**{"driver.desired_speed_factor": [factor, factor]})
            cases = [("stream", slow, None)]
            for k in args.roster:
                scen = base.replace(**{"sim.n_highway_agents": k})
                cases.append((f"roster_{k}", scen, constant_speed(factor, scen)))
            for case, scen, highway in cases:
                ego, scen = policy_for_evaluation(spec, scen)  # a run keeps its observation
                r = evaluate_policy(ego, scen, args.episodes, SEED, 100, highway)
                row = {"ego": spec, "factor": factor, "case": case}
                rows.append(row | {k: round(float(r[k]), 4) for k in KEYS})
                print(json.dumps(rows[-1]), flush=True)
    print(json.dumps({"episodes": args.episodes, "rows": rows}))


if __name__ == "__main__":
    main()
