"""Forced joins against chosen joins (`ego.join`), side by side, printed as JSON and written as a
table.

1. The paper's one ego: each rule (gap acceptance, hold speed, IDM) on the same held-out roads,
   joining by force (`envs/default.toml`) and choosing its join (`envs/chosen_join.toml`: gap
   acceptance joins when the gap alongside passes its gap test; hold and IDM join where the
   forced join would, but brake for the acceleration lane's end until then).
2. Ramp flow: the same rules for every merging vehicle (`marlmerge rampflow`), forced and chosen.

    python benchmarks/chosen_join.py [--episodes 1000] [--hours 1] [--worlds 4]
        [--out docs/ramp_flow]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.ramp_flow import run_ramp_flow
from marlmerge.evaluation.registry import policy_from_spec
from marlmerge.evaluation.rollout import evaluate_policy

RULES = ("gap", "hold", "idm")
JOINS = {"forced": "default", "chosen": "chosen_join"}
RAMP_JOINS = {"forced": "ramp_flow", "chosen": "ramp_flow_chosen"}
RAMP_DEMANDS = (600.0, 1000.0)


def one_ego(episodes: int, seed: int) -> list[dict]:
    rows = []
    for rule in RULES:
        for join, preset in JOINS.items():
            scen = resolve_config(preset)
            s = evaluate_policy(policy_from_spec(rule, scen), scen, episodes, seed)
            rows.append({"policy": rule, "join": join, **s})
            print(json.dumps(rows[-1]), flush=True)
    return rows


def ramp_flow(hours: float, worlds: int, seed: int) -> list[dict]:
    rows = []
    for rule in ("gap", "idm"):
        for join, preset in RAMP_JOINS.items():
            base = resolve_config(preset)
            for demand in RAMP_DEMANDS:
                scen = base.replace(**{"ramp.flow_vph": demand})
                r = run_ramp_flow(scen, rule, hours=hours, worlds=worlds, seed=seed)
                keep = ("merged_vph", "merged_vph_ci95", "ramp_delay_s", "ramp_collisions")
                row = {"policy": rule, "join": join, "ramp_demand_vph": demand}
                rows.append({**row, **{k: getattr(r, k) for k in keep}})
                rows[-1]["collisions_per_1000"] = r.ramp_collisions_per_1000
                rows[-1]["collisions_per_1000_ci95"] = r.ramp_collisions_per_1000_ci95
                print(json.dumps(rows[-1]), flush=True)
    return rows


def table(ego: list[dict], flow: list[dict], args: argparse.Namespace) -> str:
    out = [
        "# Forced joins against chosen joins",
        "",
        f"`python benchmarks/chosen_join.py --episodes {args.episodes} --hours {args.hours:g} "
        f"--worlds {args.worlds}` (one run).",
        "",
        f"## The paper's one ego ({args.episodes} held-out roads, seeds {args.seed}-)",
        "",
        "| policy | join | success | collisions [95 % CI] | merge time s | mean abs accel m/s² |",
        "|---|---|---|---|---|---|",
    ]
    for r in ego:
        lo, hi = r["collision_ci95"]
        out.append(
            f"| {r['policy']} | {r['join']} | {100 * r['success_rate']:.1f} % | "
            f"{100 * r['collision_rate']:.2f} % [{100 * lo:.2f}, {100 * hi:.2f}] | "
            f"{r['mean_merge_time_s']:.2f} | {r['mean_abs_accel_mps2']:.2f} |"
        )
    out += [
        "",
        f"## Ramp flow, mainline 1,200 veh/h/lane ({args.worlds} worlds x {args.hours:g} h, "
        f"seed {args.seed})",
        "",
        "| policy | join | ramp demand veh/h | merged veh/h [95 % CI] | ramp delay s | "
        "collisions per 1,000 merged [95 % CI] |",
        "|---|---|---|---|---|---|",
    ]
    for r in flow:
        lo, hi = r["merged_vph_ci95"]
        c_lo, c_hi = r["collisions_per_1000_ci95"]
        out.append(
            f"| {r['policy']} | {r['join']} | {r['ramp_demand_vph']:.0f} | "
            f"{r['merged_vph']:.0f} [{lo:.0f}, {hi:.0f}] | {r['ramp_delay_s']:.1f} | "
            f"{r['collisions_per_1000']:.2f} [{c_lo:.2f}, {c_hi:.2f}] |"
        )
    return "\n".join(out) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--episodes", type=int, default=1000)
    p.add_argument("--hours", type=float, default=1.0)
    p.add_argument("--worlds", type=int, default=4)
    p.add_argument("--seed", type=int, default=100)
    p.add_argument("--out", default="docs/ramp_flow")
    args = p.parse_args()
    t0 = time.perf_counter()
    ego = one_ego(args.episodes, args.seed)
    flow = ramp_flow(args.hours, args.worlds, args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {"one_ego": ego, "ramp_flow": flow, "wall_s": time.perf_counter() - t0}
    (out / "chosen_join.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / "chosen_join.md").write_text(table(ego, flow, args))
    print(json.dumps({"wall_s": result["wall_s"], "out": str(out)}))


if __name__ == "__main__":
    main()
