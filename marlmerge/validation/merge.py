"""Merge capacity against SUMO (`marlmerge validate --merge`): ramp flow on the same road with the
same drawn vehicles in both simulators, marlmerge's merging drivers against SUMO's LC2013 merging
from its acceleration lane. Two marlmerge variants (`VARIANTS`): gap acceptance with the paper's
forced join, and IDM car following that joins when the gap is safe (`ramp.join = "when_safe"`,
the closest to SUMO's lane changer).

Each cell of `MERGE_GRID` (ramp demand x mainline demand) runs `WORLDS` worlds: world i of
marlmerge seeded `seed` and SUMO fed the arrivals that world draws (`SeedSequence(seed,
spawn_key=(i,))`: the same arrival times, speeds and drivers on the mainline and the ramp).
Both are measured the same way (`marlmerge.evaluation.ramp_flow`) after `SKIP_S` of settling:
merged flow (ramp vehicles past the merge point per hour) and ramp delay (travel time from the
drawn arrival at the ramp start to x = 0, minus the same distance at the speed limit). The SUMO
side is committed (`reference/sumo_merge.json`), so the comparison runs without SUMO.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.evaluation.merge_metrics import SECTIONS
from marlmerge.evaluation.ramp_flow import run_ramp_flow

RAMP_DEMANDS_VPH = (200.0, 600.0, 1000.0, 1200.0)
MAINLINE_DEMANDS_VPH = (600.0, 1200.0, 1800.0)
MERGE_GRID = tuple((r, m) for m in MAINLINE_DEMANDS_VPH for r in RAMP_DEMANDS_VPH)
"""(ramp veh/h, mainline veh/h/lane) of each cell."""
WORLDS = 2
HOURS = 0.5
SKIP_S = 300.0
TOLERANCE = 0.10
"""Merged flow and ramp delay within this relative difference of SUMO's."""
ENTRANCE_FACTOR = 2.0
"""The share of the mainline's lane changes at its entrance within this factor of SUMO's."""
REFERENCE = Path(__file__).parent / "reference" / "sumo_merge.json"
REFERENCES = {"drawn": REFERENCE, "best": REFERENCE.with_name("sumo_merge_best.json")}
"""The committed SUMO side for each `traffic.entrance_lane` (SUMO's `departLane` the lane each
vehicle was drawn for, or "best")."""
VARIANTS = {"gap_forced": ("gap", "forced"), "idm_when_safe": ("idm", "when_safe")}
"""marlmerge's merging variants: name -> (ramp policy, `ramp.join`)."""


def cell_scenario(cfg: ScenarioConfig, ramp_vph: float, main_vph: float) -> ScenarioConfig:
    return cfg.replace(**{"ramp.flow_vph": ramp_vph, "traffic.flow_vph_per_lane": main_vph})


def run_marlmerge_cell(
    cfg: ScenarioConfig, seed: int = 0, variant: str = "gap_forced"
) -> dict[str, float]:
    """One cell in marlmerge: every ramp vehicle driven as `VARIANTS[variant]` says."""
    driver, join = VARIANTS[variant]
    cfg = cfg.replace(**{"ramp.join": join})
    r = run_ramp_flow(cfg, driver, hours=HOURS, worlds=WORLDS, seed=seed, skip_s=SKIP_S)
    return {
        "merged_vph": r.merged_vph,
        "ramp_delay_s": r.ramp_delay_s,
        "ramp_wait_s": r.ramp_wait_s,
        "collisions": float(r.ramp_collisions),
        "mainline_speed_merge_mps": r.mainline_speed_merge_mps,
        "mainline_speed_upstream_mps": r.mainline_speed_upstream_mps,
        "lane_changes_per_hour": r.lane_changes_per_hour,
        "entrance_lane_change_share": r.lane_change_shares["entrance"],
        "braking_over_b_share": r.braking_over_b_share,
        "hardest_braking_mps2": r.hardest_braking_mps2,
    }


def run_sumo_cell(cfg: ScenarioConfig, seed: int = 0) -> dict[str, float]:
    """One cell in SUMO (the `[sumo]` extra), measured as `run_marlmerge_cell` measures.

    marlmerge's worlds start filled and warmed up (`traffic.warmup_s`), SUMO's empty: both skip
    `SKIP_S` of simulated time before counting."""
    from marlmerge.validation.sumo import run_merge

    warm = cfg.traffic.warmup_s
    tot: dict[str, float] = {}
    for i in range(WORLDS):
        out = run_merge(
            cfg, np.random.SeedSequence(seed, spawn_key=(i,)), warm + SKIP_S + HOURS * 3600.0,
            warm + SKIP_S, sumo_seed=i,
        )  # fmt: skip
        for k, v in out.items():
            tot[k] = max(tot.get(k, 0.0), v) if k.startswith("hardest") else tot.get(k, 0.0) + v
    free_s = -cfg.road.x_ramp_start_m / cfg.road.speed_limit_mps
    passed = max(tot["passed"], 1.0)
    changes = sum(tot[f"lane_changes_{k}"] for k in SECTIONS)
    return {
        "merged_vph": tot["passed"] / (WORLDS * HOURS),
        "ramp_delay_s": tot["travel_s"] / passed - free_s,
        "ramp_wait_s": tot["wait_s"] / max(tot["entered"], 1.0),
        "collisions": tot["collisions"],
        "teleports": tot["teleports"],
        "mainline_speed_merge_mps": tot["speed_merge_sum"] / max(tot["speed_merge_n"], 1.0),
        "mainline_speed_upstream_mps": tot["speed_up_sum"] / max(tot["speed_up_n"], 1.0),
        "lane_changes_per_hour": changes / (WORLDS * HOURS),
        "entrance_lane_change_share": tot["lane_changes_entrance"] / changes if changes else None,
        "braking_over_b_share": tot["brake_over_b"] / max(tot["brake_samples"], 1.0),
        "hardest_braking_mps2": tot["hardest_braking_mps2"],
    }


def _key(ramp_vph: float, main_vph: float) -> str:
    return f"{ramp_vph:g}/{main_vph:g}"


def run_grid(cfg: ScenarioConfig, which: str, seed: int = 0) -> dict[str, dict[str, float]]:
    """Every cell of `MERGE_GRID` in `which` (a name of `VARIANTS`, or "sumo"), keyed
    "ramp/mainline"."""
    if which == "sumo":
        return {_key(r, m): run_sumo_cell(cell_scenario(cfg, r, m), seed) for r, m in MERGE_GRID}
    return {
        _key(r, m): run_marlmerge_cell(cell_scenario(cfg, r, m), seed, which) for r, m in MERGE_GRID
    }


def compare(ours: dict[str, dict[str, float]], ref: dict[str, dict[str, float]]) -> dict[str, Any]:
    """Per cell: both simulators' numbers, the ratios of merged flow and ramp delay, and whether
    each is within `TOLERANCE`."""
    cells = {}
    for key, o in ours.items():
        s = ref[key]
        row: dict[str, Any] = {"marlmerge": o, "sumo": s}
        for name in ("merged_vph", "ramp_delay_s"):
            ratio = o[name] / s[name] if s[name] > 0 else float("inf")
            row[f"{name}_ratio"] = ratio
            row[f"{name}_ok"] = bool(abs(ratio - 1.0) <= TOLERANCE)
        ours_e, sumo_e = o.get("entrance_lane_change_share"), s.get("entrance_lane_change_share")
        known = ours_e is not None and sumo_e is not None and sumo_e > 0
        row["entrance_share_ratio"] = ours_e / sumo_e if known else None
        row["entrance_share_ok"] = bool(
            known and 1.0 / ENTRANCE_FACTOR <= ours_e / sumo_e <= ENTRANCE_FACTOR
        )
        cells[key] = row
    met = sum(r["merged_vph_ok"] for r in cells.values())
    met_delay = sum(r["ramp_delay_s_ok"] for r in cells.values())
    met_entrance = sum(r["entrance_share_ok"] for r in cells.values())
    return {
        "cells": cells,
        "merged_within_10pct": f"{met}/{len(cells)}",
        "delay_within_10pct": f"{met_delay}/{len(cells)}",
        "entrance_share_within_2x": f"{met_entrance}/{len(cells)}",
        "all_targets_met": met == met_delay == len(cells),
    }


def validate_merge(
    cfg: ScenarioConfig | None = None,
    out_dir: str | Path = "docs/validation/merge",
    use_sumo: bool = False,
    update_reference: bool = False,
    seed: int = 0,
) -> dict[str, Any]:
    """Run marlmerge's grid (and SUMO's when `use_sumo`, else the committed reference), compare,
    write `results.json` and `README.md` under `out_dir`."""
    cfg = cfg or ScenarioConfig()
    reference = REFERENCES[cfg.traffic.entrance_lane]
    if update_reference and not (use_sumo and _reference_scenario(cfg) and seed == 0):
        raise ValueError(
            "--update-reference needs SUMO, the default scenario (traffic.entrance_lane may be "
            "set) and seed 0"
        )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if use_sumo:
        from marlmerge.validation.sumo import sumo_version

        ref, version = run_grid(cfg, "sumo", seed), sumo_version()
        if update_reference:
            reference.write_text(json.dumps({"sumo_version": version, "cells": ref}, indent=1))
    else:
        saved = json.loads(reference.read_text())
        ref, version = saved["cells"], saved["sumo_version"]
    result: dict[str, Any] = {name: compare(run_grid(cfg, name, seed), ref) for name in VARIANTS}
    result["all_targets_met"] = any(result[name]["all_targets_met"] for name in VARIANTS)
    result["sumo_version"], result["sumo_ran"] = version, use_sumo
    result["entrance_lane"] = cfg.traffic.entrance_lane
    result["cooperation"] = cfg.ramp.cooperation
    (out / "results.json").write_text(json.dumps(result, indent=1))
    (out / "README.md").write_text(markdown(result))
    return result


def _reference_scenario(cfg: ScenarioConfig) -> bool:
    """The default scenario, whatever its name and entrance rule: the ones a committed SUMO
    reference is made of."""
    default = ScenarioConfig()
    same = cfg.replace(**{"name": default.name, "traffic.entrance_lane": "drawn"})
    return same == default


VARIANT_TITLES = {
    "gap_forced": "Gap acceptance, the paper's forced join",
    "idm_when_safe": 'IDM car following, joining when the gap is safe (`ramp.join = "when_safe"`)',
}


def markdown(result: dict[str, Any]) -> str:
    lines = _intro(result)
    for name in VARIANTS:
        lines += ["", f"## {VARIANT_TITLES[name]}", "", *_table(result[name])]
    return "\n".join(lines) + "\n"


def _intro(result: dict[str, Any]) -> list[str]:
    return [
        "# Merge capacity: marlmerge against SUMO",
        "",
        "Written by `marlmerge validate --merge` (`marlmerge.validation.merge`). Ramp flow on the "
        "default road, the same drawn vehicles in both simulators; every ramp vehicle merges by "
        "one of marlmerge's variants below, and by SUMO's LC2013 from its acceleration lane "
        f"(SUMO {result['sumo_version']}). {WORLDS} worlds x {HOURS:g} h per cell after "
        f"{SKIP_S:g} s of settling. Delay: travel time from the drawn arrival at the ramp start "
        "to the merge point, minus that distance at the speed limit. Lane changes and braking: "
        "the mainline (ramp vehicles once past the merge point) sampled every control step "
        "(`marlmerge.evaluation.merge_metrics`); braking around the merge. Targets: merged flow "
        "and ramp delay within 10 % of SUMO's in every cell, the entrance's share of the "
        "lane changes within 2x.",
        "",
        ENTRANCE_TEXT[result.get("entrance_lane", "drawn")],
        "",
        COOPERATION_TEXT[result.get("cooperation", "head")],
    ]


ENTRANCE_TEXT = {
    "drawn": "Entrance: every mainline vehicle enters the lane it was drawn for in both "
    '(`traffic.entrance_lane = "drawn"`, SUMO `departLane` its index).',
    "best": "Entrance: the mainline's arrivals enter in the order of their drawn times, each in "
    'the best lane (`traffic.entrance_lane = "best"`, SUMO `departLane="best"`: the lane whose '
    "last vehicle is farthest from the entrance).",
}


COOPERATION_TEXT = {
    "head": "Mainline cooperation: marlmerge's drivers yield by profile to the ramp's first "
    'vehicle (`ramp.cooperation = "head"`: cooperative drivers yield to it, adversarial ones '
    "close the gap ahead of it); SUMO's by LC2013's cooperative speed adjustment.",
    "zipper": "Mainline cooperation: every neutral or cooperative right-lane driver yields, "
    "braking at most `driver.yield_max_brake_mps2`, to the ramp vehicle in the merge zone "
    'nearest ahead of it in its gap (`ramp.cooperation = "zipper"`, as SUMO\'s LC2013 '
    "cooperative speed adjustment); adversarial drivers close the gap ahead of the ramp's "
    "first vehicle.",
}


def _table(result: dict[str, Any]) -> list[str]:
    lines = [
        f"Merged flow within 10 %: {result['merged_within_10pct']} cells; ramp delay within "
        f"10 %: {result['delay_within_10pct']} cells; share of the mainline's lane changes in "
        f"its first 50 m within 2x: {result.get('entrance_share_within_2x', '-')} cells.",
        "",
        "| ramp veh/h | mainline veh/h/lane | merged veh/h (ours / SUMO) | ratio "
        "| ramp delay s (ours / SUMO) | ratio | mainline speed in the zone m/s (ours / SUMO) "
        "| lane changes /h (ours / SUMO) | at the entrance % (ours / SUMO) "
        "| braking > b % (ours / SUMO) | hardest braking m/s² (ours / SUMO) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for key, row in result["cells"].items():
        r, m = key.split("/")
        o, s = row["marlmerge"], row["sumo"]
        lines.append(
            f"| {r} | {m} | {o['merged_vph']:.0f} / {s['merged_vph']:.0f} | "
            f"{row['merged_vph_ratio']:.2f} | {o['ramp_delay_s']:.1f} / {s['ramp_delay_s']:.1f} | "
            f"{row['ramp_delay_s_ratio']:.2f} | {o['mainline_speed_merge_mps']:.1f} / "
            f"{s['mainline_speed_merge_mps']:.1f} | {_pair(o, s, 'lane_changes_per_hour', 1, 0)} "
            f"| {_pair(o, s, 'entrance_lane_change_share', 100, 0)} "
            f"| {_pair(o, s, 'braking_over_b_share', 100, 2)} "
            f"| {_pair(o, s, 'hardest_braking_mps2', 1, 1)} |"
        )
    return lines


def _pair(ours: dict, sumo: dict, key: str, scale: float, digits: int) -> str:
    """`ours / SUMO` of `key` (scaled), `-` for a value not measured."""

    def one(v: float | None) -> str:
        return "-" if v is None else f"{scale * v:.{digits}f}"

    return f"{one(ours.get(key))} / {one(sumo.get(key))}"
