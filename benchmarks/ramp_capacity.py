"""The merge's capacity curve under ramp flow, printed as JSON and written as a table and a figure.

For each mainline demand and each merging variant (a ramp policy and a `ramp.join` mode), the ramp
demand rises and `marlmerge.evaluation.ramp_flow.run_ramp_flow` measures merged flow, ramp delay,
collisions, the mainline's speed through the merge zone, where it changes lanes and how hard it
brakes. Merged flow follows the demand until
the merge saturates; the curve's plateau is the merge's capacity at that mainline demand.

    python benchmarks/ramp_capacity.py [--hours 1] [--worlds 4] [--out docs/ramp_flow]
    python benchmarks/ramp_capacity.py --variant quadq=runs/paper/seed_0:forced   # a learned ego
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from marlmerge.config import ScenarioConfig
from marlmerge.evaluation.ramp_flow import (
    bounds_text,
    braking_share_text,
    entrance_share_text,
    run_ramp_flow,
)

RAMP_DEMANDS = (200.0, 400.0, 600.0, 800.0, 1000.0, 1200.0, 1400.0, 1600.0)
MAINLINE_DEMANDS = (600.0, 1200.0, 1800.0)
VARIANTS = {"gap, forced join": ("gap", "forced"), "idm, join when safe": ("idm", "when_safe")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--hours", type=float, default=1.0)
    p.add_argument("--worlds", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="docs/ramp_flow")
    p.add_argument(
        "--variant",
        action="append",
        default=None,
        help="NAME=POLICY:JOIN (repeatable; default: gap with forced join, idm joining when safe)",
    )
    args = p.parse_args()
    variants = dict(VARIANTS)
    if args.variant:
        variants = {}
        for v in args.variant:
            name, rest = v.split("=", 1)
            policy, join = rest.rsplit(":", 1)
            variants[name] = (policy, join)
    rows = []
    for name, (policy, join) in variants.items():
        for main_vph in MAINLINE_DEMANDS:
            for ramp_vph in RAMP_DEMANDS:
                cfg = ScenarioConfig().replace(
                    **{
                        "ramp.flow_vph": ramp_vph,
                        "ramp.join": join,
                        "traffic.flow_vph_per_lane": main_vph,
                    }
                )
                r = run_ramp_flow(cfg, policy, args.hours, args.worlds, args.seed)
                rows.append({"variant": name, "join": join, **r.to_dict()})
                print(json.dumps(rows[-1]), flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "capacity.json").write_text(json.dumps(rows, indent=1))
    (out / "capacity.md").write_text(_table(rows, args))
    _figure(rows, out / "capacity.png")


def _table(rows: list[dict], args: argparse.Namespace) -> str:
    lines = [
        "# Merge capacity under ramp flow",
        "",
        f"Written by `python benchmarks/ramp_capacity.py --hours {args.hours:g} --worlds "
        f"{args.worlds}` ({args.worlds} worlds x {args.hours:g} h per row after 300 s of "
        "settling; merged flow, ramp delay and the lane-change and braking shares with their 95 % "
        "intervals over worlds, collisions per 1,000 merged with Wilson's, each merged vehicle "
        "a trial). Lane changes and braking: "
        "the mainline, one sample per vehicle and control step "
        "(`marlmerge.evaluation.merge_metrics`); braking around the merge; a cut-in's follower "
        "is watched for 3 s.",
        "",
        "| variant | mainline veh/h/lane | ramp demand veh/h | merged veh/h | ramp delay s "
        "| longest ramp queue | ramp collisions | per 1,000 merged [95 % CI] "
        "| mainline speed upstream -> zone m/s | mainline lane changes at the entrance % "
        "| braking > b % | hardest braking m/s² | cut-ins followed by braking > b |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lo, hi = r["merged_vph_ci95"]
        c_lo, c_hi = r["ramp_collisions_per_1000_ci95"]
        lines.append(
            f"| {r['variant']} | {r['mainline_demand_vph_per_lane']:g} | "
            f"{r['ramp_demand_vph']:g} | {r['merged_vph']:.0f} [{lo:.0f}, {hi:.0f}] | "
            f"{r['ramp_delay_s']:.1f}{bounds_text(r['ramp_delay_s_ci95'], 1)} | "
            f"{r['ramp_max_queue']} | {r['ramp_collisions']} | "
            f"{r['ramp_collisions_per_1000']:.2f} [{c_lo:.2f}, {c_hi:.2f}] | "
            f"{r['mainline_speed_upstream_mps']:.1f} -> "
            f"{r['mainline_speed_merge_mps']:.1f} | {entrance_share_text(r)} | "
            f"{braking_share_text(r)} | "
            f"{r['hardest_braking_mps2']:.1f} | "
            f"{r['cut_ins_braking_over_b']} of {r['cut_ins']} |"
        )
    return "\n".join(lines) + "\n"


def _figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = list(dict.fromkeys(r["variant"] for r in rows))
    fig, axes = plt.subplots(1, len(variants), figsize=(5 * len(variants), 4), squeeze=False)
    for ax, name in zip(axes[0], variants, strict=True):
        for main_vph in MAINLINE_DEMANDS:
            sel = [
                r
                for r in rows
                if r["variant"] == name and r["mainline_demand_vph_per_lane"] == main_vph
            ]
            ax.plot(
                [r["ramp_demand_vph"] for r in sel],
                [r["merged_vph"] for r in sel],
                marker="o",
                label=f"mainline {main_vph:g} veh/h/lane",
            )
        ax.plot([0, max(RAMP_DEMANDS)], [0, max(RAMP_DEMANDS)], "k:", lw=0.8, label="demand")
        ax.set_title(name)
        ax.set_xlabel("ramp demand (veh/h)")
        ax.set_ylabel("merged flow (veh/h)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
