"""The shield with and without an IDM cap on the ego's command once it is in its lane.

The gap-acceptance shield (`@shield`) judges the ramp vehicle's join and leaves it alone after
it (the command stands from the overlap point on). This script measures what a shield that also
caps the ego's acceleration at IDM's behind its leader, once it is in its lane, would change:
the same roads as the grid (`marlmerge.evaluation.grid.road_seeds`, root seed 2,000,000), each
learned run behind the shield, with and without the cap. `--sees-ramp` runs the conditions with
`driver.lane_change_sees_ramp = true` (drivers who do not move right in beside a merging
vehicle; the roads stay the same). Prints one JSON line per variant: episodes, collisions,
success.

    python benchmarks/shield_in_lane.py --runs "runs/hardened_s?" \
        --condition "heldout_*" --condition "heldout4_*" [--sees-ramp] [--episodes 400]
"""

from __future__ import annotations

import argparse
import glob
import json

import numpy as np
import torch

from marlmerge.config import ScenarioConfig
from marlmerge.evaluation.grid import expand_conditions, parse_condition, road_seeds
from marlmerge.evaluation.registry import make_policy, parse_policy, scenario_for
from marlmerge.evaluation.rollout import EgoPolicy, rollout_first_egos
from marlmerge.policies.scripted import IdmEgoPolicy, joined
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_SUCCESS

GRID_SEED = 2_000_000


def capped(shielded: EgoPolicy, scen: ScenarioConfig) -> EgoPolicy:
    """`shielded`, its acceleration at most IDM's once the ego is in its lane."""
    idm = IdmEgoPolicy(scen)

    def policy(obs: torch.Tensor) -> torch.Tensor:
        a = shielded(obs).numpy().copy()  # [B, A]
        o = obs.numpy()
        in_lane = joined(o, scen)  # past the overlap point: the shield forces the join
        a[..., 0] = np.where(in_lane, np.minimum(a[..., 0], idm(o)[..., 0]), a[..., 0])
        return torch.as_tensor(a)

    return policy


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", required=True, help="glob of learned run folders (policy.pt)")
    ap.add_argument("--condition", action="append", required=True)
    ap.add_argument("--episodes", type=int, default=400)
    ap.add_argument("--sees-ramp", action="store_true")
    args = ap.parse_args()
    runs = sorted(glob.glob(args.runs))
    if not runs:
        raise SystemExit(f"--runs {args.runs!r} matches no run folder")
    spec = parse_policy(f"quadq@shield:{runs[0]}")
    totals = {v: {"episodes": 0, "collisions": 0, "success": 0} for v in ("shield", "shield+cap")}
    for preset in expand_conditions(args.condition):
        base = parse_condition(preset).scenario()
        if args.sees_ramp:
            base = base.replace(**{"driver.lane_change_sees_ramp": True})
        for run in runs:
            scen = scenario_for(spec, run, base)
            shielded = make_policy(spec, run, scen)
            seeds = road_seeds(GRID_SEED, scen.name, args.episodes)
            for name, policy in (("shield", shielded), ("shield+cap", capped(shielded, scen))):
                rec, _ = rollout_first_egos(
                    policy, scen, args.episodes, 0, args.episodes, road_seeds=seeds
                )
                t = totals[name]
                t["episodes"] += args.episodes
                t["collisions"] += int(np.count_nonzero(rec["outcome"] == OUTCOME_COLLISION))
                t["success"] += int(np.count_nonzero(rec["outcome"] == OUTCOME_SUCCESS))
    for name, t in totals.items():
        print(json.dumps({"variant": name, "sees_ramp": args.sees_ramp, "runs": args.runs} | t))


if __name__ == "__main__":
    main()
