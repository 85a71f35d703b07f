"""The gap-acceptance shield's options side by side, on the grid's roads.

`GapShield` (the grid's `@shield`) judges the ramp vehicle's join from its observation. Its three
options (`@shield-left` turns them all on): `watch_left`, which also judges the left-lane drivers
predicted to move right into the ego's gap (an extended observation only), `cap_in_lane`, which
caps the ego's command at IDM's behind its leader once it has joined, and `keep_rolling`, which
keeps a nearly stopped ego rolling towards gap acceptance's wait point. This script runs a
policy behind each variant (and, as `bare`, without a shield) on the same roads as the grid
(`marlmerge.evaluation.grid.road_seeds`, root seed 2,000,000) and prints one JSON line per
variant: episodes, collisions, success, truncations and the mean merge time of the successful
episodes.

    python benchmarks/shield_variants.py --policy "quadq:runs/hardened_s?" \\
        --condition "heldout_*" --condition "heldout4_*" [--sees-ramp] [--episodes 400]
    python benchmarks/shield_variants.py --policy idm --observation extended_accel \\
        --condition "heldout3_*" --episodes 200

`--sees-ramp` runs the conditions with `driver.lane_change_sees_ramp = true` (drivers who do
not move right in beside a merging vehicle; the roads stay the same). `--observation` sets the
ego's layout for a rule (a learned policy keeps its own).
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from marlmerge.config import ScenarioConfig
from marlmerge.evaluation.grid import expand_conditions, parse_condition, road_seeds
from marlmerge.evaluation.registry import PolicySpec, make_policy, parse_policy, scenario_for
from marlmerge.evaluation.rollout import EgoPolicy, rollout_first_egos
from marlmerge.policies.gap_acceptance import GapShield
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_SUCCESS, OUTCOME_TRUNCATED

GRID_SEED = 2_000_000
VARIANTS: dict[str, tuple[bool, bool, bool] | None] = {  # (watch_left, cap_in_lane, keep_rolling)
    "bare": None,  # no shield: the policy alone
    "shield": (False, False, False),
    "shield+cap": (False, True, False),
    "shield+left": (True, False, False),
    "shield+roll": (False, False, True),
    "shield-left": (True, True, True),
}


def shielded(
    spec: PolicySpec,
    run: str | None,
    scen: ScenarioConfig,
    watch_left: bool,
    cap: bool,
    roll: bool,
    margin: float,
) -> EgoPolicy:
    """The policy behind a `GapShield` with these options."""
    bare = make_policy(spec, run, scen)
    shield = GapShield(
        scen, watch_left=watch_left, cap_in_lane=cap, keep_rolling=roll, left_margin_mps2=margin
    )
    return lambda obs: torch.as_tensor(shield(obs.numpy(), bare(obs).numpy()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--policy", required=True, help="a rule or KIND:RUN_GLOB, without modifier")
    ap.add_argument("--condition", action="append", required=True)
    ap.add_argument("--episodes", type=int, default=400)
    ap.add_argument("--sees-ramp", action="store_true")
    ap.add_argument("--observation", default=None, help="the ego's layout, for a rule")
    ap.add_argument("--variants", default=",".join(v for v in VARIANTS if v != "bare"),
                    help="comma-separated; `bare` is the policy without a shield")  # fmt: skip
    ap.add_argument("--left-margin", type=float, default=1.0, help="GapShield.left_margin_mps2")
    args = ap.parse_args()
    spec = parse_policy(args.policy)
    if spec.shield or spec.safety_filter is not None:
        raise SystemExit(f"--policy {args.policy!r}: give it without a modifier")
    names = [v for v in args.variants.split(",") if v]
    unknown = [v for v in names if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"--variants: unknown {unknown[0]!r} (one of {', '.join(VARIANTS)})")
    keys = ("episodes", "collisions", "success", "truncated", "merge_time_sum_s")
    totals = {v: dict.fromkeys(keys, 0.0) for v in names}
    for preset in expand_conditions(args.condition):
        base = parse_condition(preset).scenario()
        if args.sees_ramp:
            base = base.replace(**{"driver.lane_change_sees_ramp": True})
        if args.observation and not spec.runs:
            base = base.replace(**{"ego.observation": args.observation})
        for run in spec.runs or (None,):
            scen = scenario_for(spec, run, base)
            seeds = road_seeds(GRID_SEED, scen.name, args.episodes)
            for name in names:
                opts = VARIANTS[name]
                policy = (
                    make_policy(spec, run, scen)
                    if opts is None
                    else shielded(spec, run, scen, *opts, args.left_margin)
                )
                rec, _ = rollout_first_egos(
                    policy, scen, args.episodes, 0, args.episodes, road_seeds=seeds
                )
                out, t = rec["outcome"], totals[name]
                ok = out == OUTCOME_SUCCESS
                t["episodes"] += args.episodes
                t["collisions"] += int(np.count_nonzero(out == OUTCOME_COLLISION))
                t["success"] += int(np.count_nonzero(ok))
                t["truncated"] += int(np.count_nonzero(out == OUTCOME_TRUNCATED))
                t["merge_time_sum_s"] += float(rec["time_s"][ok].sum())
    for name, t in totals.items():
        row = {"variant": name, "policy": args.policy, "sees_ramp": args.sees_ramp}
        row["left_margin_mps2"] = args.left_margin
        row |= {k: int(t[k]) for k in keys[:-1]}
        row["merge_time_s"] = round(t["merge_time_sum_s"] / max(t["success"], 1), 2)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
