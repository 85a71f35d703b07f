"""`marlmerge validate`: run the validation scenarios in both simulators, compare, write a report.

Without SUMO, the committed reference outputs of SUMO (`reference/sumo_reference.npz`, written
by a run with SUMO installed) stand in for it; with SUMO, it is run afresh and its outputs are
written beside the report (`OUT/sumo_reference.npz`); the shipped reference inside the package
is rewritten only when asked (`--update-reference`, from a source checkout). The report goes to
`--out` (default `docs/validation/`): `README.md` (tables against the targets),
`results.json`, and plots of the car-following trajectories, the fundamental diagram and the
time-headway distributions.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from marlmerge.config import ScenarioConfig
from marlmerge.validation import scenarios as S
from marlmerge.validation import sumo
from marlmerge.validation.measure import (
    DETECTOR_M,
    SECTION_M,
    FlowSamples,
    detector_crossings,
    flow_metrics,
    time_headways,
)

REFERENCE = Path(__file__).resolve().parent / "reference" / "sumo_reference.npz"
CF_TOLERANCE_M = 1e-3
"""Car following: largest position difference allowed, m."""
FLOW_TOLERANCE = {"throughput_vphpl": 0.10, "density_vpkmpl": 0.10, "space_mean_speed_mps": 0.10}
"""Flow sweep: largest relative difference allowed per measurement."""
HEADWAY_TOLERANCE = {"headway_p10_s": 0.20}
DURATION_S = 900.0
"""Simulated time of each flow-sweep run ..."""
MEASURE_FROM_S = 300.0
"""... measured from here on (the entrance queue and the road have settled)."""
SEEDS = (0, 1)
"""Flow-sweep runs per flow (one world each; both simulators get its drawn arrivals)."""
METRICS = tuple(FLOW_TOLERANCE) + tuple(HEADWAY_TOLERANCE) + ("headway_median_s",)


@dataclass
class SimResults:
    """What one simulator produced: trajectories per case, measurements and headways per flow."""

    trajectories: dict[str, S.Trajectories] = field(default_factory=dict)
    metrics: dict[float, list[dict[str, float]]] = field(default_factory=dict)  # per seed
    headways: dict[float, np.ndarray] = field(default_factory=dict)  # pooled over seeds


def _flow_results(samples: FlowSamples) -> tuple[dict[str, float], np.ndarray]:
    t_cross, lane = detector_crossings(samples, DETECTOR_M)
    keep = t_cross >= MEASURE_FROM_S
    return flow_metrics(samples, MEASURE_FROM_S), time_headways(t_cross[keep], lane[keep])


def run_simulator(cfg: ScenarioConfig, which: str, seeds: tuple[int, ...] = SEEDS) -> SimResults:
    """Every scenario in "marlmerge" or "sumo"."""
    mod = S if which == "marlmerge" else sumo
    res = SimResults()
    for case in S.CASES:
        res.trajectories[case.name] = mod.run_car_following(case, cfg)
    for flow in S.FLOWS_VPHPL:
        runs = [_flow_results(mod.run_flow(S.flow_config(cfg, flow), s, DURATION_S)) for s in seeds]
        res.metrics[flow] = [m for m, _ in runs]
        res.headways[flow] = np.concatenate([h for _, h in runs])
    return res


def save_reference(res: SimResults, path: Path = REFERENCE, version: str = "") -> None:
    """SUMO's results as a small compressed file (trajectories, measurements, headways)."""
    arrays: dict[str, np.ndarray] = {"version": np.array(version)}
    for name, tr in res.trajectories.items():
        arrays[f"cf/{name}"] = np.stack(
            [tr.t_s, tr.follower_pos_m, tr.follower_v_mps, tr.leader_pos_m, tr.leader_v_mps]
        )
    for flow, runs in res.metrics.items():
        arrays[f"flow/{flow:g}/metrics"] = np.array([[m[k] for k in METRICS] for m in runs])
        arrays[f"flow/{flow:g}/headways"] = np.round(res.headways[flow], 3)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)


def load_reference(path: Path = REFERENCE) -> tuple[SimResults, str]:
    """The committed SUMO results and the SUMO version that produced them."""
    if not path.exists():
        raise FileNotFoundError(f"no SUMO reference at {path}: run `marlmerge validate` with SUMO")
    res = SimResults()
    with np.load(path) as z:
        version = str(z["version"])
        for case in S.CASES:
            res.trajectories[case.name] = S.Trajectories(*z[f"cf/{case.name}"])
        for flow in S.FLOWS_VPHPL:
            rows = z[f"flow/{flow:g}/metrics"]
            res.metrics[flow] = [dict(zip(METRICS, map(float, r), strict=True)) for r in rows]
            res.headways[flow] = z[f"flow/{flow:g}/headways"]
    return res, version


def compare(ours: SimResults, ref: SimResults) -> dict[str, Any]:
    """Differences against the targets: per case the largest position and speed difference,
    per flow the mean of each measurement over the seeds and its ratio to SUMO's."""
    cf = {}
    for name, a in ours.trajectories.items():
        b = ref.trajectories[name]
        cf[name] = {
            "max_pos_diff_m": float(np.nanmax(np.abs(a.follower_pos_m - b.follower_pos_m))),
            "max_speed_diff_mps": float(np.nanmax(np.abs(a.follower_v_mps - b.follower_v_mps))),
        }
        cf[name]["ok"] = cf[name]["max_pos_diff_m"] <= CF_TOLERANCE_M
    flows = {}
    tol = FLOW_TOLERANCE | HEADWAY_TOLERANCE
    for flow in ours.metrics:
        row: dict[str, Any] = {}
        for k in METRICS:
            a = float(np.mean([m[k] for m in ours.metrics[flow]]))
            b = float(np.mean([m[k] for m in ref.metrics[flow]]))
            row[k] = {"marlmerge": a, "sumo": b, "ratio": a / b}
            if k in tol:
                row[k]["ok"] = abs(a / b - 1.0) <= tol[k]
        flows[f"{flow:g}"] = row
    ok = all(c["ok"] for c in cf.values()) and all(
        v["ok"] for row in flows.values() for v in row.values() if "ok" in v
    )
    return {"car_following": cf, "flow_sweep": flows, "all_targets_met": ok}


def validate(
    cfg: ScenarioConfig | None = None,
    out_dir: str | Path = "docs/validation",
    use_sumo: bool | None = None,
    seeds: tuple[int, ...] = SEEDS,
    update_reference: bool = False,
) -> dict[str, Any]:
    """Run marlmerge (and SUMO when installed, else its reference), compare, write the report.
    Everything is written under `out_dir`; `update_reference` (with SUMO, the default scenario
    and seeds) also replaces the shipped reference `REFERENCE`."""
    cfg = cfg or ScenarioConfig()
    use_sumo = sumo.available() if use_sumo is None else use_sumo
    if update_reference and not (use_sumo and seeds == SEEDS and cfg == ScenarioConfig()):
        raise ValueError(
            "--update-reference needs SUMO, the default scenario and the default seeds"
        )
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ours = run_simulator(cfg, "marlmerge", seeds)
    if use_sumo:
        ref, version = run_simulator(cfg, "sumo", seeds), sumo.sumo_version()
        save_reference(ref, out / REFERENCE.name, version)
        if update_reference:
            save_reference(ref, version=version)
    else:
        ref, version = load_reference()
    result = compare(ours, ref)
    result["sumo_version"] = version
    result["sumo_ran"] = bool(use_sumo)
    (out / "results.json").write_text(json.dumps(result, indent=1))
    _plots(ours, ref, out)
    (out / "README.md").write_text(_markdown(result, seeds))
    return result


def _plots(ours: SimResults, ref: SimResults, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(S.CASES), figsize=(4.2 * len(S.CASES), 6), squeeze=False)
    for j, case in enumerate(S.CASES):
        a, b = ours.trajectories[case.name], ref.trajectories[case.name]
        ax = axes[0, j]
        ax.plot(a.t_s, a.follower_v_mps, label="marlmerge follower", lw=2)
        ax.plot(b.t_s, b.follower_v_mps, "--", label="SUMO follower", lw=1.5)
        if not np.all(np.isnan(a.leader_v_mps)):
            ax.plot(a.t_s, a.leader_v_mps, ":", color="grey", label="leader")
        ax.set(title=case.name, xlabel="t (s)", ylabel="speed (m/s)")
        ax.legend(fontsize=7)
        ax = axes[1, j]
        ax.plot(a.t_s, a.follower_pos_m - b.follower_pos_m, color="tab:red")
        ax.set(xlabel="t (s)", ylabel="position, marlmerge - SUMO (m)")
    fig.tight_layout()
    fig.savefig(out / "car_following.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for res, name, mark in ((ours, "marlmerge", "o-"), (ref, "SUMO", "s--")):
        k = [np.mean([m["density_vpkmpl"] for m in res.metrics[f]]) for f in S.FLOWS_VPHPL]
        q = [np.mean([m["throughput_vphpl"] for m in res.metrics[f]]) for f in S.FLOWS_VPHPL]
        v = [np.mean([m["space_mean_speed_mps"] for m in res.metrics[f]]) for f in S.FLOWS_VPHPL]
        axes[0].plot(k, q, mark, label=name)
        axes[1].plot(k, v, mark, label=name)
    axes[0].set(xlabel="density (veh/km/lane)", ylabel="throughput (veh/h/lane)")
    axes[1].set(xlabel="density (veh/km/lane)", ylabel="space-mean speed (m/s)")
    for ax in axes:
        ax.legend()
    fig.suptitle(f"Fundamental diagram, demand {', '.join(f'{f:g}' for f in S.FLOWS_VPHPL)}")
    fig.tight_layout()
    fig.savefig(out / "fundamental_diagram.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(S.FLOWS_VPHPL), figsize=(3.6 * len(S.FLOWS_VPHPL), 3.4))
    bins = np.linspace(0.0, 8.0, 41)
    for ax, flow in zip(axes, S.FLOWS_VPHPL, strict=True):
        ax.hist(ours.headways[flow], bins, density=True, alpha=0.55, label="marlmerge")
        ax.hist(ref.headways[flow], bins, density=True, histtype="step", lw=1.5, label="SUMO")
        ax.set(title=f"{flow:g} veh/h/lane", xlabel="time headway (s)")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out / "headways.png", dpi=110)
    plt.close(fig)


def _markdown(r: dict[str, Any], seeds: tuple[int, ...]) -> str:
    src = "a fresh SUMO run" if r["sumo_ran"] else "the committed SUMO reference outputs"
    lines = [
        "# Validation against SUMO",
        "",
        f"marlmerge against SUMO {r['sumo_version']} ({src}) on the same road with the same "
        "driver parameters. Regenerate with `marlmerge validate` (SUMO from `pip install -e "
        '".[sumo]"`; without it the committed reference stands in for SUMO). What is run and '
        "how: `marlmerge/validation/`.",
        "",
        f"All targets met: **{'yes' if r['all_targets_met'] else 'no'}**.",
        "",
        "## Car following (IDM, ballistic update)",
        "",
        f"Target: positions within {CF_TOLERANCE_M:g} m of SUMO's IDM (`--step-method.ballistic`).",
        "",
        "| case | largest position difference (m) | largest speed difference (m/s) | target |",
        "|---|---|---|---|",
    ]
    for name, c in r["car_following"].items():
        lines.append(
            f"| {name} | {c['max_pos_diff_m']:.2e} | {c['max_speed_diff_mps']:.2e} | "
            f"{'met' if c['ok'] else 'missed'} |"
        )
    lines += [
        "",
        "![car following](car_following.png)",
        "",
        "## Mainline flow sweep (no ramp vehicle)",
        "",
        f"Both simulators get the same drawn vehicles (arrival time, lane, entry speed, desired "
        f"speed, headway) of {len(seeds)} worlds per flow, {DURATION_S:g} s each, measured from "
        f"{MEASURE_FROM_S:g} s on: throughput at the detector {DETECTOR_M:g} m from the entrance, "
        f"density and space-mean speed over {SECTION_M[0]:g}-{SECTION_M[1]:g} m. Lane changes: "
        "MOBIL in marlmerge, LC2013 in SUMO. Targets: throughput, density and speed within 10 %, "
        "10th-percentile time headway within 20 %.",
        "",
        "| demand (veh/h/lane) | measurement | marlmerge | SUMO | ratio | target |",
        "|---|---|---|---|---|---|",
    ]
    for flow, row in r["flow_sweep"].items():
        for k, v in row.items():
            target = ("met" if v["ok"] else "missed") if "ok" in v else "-"
            lines.append(
                f"| {flow} | {k} | {v['marlmerge']:.2f} | {v['sumo']:.2f} | {v['ratio']:.3f} "
                f"| {target} |"
            )
    lines += [
        "",
        "![fundamental diagram](fundamental_diagram.png)",
        "",
        "![time headways](headways.png)",
        "",
    ]
    return "\n".join(lines)
