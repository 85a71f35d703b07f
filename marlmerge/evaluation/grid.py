"""The robustness grid: every policy on every traffic condition, on the same held-out episodes.

    marlmerge grid --policy hold --policy idm --policy gap --policy "quadq:runs/paper_s*" \
        --episodes 30 --out runs/grid

Conditions are scenario presets (default: every `envs/grid_*.toml`: three flows x four driver
mixes). In each condition every policy meets the same episodes: episode e is the first ramp
vehicle of a fresh world seeded `SeedSequence(seed, spawn_key=(crc32(preset name), e))`, so the
roads of a condition depend only on the root seed and the preset (not on the other conditions,
the policies, the batching or the backend). A learned policy is evaluated once per training run
(one run folder per training seed) and its episodes are pooled.

The work is split into cells, one per (condition, policy, training run, learned highway policy), run
on a backend (`marlmerge.evaluation.backends`: serial, processes, Ray). Each cell's rows are written
atomically to `cells/` as soon as it finishes; a grid that is run again with the same arguments
skips the cells it already has, so an interrupted grid resumes. The outputs are the same, byte for
byte, whatever the backend and however often it was interrupted.

Outputs in `out`: `episodes.csv` (one row per episode, every metric of
`marlmerge.evaluation.metrics`), `summary.md` (success / collision with 95 % intervals, comfort and
safety tables) and heat maps `heatmap_success.png`, `heatmap_collision.png`. A condition with
ramp flow (`ramp.flow_vph > 0`, e.g. `envs/ramp_flow.toml`) is measured as the merge as a whole
instead, in its own table (`marlmerge.evaluation.grid_flow`).
"""

from __future__ import annotations

import csv
import functools
import glob
import hashlib
import io
import json
import math
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from marlmerge.config import ScenarioConfig, to_dict
from marlmerge.config.presets import find_preset, resolve_config
from marlmerge.evaluation.backends import check_backend, run_tasks
from marlmerge.evaluation.grid_flow import FlowCell, check_flow_cell, flow_table, run_flow_cells
from marlmerge.evaluation.metrics import Z_95, aggregate, episode_metrics
from marlmerge.evaluation.registry import (  # noqa: F401 - the grid's policies, re-exported
    LEARNED_KINDS,
    RULE_POLICIES,
    PolicySpec,
    check_shield_left,
    make_policy,
    parse_policy,
    scenario_for,
)
from marlmerge.evaluation.rollout import rollout_first_egos
from marlmerge.io.files import saved_digest, write_text
from marlmerge.io.policy_file import DEFAULT_FILE


def condition_label(cfg: ScenarioConfig) -> str:
    return cfg.name.removeprefix("grid_").replace("_", " ")


@dataclass(frozen=True)
class Condition:
    """A traffic condition: a scenario preset, optionally with learned highway agents.

    With `highway` (one saved highway policy per adversary training seed), the K highway agents of
    every episode are driven by each of them in turn and the episodes are pooled; the roads are
    the same as the preset's scripted column.
    """

    preset: str
    label: str
    highway: tuple[str, ...] = ()
    sensing: str | None = None
    """A preset whose `[sensing]` (noise, latency, occlusion) the ego's sensor has here."""

    def scenario(self) -> ScenarioConfig:
        """The preset, with the sensors of `sensing` (same roads: the name is the preset's)."""
        scen = resolve_config(self.preset)
        if self.sensing is None:
            return scen
        sensors = to_dict(resolve_config(self.sensing).sensing)
        return scen.replace(**{f"sensing.{k}": v for k, v in sensors.items()})


def parse_condition(spec: str) -> Condition:
    """`PRESET`, `[label=]PRESET+highway:GLOB` (GLOB matches run folders holding a
    `highway_policy.pt`, or such files; `edge` or `pace`: a scripted driver,
    `marlmerge.learners.highway.SCRIPTED_DRIVERS`) or `[label=]PRESET+sensing:SENSING_PRESET` (the
    ego's sensor of that preset's `[sensing]` on the preset's roads)."""
    from marlmerge.learners.highway import SCRIPTED_LABELS

    label, _, body = spec.rpartition("=")
    preset, plus, learned = body.partition("+")
    scen = resolve_config(preset)
    if not plus:
        return Condition(preset, label or condition_label(scen))
    kind, _, pattern = learned.partition(":")
    if kind == "sensing" and pattern:
        resolve_config(pattern)  # a clear error now for an unknown preset
        return Condition(preset, label or f"{condition_label(scen)} + sensing", sensing=pattern)
    if kind != "highway" or not pattern:
        raise ValueError(
            f"unknown condition {spec!r} (use PRESET, [label=]PRESET+highway:GLOB or "
            "[label=]PRESET+sensing:PRESET)"
        )
    if pattern in SCRIPTED_LABELS:
        named = f"{condition_label(scen)} + {SCRIPTED_LABELS[pattern]}"
        return Condition(preset, label or named, (pattern,))
    found = tuple(
        m for m in sorted(glob.glob(pattern)) if Path(m).is_dir() or m.endswith(".pt")
    ) or (pattern,)
    missing = [
        r for r in found if not (r.endswith(".pt") or (Path(r) / "highway_policy.pt").exists())
    ]
    if missing:
        raise ValueError(f"condition {spec!r}: no highway_policy.pt in {missing[0]!r}")
    return Condition(preset, label or f"{condition_label(scen)} + learned", found)


def default_conditions() -> list[str]:
    envs = find_preset("default").parent
    return [str(p) for p in sorted(envs.glob("grid_*.toml"), key=_condition_order)]


def expand_conditions(specs: Sequence[str]) -> list[str]:
    """Condition specs with preset-name globs expanded in the grid's order: `grid_*` is every
    `envs/grid_*.toml`, `grid_dense_*` the dense ones, `grid_*+sensing:sensing_realistic` each of
    them with that sensor; other specs pass through."""
    envs = find_preset("default").parent
    out: list[str] = []
    for spec in specs:
        head, plus, tail = spec.partition("+")
        if "*" in head and "/" not in head and "=" not in head:
            found = sorted(envs.glob(f"{head.removesuffix('.toml')}.toml"), key=_condition_order)
            if not found:
                raise ValueError(f"condition {spec!r} matches no preset in {envs}")
            out += [str(p) + plus + tail for p in found]
        else:
            out.append(spec)
    return out


def _condition_order(p: Path) -> tuple[int, int, str]:
    flows = ["light", "moderate", "dense"]
    mixes = ["cooperative", "neutral", "adversarial", "mixed"]
    parts = p.stem.removeprefix("grid_").split("_")
    f = flows.index(parts[0]) if parts and parts[0] in flows else 99
    m = mixes.index(parts[1]) if len(parts) > 1 and parts[1] in mixes else 99
    return (f, m, p.stem)


@dataclass
class GridResult:
    rows: list[dict]
    episodes_per_s: float
    wall_s: float
    out_dir: Path
    backend: str = "serial"
    cells_run: int = 0
    cells_reused: int = 0


@dataclass(frozen=True)
class Cell:
    """One unit of grid work: a policy (one training run of it) on one condition (one learned
    highway policy of it, or scripted traffic), over the condition's episodes."""

    policy: PolicySpec
    run: str | None
    condition: Condition
    highway: str | None
    episodes: int
    seed: int
    worlds: int

    @property
    def key(self) -> str:
        """A name for the cell's result file, fixed by everything the result depends on: the
        arguments, the condition's scenario as loaded now, and the saved policies' contents (a
        preset edited or a run trained again into the same folder gives a new key)."""
        saved = (
            saved_digest(self.run, DEFAULT_FILE["ego"]),
            saved_digest(self.highway, DEFAULT_FILE["highway"]),
        )
        scenario = to_dict(self.condition.scenario())
        text = repr((self.policy, self.run, self.condition, self.highway, self.episodes, self.seed))
        text += repr((saved, scenario))
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def road_seeds(seed: int, preset_name: str, episodes: int) -> list[np.random.SeedSequence]:
    """The seeds of a condition's episodes: keyed by the root seed, the preset and the episode."""
    key = zlib.crc32(preset_name.encode())
    return [np.random.SeedSequence(seed, spawn_key=(key, e)) for e in range(episodes)]


def run_cell(cell: Cell) -> list[dict]:
    """The rows of one cell (runs anywhere: a pure function of the cell)."""
    from marlmerge.learners.highway import load_highway_policy

    scen = scenario_for(cell.policy, cell.run, cell.condition.scenario())
    policy = make_policy(cell.policy, cell.run, scen)
    rec, traces = rollout_first_egos(
        policy,
        scen,
        cell.episodes,
        cell.seed,
        cell.worlds,
        record=True,
        highway_policy=None if cell.highway is None else load_highway_policy(cell.highway, scen),
        road_seeds=road_seeds(cell.seed, scen.name, cell.episodes),
    )
    return [
        {
            "policy": cell.policy.name,
            "run": cell.run or "-",
            "condition": cell.condition.label,
            "highway": cell.highway or "scripted",
            "flow_vph_per_lane": scen.traffic.flow_vph_per_lane,
            "episode": i,
            **episode_metrics(traj),
            "background_collisions": int(rec["background_collisions"][i]),
        }
        for i, traj in enumerate(traces)
    ]


ESTIMATORS = ("mc", "is")
"""`mc`: the cells' episodes only; `is`: also an importance-sampled collision rate per cell
(`marlmerge.evaluation.estimate`)."""


def run_estimate_cell(cell: Cell, out_dir: str) -> dict:
    """A cell's collision rate by importance sampling: cross-entropy rounds of half the cell's
    episodes, then the cell's episodes under the fitted proposal (resumable in `out_dir`)."""
    from marlmerge.evaluation.estimate import EstimateSettings, Estimator

    scen = scenario_for(cell.policy, cell.run, cell.condition.scenario())
    policy = make_policy(cell.policy, cell.run, scen)
    settings = EstimateSettings(
        episodes=cell.episodes,
        seed=(cell.seed + zlib.crc32(scen.name.encode())) % 2**31,
        worlds=cell.worlds,
        rounds=4,
        round_episodes=max(cell.episodes // 2, 50),
    )
    name = f"{cell.policy.name}:{cell.run or '-'}"
    report = Estimator(policy, name, scen, settings, Path(out_dir) / cell.key).run()
    keys = ("rate", "ci95", "se", "events", "ess", "episodes", "trusted")
    return {"policy": cell.policy.name, "condition": cell.condition.label} | {
        k: report[k] for k in keys
    }


def _run_estimates(
    cells: list[Cell], out: Path, backend: str, workers: int | None, address: str | None
) -> list[dict]:
    """The importance-sampled estimate of every scripted-traffic cell (reused when present)."""
    mine = [c for c in cells if c.highway is None]
    files = [out / "cells" / f"{c.key}.is.json" for c in mine]
    todo = [i for i, f in enumerate(files) if not f.exists()]

    def done(j: int, result: dict) -> None:
        write_text(files[todo[j]], json.dumps(result))

    task = functools.partial(run_estimate_cell, out_dir=str(out / "estimates"))
    run_tasks(task, [mine[i] for i in todo], backend, done, workers, address)
    return [json.loads(f.read_text()) for f in files]


def _estimate_table(estimates: list[dict], policies: list[str], conds: list[str]) -> list[str]:
    """Collision % by importance sampling per (policy, condition): the runs' estimates averaged,
    their standard errors combined, and the runs' effective events (ESS) summed."""
    by: dict[tuple[str, str], list[dict]] = {}
    for e in estimates:
        by.setdefault((e["policy"], e["condition"]), []).append(e)

    def fmt(p: str, c: str) -> str:
        runs = by.get((p, c), [])
        if not runs:
            return "–"
        rate = float(np.mean([e["rate"] for e in runs]))
        se = float(np.sqrt(np.sum([e["se"] ** 2 for e in runs]))) / len(runs)
        ess = sum(e["ess"] for e in runs)
        if not math.isfinite(se):  # a run without events: no interval (`weighted_mean_estimate`)
            return f"{100 * rate:.3f} [no interval: a run without events] ESS {ess:.0f}"
        lo, hi = max(rate - Z_95 * se, 0.0), rate + Z_95 * se
        return f"{100 * rate:.3f} [{100 * lo:.3f}–{100 * hi:.3f}] ESS {ess:.0f}"

    return [
        "## Collision % by importance sampling (95 % interval, effective events)",
        "",
        "Each cell's traffic drawn from a proposal fitted by the cross-entropy method and "
        "weighed back (`marlmerge estimate`); fresh roads, not the episodes above. An ESS "
        "below 30 is too few effective events to trust the interval.",
        "",
        *_table([], policies, conds, fmt),
        "",
    ]


def refuse_twice(what: str, names: Sequence[str]) -> None:
    """A policy or condition named twice would add the same episodes twice to its pooled rates
    (and narrow their intervals): refused, naming it."""
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise ValueError(
                f"{what} {name!r} is given twice (a glob may overlap another spec): its episodes "
                "would count twice; give each once, or a label of its own (LABEL=SPEC)"
            )
        seen.add(name)


def run_grid(
    policies: Sequence[PolicySpec],
    conditions: Sequence[str | Condition],
    episodes: int = 30,
    seed: int = 2_000_000,
    worlds: int = 50,
    out_dir: str | Path = "runs/grid",
    progress: bool = True,
    backend: str = "serial",
    workers: int | None = None,
    address: str | None = None,
    estimator: str = "mc",
    ramp_hours: float = 0.25,
    ramp_worlds: int = 4,
) -> GridResult:
    """Evaluate every policy on every condition on `backend`; write the CSV, the summary and the
    heat maps. Cells already in `out_dir/cells` (same arguments) are reused. With `estimator`
    "is" the summary adds each cell's importance-sampled collision rate. Conditions with ramp
    flow are measured as a whole merge instead (`marlmerge.evaluation.grid_flow`: `ramp_hours`
    in each of `ramp_worlds` worlds)."""
    check_backend(backend, workers, address)
    _check_grid_args(estimator, episodes, worlds, ramp_hours, ramp_worlds)
    every = [c if isinstance(c, Condition) else parse_condition(c) for c in conditions]
    _check_cells(policies, every)  # refused before any file is written
    out = Path(out_dir)
    (out / "cells").mkdir(parents=True, exist_ok=True)
    flowing = [c for c in every if c.scenario().ramp.flowing]
    conds = [c for c in every if c not in flowing]
    flow_cells = [
        FlowCell(p, run, c, ramp_hours, ramp_worlds, seed)
        for c in flowing
        for p in policies
        for run in (p.runs or (None,))
    ]
    for cell in flow_cells:
        check_flow_cell(cell.policy, cell.condition)
    names = list(dict.fromkeys(p.name for p in policies))
    if not conds:  # ramp flow only: no episodes
        flows = run_flow_cells(flow_cells, out, backend, workers, address)
        write_text(
            out / "summary.md",
            "\n".join(["# Robustness grid", "", *flow_table(flows, ramp_hours, ramp_worlds)]),
        )
        return GridResult([], 0.0, 0.0, out, backend, 0, 0)
    cells = [
        Cell(p, run, c, hw, episodes, seed, worlds)
        for c in conds
        for p in policies
        for run in (p.runs or (None,))
        for hw in (c.highway or (None,))
    ]
    result = _run_cells(cells, out, episodes, progress, backend, workers, address)
    rows = result.rows
    labels = list(dict.fromkeys(c.label for c in conds))
    summary = summary_markdown(rows, names, labels, result, episodes, seed)
    if estimator == "is":
        estimates = _run_estimates(cells, out, backend, workers, address)
        summary += "\n".join(_estimate_table(estimates, names, labels)) + "\n"
    flows = run_flow_cells(flow_cells, out, backend, workers, address)
    if flows:
        summary += "\n" + "\n".join(flow_table(flows, ramp_hours, ramp_worlds))
    (out / "summary.md").write_text(summary)
    plot_heatmaps(rows, names, labels, out)
    return result


def _check_grid_args(
    estimator: str, episodes: int, worlds: int, ramp_hours: float, ramp_worlds: int
) -> None:
    """`run_grid`'s counts and estimator, refused naming the value."""
    if estimator not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {', '.join(ESTIMATORS)}, got {estimator!r}")
    if episodes < 1 or worlds < 1:
        raise ValueError(f"episodes and worlds must be >= 1, got {episodes} and {worlds}")
    if not 0 < ramp_hours < math.inf or ramp_worlds < 1:
        raise ValueError(
            f"ramp_hours must be finite and > 0 and ramp_worlds >= 1, got {ramp_hours} and "
            f"{ramp_worlds}"
        )


def _check_cells(policies: Sequence[PolicySpec], every: Sequence[Condition]) -> None:
    """Names given twice, and left-lane shields on conditions without left-lane features."""
    refuse_twice("policy", [p.name for p in policies])
    refuse_twice("condition", [c.label for c in every])
    for p in (p for p in policies if p.shield_left):
        for c in every:
            for run in p.runs or (None,):
                check_shield_left(p, scenario_for(p, run, c.scenario()))


def _run_cells(
    cells: list[Cell],
    out: Path,
    episodes: int,
    progress: bool,
    backend: str,
    workers: int | None,
    address: str | None,
) -> GridResult:
    """Run the cells not already in `out/cells` (one CSV each) on `backend`, then join every
    cell's episodes into `out/episodes.csv`."""
    files = [out / "cells" / f"{cell.key}.csv" for cell in cells]
    todo = [i for i, f in enumerate(files) if not f.exists()]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(
            total=len(cells) * episodes,
            initial=(len(cells) - len(todo)) * episodes,
            unit="ep",
            desc=f"grid ({backend})",
            dynamic_ncols=True,
        )

    def done(j: int, rows: list[dict]) -> None:
        write_text(files[todo[j]], _csv_text(rows))
        if bar is not None:
            bar.update(len(rows))

    t0 = time.perf_counter()
    run_tasks(run_cell, [cells[i] for i in todo], backend, done, workers, address)
    wall = time.perf_counter() - t0
    if bar is not None:
        bar.close()
    texts = [f.read_text() for f in files]
    write_text(out / "episodes.csv", texts[0] + "".join(t.split("\n", 1)[1] for t in texts[1:]))
    rows = list(csv.DictReader(io.StringIO((out / "episodes.csv").read_text())))
    rate = len(todo) * episodes / max(wall, 1e-9)
    return GridResult(rows, rate, wall, out, backend, len(todo), len(cells) - len(todo))


def _csv_text(rows: list[dict]) -> str:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def _by_cell(rows: list[dict]) -> dict[tuple[str, str], list[dict]]:
    """The rows of each (policy, condition), in order: the tables read their cells from here
    (one pass over the rows, not one per table cell)."""
    cells: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        cells.setdefault((r["policy"], r["condition"]), []).append(r)
    return cells


def _cell(cells: dict, policy: str, cond: str, metric: str) -> np.ndarray:
    return np.array([r[metric] for r in cells.get((policy, cond), [])], dtype=np.float64)


def _fmt_rate(values: np.ndarray) -> str:
    m, lo, hi = aggregate(values, "rate")
    return f"{100 * m:.1f} [{100 * lo:.1f}–{100 * hi:.1f}]"


def _fmt_rate2(values: np.ndarray) -> str:
    """A pooled rate in % with two decimals and its 95 % Wilson interval."""
    m, lo, hi = aggregate(values, "rate")
    return f"{100 * m:.2f} [{100 * lo:.2f}–{100 * hi:.2f}]"


def _fmt_mean(values: np.ndarray, digits: int = 1) -> str:
    m, lo, hi = aggregate(values, "mean")
    if not np.isfinite(m):
        return "–"
    return f"{m:.{digits}f} ±{(hi - lo) / 2:.{digits}f}"


def _table(rows: list[dict], policies: list[str], conds: list[str], cell) -> list[str]:
    lines = ["| policy | " + " | ".join(conds) + " |", "|---" * (len(conds) + 1) + "|"]
    for p in policies:
        lines.append(f"| {p} | " + " | ".join(cell(p, c) for c in conds) + " |")
    return lines


def _overall_table(
    rows: list[dict], cells: dict, policies: list[str], conds: list[str]
) -> list[str]:
    """Per policy: success / collision / truncation over all conditions, the worst condition
    (pooled over runs) and the worst (training run, condition), by success rate."""
    lines = [
        "| policy | episodes | success % | collision % | truncation % | worst condition | "
        "worst run in a condition | time to merge (s) | max jerk (m/s³) |",
        "|---" * 9 + "|",
    ]
    for p in policies:
        mine = [r for r in rows if r["policy"] == p]
        rate = {k: _fmt_rate2(np.array([float(r[k]) for r in mine])) for k in _OUTCOMES}
        by_run: dict[tuple[str, str], list[float]] = {}
        for r in mine:
            by_run.setdefault((r["run"], r["condition"]), []).append(float(r["success"]))
        pooled = {c: _cell(cells, p, c, "success") for c in conds}
        worst_c = min(conds, key=lambda c: float(np.mean(pooled[c])))
        run, cond = min(by_run, key=lambda k: float(np.mean(by_run[k])))
        lines.append(
            f"| {p} | {len(mine)} | {rate['success']} | {rate['collision']} | "
            f"{rate['truncation']} | {worst_c}: {_fmt_rate(pooled[worst_c])} | "
            f"{run_name(run)} in {cond}: {_fmt_rate(np.array(by_run[(run, cond)]))} | "
            f"{_fmt_mean(np.array([float(r['time_to_merge_s']) for r in mine]))} | "
            f"{_fmt_mean(np.array([float(r['max_abs_jerk_mps3']) for r in mine]))} |"
        )
    return lines


_OUTCOMES = ("success", "collision", "truncation")


def run_name(run: str) -> str:
    """A run as the tables name it: its folder (also for a policy file inside one)."""
    path = Path(run)
    return path.parent.name if path.suffix == ".pt" else path.name


def _runs_table(rows: list[dict], policies: list[str], conds: list[str]) -> list[str]:
    """Per training run of the policies that have several: success and collision over every
    condition, and its worst condition (empty if no policy has several runs)."""
    lines = [
        "## Per training run",
        "",
        "| policy | run | success % | collision % | worst condition |",
        "|---|---|---|---|---|",
    ]
    by_run: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        by_run.setdefault((r["policy"], r["run"]), []).append(r)
    for p in policies:
        runs = [run for policy, run in by_run if policy == p]
        if len(runs) < 2:
            continue
        for run in runs:
            mine = by_run[(p, run)]
            succ = {
                c: np.array([float(r["success"]) for r in mine if r["condition"] == c])
                for c in conds
            }
            worst = min(conds, key=lambda c: float(np.mean(succ[c])))
            lines.append(
                f"| {p} | {run_name(run)} | "
                f"{_fmt_rate2(np.array([float(r['success']) for r in mine]))} | "
                f"{_fmt_rate2(np.array([float(r['collision']) for r in mine]))} | "
                f"{worst}: {_fmt_rate(succ[worst])} |"
            )
    return [*lines, ""] if len(lines) > 4 else []


def _metric_sections(cells: dict) -> list[tuple[str, Callable[[str, str], str]]]:
    """The summary's per-cell tables: (heading, the text of a policy's cell in a condition)."""

    def mean(p: str, c: str, key: str, digits: int = 1) -> str:
        return _fmt_mean(_cell(cells, p, c, key), digits)

    def rate(p: str, c: str, key: str) -> str:
        return _fmt_rate(_cell(cells, p, c, key))

    return [
        (
            "Success % / collision %",
            lambda p, c: f"{rate(p, c, 'success')} / {rate(p, c, 'collision')}",
        ),
        (
            "Comfort: mean |acceleration| (m/s²) / max |jerk| (m/s³)",
            lambda p, c: (
                f"{mean(p, c, 'mean_abs_accel_mps2', 2)} / {mean(p, c, 'max_abs_jerk_mps3')}"
            ),
        ),
        (
            "Safety: time with TTC < 1.5 s (s) / min headway after merging (s) / "
            "new follower's min acceleration (m/s²)",
            lambda p, c: (
                f"{mean(p, c, 'time_ttc_below_s', 2)} / "
                f"{mean(p, c, 'min_headway_after_merge_s', 2)} / "
                f"{mean(p, c, 'follower_min_accel_mps2')}"
            ),
        ),
        (
            "Collisions among mainline vehicles (not involving the ego), per episode",
            lambda p, c: mean(p, c, "background_collisions", 3),
        ),
        ("Timeliness: time to merge (s)", lambda p, c: mean(p, c, "time_to_merge_s")),
    ]


def summary_markdown(
    rows: list[dict],
    policies: list[str],
    conds: list[str],
    result: GridResult,
    episodes: int,
    seed: int,
) -> str:
    n_runs = {p: len({r["run"] for r in rows if r["policy"] == p}) for p in policies}
    cells = _by_cell(rows)
    out = [
        "# Robustness grid",
        "",
        f"{episodes} episodes per condition (root seed {seed}), the same for every policy; "
        "learned policies pooled over their training runs "
        f"({', '.join(f'{p}: {n}' for p, n in n_runs.items())}). "
        f"{len(rows)} episodes; {result.cells_run} of {len(result.rows) // max(episodes, 1)} "
        f"cells run here on the {result.backend} backend in {result.wall_s:.0f} s "
        f"({result.episodes_per_s:.1f} episodes/s).",
        "Rates in % with 95 % Wilson intervals; means with 95 % half-widths.",
        "",
        "## Overall: every condition pooled, and the worst cell",
        "",
        *_overall_table(rows, cells, policies, conds),
        "",
        *_runs_table(rows, policies, conds),
    ]
    for i, (title, fmt) in enumerate(_metric_sections(cells)):
        if i:
            out.append("")
        out += [f"## {title}", "", *_table(rows, policies, conds, fmt)]
    out += ["", "Every metric of every episode is in `episodes.csv`.", ""]
    return "\n".join(out)


def plot_heatmaps(rows: list[dict], policies: list[str], conds: list[str], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = _by_cell(rows)
    for metric, cmap in (("success", "RdYlGn"), ("collision", "RdYlGn_r")):
        grid = np.array([[np.mean(_cell(cells, p, c, metric)) for c in conds] for p in policies])
        fig, ax = plt.subplots(figsize=(1.1 * len(conds) + 2.5, 0.6 * len(policies) + 2))
        im = ax.imshow(100 * grid, cmap=cmap, vmin=0, vmax=100, aspect="auto")
        ax.set_xticks(range(len(conds)), conds, rotation=40, ha="right")
        ax.set_yticks(range(len(policies)), policies)
        for i in range(len(policies)):
            for j in range(len(conds)):
                ax.text(j, i, f"{100 * grid[i, j]:.0f}", ha="center", va="center", fontsize=9)
        fig.colorbar(im, ax=ax, label=f"{metric} rate (%)")
        ax.set_title(f"{metric} rate by policy and traffic condition")
        fig.tight_layout()
        fig.savefig(out / f"heatmap_{metric}.png", dpi=120)
        plt.close(fig)
