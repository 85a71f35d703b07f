"""The robustness grid's ramp-flow conditions: the merge as a whole, per policy and condition.

A grid condition whose scenario has `ramp.flow_vph > 0` is not run as first-ego episodes: every
ramp vehicle is driven by the policy (`marlmerge.evaluation.ramp_flow.run_ramp_flow`) for
`hours` of simulated time per world in `worlds` worlds, seeded by the grid's root seed and the
preset's name (as the episodes' roads are), once per training run of a learned policy. Each
cell's result is written to `cells/KEY.flow.json` as it finishes and reused by a rerun; the
summary's table "Merge under ramp flow" has one row per (policy, run, condition).
"""

from __future__ import annotations

import hashlib
import json
import math
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from marlmerge.config import to_dict
from marlmerge.evaluation.backends import run_tasks
from marlmerge.io.files import saved_digest, write_text
from marlmerge.io.policy_file import DEFAULT_FILE

if TYPE_CHECKING:
    from marlmerge.evaluation.grid import Condition
    from marlmerge.evaluation.registry import PolicySpec

SKIP_S = 120.0
"""Settling time before the measurement (s)."""


@dataclass(frozen=True)
class FlowCell:
    """One policy (one training run of it) driving every ramp vehicle of one condition."""

    policy: PolicySpec
    run: str | None
    condition: Condition
    hours: float
    worlds: int
    seed: int

    @property
    def key(self) -> str:
        """The cell's result file's name: its arguments, the scenario as loaded now and the
        saved policy's contents (as the episode cells' `Cell.key`)."""
        text = repr((self.policy, self.run, self.condition, self.hours, self.worlds, self.seed))
        text += repr(
            (saved_digest(self.run, DEFAULT_FILE["ego"]), to_dict(self.condition.scenario()))
        )
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def check_flow_cell(policy: PolicySpec, condition: Condition) -> None:
    """What ramp flow cannot run, refused before any work starts."""
    if condition.highway or condition.sensing:
        raise ValueError(
            f"condition {condition.label!r}: ramp flow has scripted mainline traffic and the "
            "paper's sensing (no +highway or +sensing)"
        )
    if policy.shield or policy.safety_filter is not None:
        raise ValueError(
            f"policy {policy.name!r} on {condition.label!r}: @shield / @filter / @nofilter "
            "judge the one ego's merge, not ramp flow"
        )


def run_flow_cell(cell: FlowCell) -> dict:
    """A cell's merge measures (runs anywhere: a pure function of the cell)."""
    from marlmerge.evaluation.ramp_flow import run_ramp_flow

    scen = cell.condition.scenario()
    driver = cell.run or cell.policy.kind
    seed = (cell.seed + zlib.crc32(scen.name.encode())) % 2**31
    result = run_ramp_flow(scen, driver, cell.hours, cell.worlds, seed, skip_s=SKIP_S)
    row = result.to_dict()
    row.pop("wall_s")  # the same result on every backend, byte for byte
    head = {"policy": cell.policy.name, "run": cell.run or "-"}
    return head | {"condition": cell.condition.label} | row


def run_flow_cells(
    cells: list[FlowCell], out: Path, backend: str, workers: int | None, address: str | None
) -> list[dict]:
    """Every flow cell's result (reused when present)."""
    files = [out / "cells" / f"{c.key}.flow.json" for c in cells]
    todo = [i for i, f in enumerate(files) if not f.exists()]

    def done(j: int, result: dict) -> None:
        write_text(files[todo[j]], json.dumps(result))

    run_tasks(run_flow_cell, [cells[i] for i in todo], backend, done, workers, address)
    return [json.loads(f.read_text()) for f in files]


def _num(value: float | None, digits: int = 0) -> str:
    """`value` with `digits` decimals, `-` where it is undefined (None or NaN)."""
    if value is None or math.isnan(value):
        return "-"
    return f"{value:.{digits}f}"


def flow_table(results: list[dict], hours: float, worlds: int) -> list[str]:
    """The summary's ramp-flow section."""
    if not results:
        return []
    from marlmerge.evaluation.grid import run_name
    from marlmerge.evaluation.ramp_flow import (
        bounds_text,
        braking_share_text,
        entrance_share_text,
    )

    lines = [
        "## Merge under ramp flow",
        "",
        f"Every ramp vehicle driven by the policy, {worlds} worlds x {hours:g} h each "
        f"(after {SKIP_S:.0f} s of settling). 95 % intervals: merged flow and delay over "
        "worlds; collisions Wilson's, each merged vehicle a trial. Braking: samples of the "
        "mainline around the merge harder than the drivers' comfortable b; entrance: share "
        "of the mainline's lane changes in its first 50 m.",
        "",
        "| policy | run | condition | ramp demand (veh/h) | merged (veh/h) | ramp delay (s) | "
        "longest queue | collisions / 1,000 merged | mainline speed drop (m/s) | "
        "braking > b (%) | entrance lane changes (%) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r['policy']} | {run_name(r['run'])} | {r['condition']} | "
            f"{r['ramp_demand_vph']:g} | "
            f"{r['merged_vph']:.0f}{bounds_text(r['merged_vph_ci95'], 0)} | "
            f"{_num(r['ramp_delay_s'], 1)}{bounds_text(r['ramp_delay_s_ci95'], 1)} | "
            f"{r['ramp_max_queue']} | {_num(r['ramp_collisions_per_1000'], 2)}"
            f"{bounds_text(r.get('ramp_collisions_per_1000_ci95'), 2)} | "
            f"{r['mainline_speed_drop_mps']:.1f} | "
            f"{braking_share_text(r)} | {entrance_share_text(r)} |"
        )
    return [*lines, ""]
