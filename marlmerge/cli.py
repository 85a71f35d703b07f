"""Command line: `marlmerge train | cotrain | sweep | evaluate | grid | stress | estimate |
rampflow | plot | simulate | render | validate`.

`marlmerge --help` lists them."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any


def simulate(args: argparse.Namespace) -> int:
    """Drive ramp vehicles through scripted traffic, print what happened, save a frame."""
    from marlmerge.config.presets import resolve_config
    from marlmerge.evaluation.simulate import SHOWN_TERMS, simulate

    cfg = resolve_config(args.scenario)
    print(
        f"scenario {cfg.name!r}: {cfg.traffic.flow_vph_per_lane:.0f} veh/h/lane, drivers "
        f"coop/neutral/adv = {cfg.driver.mix_cooperative:.2f}/{cfg.driver.mix_neutral:.2f}/"
        f"{cfg.driver.mix_adversarial:.2f}, ego rule {args.ego!r}, seed {args.seed}"
    )
    print(f"{'ep':>3} {'outcome':>10} {'time_s':>7} {'reward':>8}  ", end="")
    print(" ".join(f"{k:>12}" for k in SHOWN_TERMS))

    def row(r: dict[str, Any]) -> None:
        terms = " ".join(f"{r.get(k, 0.0):>12.2f}" for k in SHOWN_TERMS)
        print(
            f"{r['episode']:>3} {r['outcome']:>10} {r['time_s']:>7.1f} {r['reward']:>8.2f}  {terms}"
        )

    out = Path(args.out)
    result = simulate(cfg, args.ego, args.episodes, args.seed, out, on_episode=row)
    shown = (
        f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in result.summary.items()
    )
    print("summary: " + ", ".join(shown))
    print(f"wrote {out / 'episodes.json'}" + (f" and {result.frame}" if result.frame else ""))
    return 0


def _parse_sets(items: list[str]) -> dict:
    """`--set key=value` pairs, values in TOML syntax (numbers, true/false, "strings")."""
    from marlmerge.config import tomllib

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--set expects key=value, got {item!r}")
        try:
            out[key.strip()] = tomllib.loads(f"v = {value.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            out[key.strip()] = value.strip()
    return out


def _run_config(
    cls: type,
    out: Path,
    cfg: Any,
    sets: dict[str, Any],
    resume: bool,
    name: str = "checkpoint.pt",
    named: bool = True,
) -> Any:
    """The config a run in `out` (checkpoint `name`) trains with: `cfg` for a new run, the
    checkpoint's when resuming (a `--set` that differs from it, or a preset `named` on the
    command line that is not the run's, is an error naming it)."""
    from marlmerge.config.presets import run_scenario
    from marlmerge.training.checkpoint import resume_config
    from marlmerge.training.seeds import CHECKPOINT_NAME

    run_scenario(cfg)
    one, many = "checkpoint.pt", CHECKPOINT_NAME  # a single run's, a --seeds run's
    if name in (one, many) and (out / (many if name == one else one)).exists():
        kind = "of several seeds (--seeds)" if name == one else "of one seed (no --seeds)"
        raise ValueError(
            f"{out} holds a run {kind}: continue it as it was started (with --resume), or use "
            "another --out"
        )
    has_run = (out / name).exists()
    if has_run and not resume:
        raise ValueError(
            f"{out} already holds a run: pass --resume to continue it, or --out to "
            "start a new one elsewhere"
        )
    if resume and not has_run:
        raise ValueError(f"--resume: no checkpoint at {out / name}")
    return resume_config(cls, out, cfg, sets, name, named) if resume else cfg


def train_cmd(args: argparse.Namespace) -> int:
    """Train the ego with the quadratic-Q learner; evaluate and plot at the end."""
    from marlmerge.training.train import TrainConfig, load_train_config, train

    sets = _parse_sets(args.set)
    if args.preset:
        cfg = load_train_config(args.preset, **sets)
    else:
        from marlmerge.config import from_dict, to_dict
        from marlmerge.config.presets import with_overrides

        cfg = from_dict(TrainConfig, with_overrides(to_dict(TrainConfig()), sets))
    out = Path(args.out or f"runs/{cfg.name}")
    if args.seeds is not None:
        return _train_seeds_cmd(args, cfg, sets, out)
    cfg = _run_config(TrainConfig, out, cfg, sets, args.resume, named=bool(args.preset))
    print(
        f"training {cfg.name!r} on scenario {cfg.scenario!r}: {cfg.total_sim_steps:,} simulator "
        f"steps in {cfg.num_worlds} worlds, seed {cfg.seed}, writing {out}",
        flush=True,
    )
    result = train(cfg, out, resume=args.resume, progress=not args.no_progress)
    if result.already_finished:
        print(f"{out} had finished training and been evaluated: nothing to do, nothing changed")
        _print_evaluation(result.evaluation or {})
        return 0
    print(
        f"done: {result.sim_steps:,} simulator steps, {result.updates:,} updates, "
        f"{result.egos:,} ramp vehicles in {result.wall_s:.0f} s "
        f"(updates {result.update_s:.0f} s, env {result.collect_s:.0f} s)"
    )
    if result.evaluation is not None:
        _print_evaluation(result.evaluation)
    if cfg.shield_drives:
        print(
            f"trained (and evaluated) behind gap acceptance's shield: drive it the same way, "
            f"as {cfg.algorithm}@{cfg.shield}:{out}"
        )
    print(f"logs, checkpoint, policy and figures in {out}")
    return 0


def _train_seeds_cmd(args: argparse.Namespace, cfg: Any, sets: dict[str, Any], out: Path) -> int:
    """`train --seeds`: the seeds in one process (`marlmerge.training.seeds`)."""
    from marlmerge.training.seeds import CHECKPOINT_NAME, train_seeds
    from marlmerge.training.sweep import parse_seeds
    from marlmerge.training.train import TrainConfig

    seeds = parse_seeds(args.seeds)
    if "seed" in sets:
        raise ValueError(f"--seeds {args.seeds} and --set seed={sets['seed']}: give one of them")
    cfg = _run_config(TrainConfig, out, cfg, sets, args.resume, CHECKPOINT_NAME, bool(args.preset))
    print(
        f"training {cfg.name!r} on scenario {cfg.scenario!r}: {len(seeds)} seeds "
        f"({', '.join(map(str, seeds))}) in one process, {cfg.total_sim_steps:,} simulator steps "
        f"each in {cfg.num_worlds} worlds, writing {out}/seed_*",
        flush=True,
    )
    results = train_seeds(cfg, seeds, out, resume=args.resume, progress=not args.no_progress)
    for seed, result in zip(seeds, results, strict=True):
        print(f"seed {seed}: {result.sim_steps:,} simulator steps, {result.updates:,} updates")
        if result.evaluation is not None:
            _print_evaluation(result.evaluation)
    r = results[0]
    if not r.already_finished:
        print(
            f"done in {r.wall_s:.0f} s (updates {r.update_s:.0f} s, env {r.collect_s:.0f} s); "
            f"runs in {out}/seed_*"
        )
    return 0


def cotrain_cmd(args: argparse.Namespace) -> int:
    """Co-train learned highway agents and the ego (alternating phases)."""
    from marlmerge.training.cotrain import (
        SEEDS_CHECKPOINT,
        CoTrainConfig,
        cotrain,
        cotrain_seeds,
        load_cotrain_config,
    )
    from marlmerge.training.sweep import parse_seeds

    sets = _parse_sets(args.set)
    cfg = load_cotrain_config(args.preset, **sets)
    out = Path(args.out or f"runs/{cfg.name}")
    seeds = None if args.seeds is None else parse_seeds(args.seeds)
    if seeds is not None and "seed" in sets:
        raise ValueError(f"--seeds {args.seeds} and --set seed={sets['seed']}: give one of them")
    name = "checkpoint.pt" if seeds is None else SEEDS_CHECKPOINT
    cfg = _run_config(CoTrainConfig, out, cfg, sets, args.resume, name)
    phases = ", ".join(f"{kind} {n:,}" for kind, n in cfg.phases())
    who = f"seed {cfg.seed}" if seeds is None else f"seeds {', '.join(map(str, seeds))}"
    print(
        f"co-training {cfg.name!r} ({cfg.profile} highway agents) on scenario "
        f"{cfg.scenario!r}, {who}, writing {out}{'' if seeds is None else '/seed_*'}; "
        f"phases (simulator steps): {phases}",
        flush=True,
    )
    progress = not args.no_progress
    if seeds is None:
        results = [cotrain(cfg, out, resume=args.resume, progress=progress)]
    else:
        results = cotrain_seeds(cfg, seeds, out, resume=args.resume, progress=progress)
    for result in results:
        _print_cotrain_result(result, seeds is not None)
    return 0


def _print_cotrain_result(result: Any, many: bool) -> None:
    """What one co-training run did, its ego selection and evaluations."""
    out = result.out_dir
    if many:
        print(f"{out.name}:")
    if result.already_finished:
        print(f"{out} had finished co-training and been evaluated: nothing to do, nothing changed")
    print(
        f"done: {result.sim_steps:,} simulator steps, {result.egos:,} ramp vehicles, "
        f"{result.pool_size} highway snapshots in the pool, {result.wall_s:.0f} s"
    )
    evaluation = dict(result.evaluation or {})
    sel = evaluation.pop("selection", None)
    if sel is not None:
        scores = ", ".join(
            f"{'start' if i < 0 else f'after phase {i + 1}'}: {sum(row)}"
            for i, row in zip(sel["candidate_phase_index"], sel["failures"], strict=True)
        )
        chosen = sel["chosen_phase_index"]
        print(
            f"ego selection, failures in {sel['episodes_per_opponent']} episodes against each of "
            f"{len(sel['opponents'])} opponents (scripted + own pool): {scores}; policy.pt = "
            f"{'the starting ego' if chosen < 0 else f'the ego after phase {chosen + 1}'}"
        )
    for name, ev in evaluation.items():
        print(f"selected ego vs {name.replace('_', ' ')} traffic:")
        _print_evaluation(ev)
    print(f"logs, checkpoint and policies in {out}")


def _print_evaluation(ev: dict) -> None:
    if "merged_vph" in ev:  # a ramp-flow run: the merge as a whole
        from marlmerge.evaluation.ramp_flow import merge_line

        print(
            f"greedy evaluation under ramp flow ({ev['ramp_demand_vph']:g} veh/h on the ramp): "
            + merge_line(ev)
        )
        return

    def rate(key: str) -> str:
        lo, hi = ev[f"{key}_ci95"]
        return f"{key} {ev[f'{key}_rate']:.1%} [{lo:.1%}, {hi:.1%}]"

    print(
        f"greedy evaluation on {ev['episodes']} held-out episodes (95 % intervals): "
        f"{rate('success')}, {rate('collision')}, {rate('truncation')}, "
        f"mean merge time {ev['mean_merge_time_s']:.1f} s, "
        f"mean |acceleration| {ev['mean_abs_accel_mps2']:.2f} m/s^2"
    )
    if ev.get("shield_changed_share") is not None:
        print(
            f"the shield changed {ev['shield_changed_share']:.1%} of the ego's "
            f"{ev['shield_judged']:,} commands on the ramp"
        )
    if "highway_hard_brake_share" in ev:
        print(
            "highway agents: own-fault collisions in "
            f"{ev['highway_own_fault_collision_rate']:.1%} of episodes, hard braking "
            f"{ev['highway_hard_brake_share']:.1%} and below half the limit "
            f"{ev['highway_slow_share']:.1%} of agent steps, headway < 1 s "
            f"{ev['highway_short_headway_share']:.1%}"
        )
    if "fair_failure_rate" in ev:
        print(
            f"fairness: the ego fails in {ev['ego_failure_rate']:.1%} of the roads, gap "
            f"acceptance in {ev['rule_failure_rate']:.1%}; the ego alone in "
            f"{ev['fair_failure_rate']:.1%}"
        )


def _note_bare_shield(spec: str) -> None:
    """Say so where a run trained behind the shield is driven without it."""
    from marlmerge.evaluation.registry import bare_shield_note

    note = bare_shield_note(spec)
    if note:
        print(note, file=sys.stderr)


def evaluate_cmd(args: argparse.Namespace) -> int:
    """Evaluate a saved policy greedily on held-out episodes."""
    from marlmerge.config.presets import resolve_config

    if args.fairness and not args.highway:
        raise ValueError("--fairness needs --highway: the highway policy it judges")
    scen = None
    if args.scenario:  # checked before torch and the policy are loaded
        scen = resolve_config(args.scenario)
    from marlmerge.evaluation.registry import policy_for_evaluation
    from marlmerge.evaluation.rollout import run_episodes, summarize

    policy, scen = policy_for_evaluation(args.policy, scen)
    _note_bare_shield(args.policy)
    if scen.ramp.flowing:  # the merge as a whole: every ramp vehicle driven by the policy
        if args.highway or args.fairness:
            raise ValueError(
                f"--highway / --fairness: scenario {scen.name!r} runs ramp flow "
                f"(ramp.flow_vph = {scen.ramp.flow_vph:g}), whose mainline is scripted"
            )
        from marlmerge.evaluation.ramp_flow import evaluate_ramp_flow

        ev = evaluate_ramp_flow(scen, args.policy, args.episodes, args.seed, args.worlds)
        _print_evaluation(ev)
        print(json.dumps(ev))
        return 0
    highway = None
    if args.highway:
        from marlmerge.learners.highway import load_highway_policy

        highway = load_highway_policy(args.highway, scen)
    rec = run_episodes(policy, scen, args.episodes, args.seed, args.worlds, highway)
    ev = summarize(rec)
    if args.fairness:
        from marlmerge.evaluation.plausibility import fairness
        from marlmerge.evaluation.registry import policy_from_spec

        rule = policy_from_spec("gap", scen)
        rule_rec = run_episodes(rule, scen, args.episodes, args.seed, args.worlds, highway)
        ev |= fairness(rec["outcome"], rule_rec["outcome"])
    _print_evaluation(ev)
    print(json.dumps(ev))
    return 0


def grid_cmd(args: argparse.Namespace) -> int:
    """Evaluate policies across traffic conditions: CSV, Markdown summary, heat maps."""
    from marlmerge.evaluation.grid import (
        default_conditions,
        expand_conditions,
        parse_policy,
        run_grid,
    )

    policies = [parse_policy(p) for p in (args.policy or ["hold", "idm", "gap"])]
    conditions = expand_conditions(args.condition) if args.condition else default_conditions()
    result = run_grid(
        policies,
        conditions,
        args.episodes,
        args.seed,
        args.worlds,
        args.out,
        progress=not args.no_progress,
        backend=args.backend,
        workers=args.workers,
        address=args.address,
        estimator=args.estimator,
        ramp_hours=args.ramp_hours,
        ramp_worlds=args.ramp_worlds,
    )
    print(
        f"{len(result.rows)} episodes; {result.cells_run} cells run on the {result.backend} "
        f"backend in {result.wall_s:.0f} s ({result.episodes_per_s:.1f} episodes/s), "
        f"{result.cells_reused} cells reused from {result.out_dir}/cells"
    )
    print((result.out_dir / "summary.md").read_text())
    if not result.rows:  # ramp-flow conditions only
        print(f"wrote {result.out_dir}/summary.md")
        return 0
    print(
        f"wrote {result.out_dir}/episodes.csv, summary.md, heatmap_success.png, "
        "heatmap_collision.png"
    )
    return 0


def _settings(cls: type, args: argparse.Namespace) -> Any:
    """A settings dataclass from the command line: each field the arguments name and give
    (`--rel-ci` sets `rel_ci`); the others, and those left at None, keep their defaults."""
    given = {k: v for k, v in vars(args).items() if v is not None}
    return cls(**{f.name: given[f.name] for f in dataclasses.fields(cls) if f.name in given})


def check_estimate_flags(args: argparse.Namespace) -> None:
    """`estimate` flags that the asked method would ignore are refused, naming them."""
    if args.method != "is":
        for flag, value in (("--rounds", args.rounds), ("--round-episodes", args.round_episodes)):
            if value is not None:
                raise ValueError(
                    f"estimate {flag} {value}: the rounds fit the proposal of --method is; "
                    f"--method {args.method} fits nothing"
                )
    if args.episodes is not None and args.max_episodes is not None:
        raise ValueError(
            f"estimate --max-episodes {args.max_episodes} caps a --rel-ci run; with --episodes "
            f"{args.episodes} it does nothing: give one of them"
        )


def stress_cmd(args: argparse.Namespace) -> int:
    """Search the traffic space for where a policy fails; verify and write the regions."""
    from marlmerge.evaluation.stress import StressSettings, stress

    settings = _settings(StressSettings, args)
    out = Path(args.out)
    report = stress(args.policy, out, args.scenario, settings, clip=not args.no_clip)
    print((out / "regions.md").read_text())
    summary = {k: report[k] for k in ("policy", "episodes", "failure_rate", "wall_s")}
    summary["regions"] = [[r["preset"], r["failure_rate"], r["ci95"]] for r in report["regions"]]
    print(json.dumps(summary))
    return 0


def estimate_cmd(args: argparse.Namespace) -> int:
    """A policy's collision (or failure) rate with its 95 % interval, by Monte Carlo or
    importance sampling; the last line printed is the JSON summary."""
    from marlmerge.config.presets import resolve_config
    from marlmerge.evaluation.estimate import EstimateSettings, Estimator

    check_estimate_flags(args)
    settings = _settings(EstimateSettings, args)
    scen = resolve_config(args.scenario) if args.scenario else None
    from marlmerge.evaluation.registry import policy_for_evaluation, saved_files_of

    policy, scen = policy_for_evaluation(args.policy, scen)
    _note_bare_shield(args.policy)
    if settings.method == "is" and scen.driver.lapse_rate_per_h > 0:
        print(
            f"note: {scen.name}'s drivers lapse; --method split usually needs several times "
            "fewer episodes for the same interval there (docs/evaluation.md)",
            file=sys.stderr,
        )
    files = saved_files_of(args.policy)
    report = Estimator(policy, args.policy, scen, settings, args.out, files).run()
    lo, hi = report["ci95"]
    print(
        f"{report['event']} rate of {args.policy} on {report['scenario']} ({report['method']}): "
        f"{report['rate']:.3g} [{lo:.3g}, {hi:.3g}] from {report['episodes']} episodes "
        + (
            f"({report['trunk_episodes']} trunks, {report['branch_episodes']} branches), "
            if report["method"] == "split"
            else f"({report['fitting_episodes']} fitting the proposal), "
        )
        + f"{report['events']} events, "
        f"ESS {report['ess']:.1f}, mean weight {report['mean_weight']:.3f}; Monte Carlo "
        f"would need {report['mc_equivalent_episodes']:.3g} episodes"
        + (
            ""
            if report["trusted"]
            else " (no event: no upper bound; run more episodes)"
            if report["events"] == 0
            else " (few effective events: not to be trusted)"
        )
    )
    if report.get("replay_mismatches"):
        print(
            f"warning: {report['replay_mismatches']} branches did not replay their trunk "
            "(the policy's answers depend on the batch): the estimate may be off",
            file=sys.stderr,
        )
    keys = ("rate", "ci95", "episodes", "ess", "mc_equivalent_episodes", "method")
    print(json.dumps({k: report[k] for k in keys}))
    return 0


def rampflow_cmd(args: argparse.Namespace) -> int:
    """Ramp flow: every ramp vehicle driven by one policy, the merge measured as a whole, one
    row per ramp demand; the last line printed is the JSON of all rows."""
    from marlmerge.config.presets import resolve_config
    from marlmerge.evaluation.ramp_flow import merge_line, parse_mix, run_ramp_flow

    if args.scenario is not None:
        base = resolve_config(args.scenario)
    else:  # the policy's own scenario (a learned one's training scenario; rules: the default)
        from marlmerge.evaluation.registry import policy_for_evaluation

        base = policy_for_evaluation(parse_mix(args.policy)[0][0], None)[1]
    if args.ramp_flow is None and not base.ramp.flowing:
        raise ValueError(
            f"--ramp-flow: scenario {base.name!r} has no ramp flow (ramp.flow_vph = 0); "
            "give the demand(s), e.g. --ramp-flow 600"
        )
    demands = [base.ramp.flow_vph] if args.ramp_flow is None else _demands(args.ramp_flow)
    if args.mainline_flow is not None:
        base = base.replace(**{"traffic.flow_vph_per_lane": args.mainline_flow})
    for spec, _ in parse_mix(args.policy):
        _note_bare_shield(spec)
    rows = []
    for vph in demands:
        cfg = base.replace(**{"ramp.flow_vph": vph})
        row = run_ramp_flow(cfg, args.policy, args.hours, args.worlds, args.seed, args.skip)
        rows.append(row.to_dict())
        print(
            f"ramp {vph:g} veh/h, mainline {row.mainline_demand_vph_per_lane:g} veh/h/lane: "
            + merge_line(rows[-1])
        )
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "report.json").write_text(json.dumps(rows, indent=1))
    print(json.dumps(rows))
    return 0


def _demands(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(
            f"--ramp-flow: expected numbers separated by commas, got {text!r}"
        ) from None
    bad = [v for v in values if not 0 < v <= 3600]
    if not values or bad:
        raise ValueError(f"--ramp-flow: each demand must be in (0, 3600] veh/h, got {text!r}")
    twice = [v for i, v in enumerate(values) if v in values[:i]]
    if twice:
        raise ValueError(f"--ramp-flow: the demand {twice[0]:g} is given twice in {text!r}")
    return values


def plot_cmd(args: argparse.Namespace) -> int:
    """Regenerate the paper's figures from a run's logs."""
    from marlmerge.training.plots import plot_run

    for p in plot_run(args.run):
        print(f"wrote {p}")
    return 0


def sweep_cmd(args: argparse.Namespace) -> int:
    """Train a preset over many seeds on a backend and summarise across seeds."""
    from marlmerge.training.sweep import parse_seeds, sweep

    seeds = parse_seeds(args.seeds)
    out = Path(args.out or f"runs/sweep_{Path(args.preset).stem}")
    summary = sweep(
        args.preset,
        seeds,
        out,
        _parse_sets(args.set),
        args.backend,
        args.workers,
        args.address,
        progress=not args.no_progress,
        vectorized=args.vectorized,
    )
    print((out / "summary.md").read_text())
    where = f"on the {args.backend} backend"
    groups = summary.get("groups")  # the seeds of each process of a vectorised sweep
    if groups is not None:
        where = "in one process" if len(groups) == 1 else f"in {len(groups)} processes"
        where += f" ({'; '.join(', '.join(map(str, g)) for g in groups)})"
    print(f"{len(seeds)} seeds {where}; runs in {out}/seed_*")
    return 0 if summary else 1


def render_cmd(args: argparse.Namespace) -> int:
    """Record greedy episodes of a policy as a video at the simulation rate."""
    from marlmerge.config.presets import resolve_config
    from marlmerge.evaluation.video import render_episodes

    cfg = resolve_config(args.scenario)
    path, n, outcomes = render_episodes(
        args.policy, cfg, args.out, args.episodes, args.seed, args.view, args.highway
    )
    print(f"wrote {path}: {n} frames at {1.0 / cfg.sim.dt_s:g} fps; outcomes {', '.join(outcomes)}")
    return 0


def validate_cmd(args: argparse.Namespace) -> int:
    """Run the validation scenarios in marlmerge and SUMO and write the report."""
    from marlmerge.config.presets import resolve_config
    from marlmerge.validation import sumo
    from marlmerge.validation.report import validate

    if args.sumo and not sumo.available():
        raise ValueError('--sumo: SUMO is not installed (pip install -e ".[sumo]")')
    use_sumo = True if args.sumo else (False if args.reference else None)
    if use_sumo is None and not sumo.available():
        print("SUMO is not installed: comparing against the committed SUMO reference outputs")
    if args.update_reference and not sumo.available():
        raise ValueError('--update-reference: SUMO is not installed (pip install -e ".[sumo]")')
    if args.merge:
        return _validate_merge(args, use_sumo is not False and sumo.available())
    result = validate(
        resolve_config(args.scenario), args.out, use_sumo, update_reference=args.update_reference
    )
    for name, c in result["car_following"].items():
        print(f"car following {name}: max position difference {c['max_pos_diff_m']:.1e} m")
    for flow, row in result["flow_sweep"].items():
        ratios = ", ".join(f"{k} {v['ratio']:.3f}" for k, v in row.items() if "ok" in v)
        print(f"flow {flow} veh/h/lane, marlmerge / SUMO: {ratios}")
    print(f"all targets met: {result['all_targets_met']}; wrote {args.out}/README.md")
    return 0 if result["all_targets_met"] else 1


def _validate_merge(args: argparse.Namespace, use_sumo: bool) -> int:
    from marlmerge.config.presets import resolve_config
    from marlmerge.validation.merge import validate_merge

    cfg = resolve_config(args.scenario)
    best, zipper = cfg.traffic.entrance_lane == "best", cfg.ramp.cooperation == "zipper"
    default_out = "docs/validation/merge" + "_best" * best + "_zipper" * zipper
    out = args.out if args.out != "docs/validation" else default_out
    result = validate_merge(cfg, out, use_sumo, update_reference=args.update_reference)
    from marlmerge.validation.merge import VARIANTS

    for name in VARIANTS:
        r = result[name]
        print(
            f"{name}: merged flow within 10 % of SUMO in {r['merged_within_10pct']} cells, "
            f"ramp delay in {r['delay_within_10pct']}, the entrance's share of the lane changes "
            f"within 2x in {r['entrance_share_within_2x']}"
        )
    print(f"wrote {out}/README.md")
    return 0 if result["all_targets_met"] else 1


def _backend_args(p: argparse.ArgumentParser) -> None:
    from marlmerge.evaluation.backends import BACKENDS

    p.add_argument(
        "--backend",
        choices=BACKENDS,
        default="process",
        help="serial, process (default: worker processes on every core) or ray",
    )
    p.add_argument("--workers", type=_at_least(1), default=None, help="processes / local Ray CPUs")
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster to join (e.g. auto after `ray start --head`); default: a local one",
    )


def _at_least(low: int) -> Callable[[str], int]:
    """argparse type: an integer >= `low` (argparse names the option in its error)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    return parse


def _add_train(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge train`."""
    t = sub.add_parser("train", help="train the ego (default: the paper's recipe)")
    t.add_argument(
        "preset",
        nargs="?",
        default=None,
        help="training preset in trainers/ or a .toml path (default: the built-in "
        "defaults, which are the paper's recipe)",
    )
    t.add_argument("--out", default=None, help="run folder (default runs/<name>)")
    t.add_argument("--resume", action="store_true", help="continue from the run's checkpoint")
    t.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a TrainConfig field, e.g. --set seed=1 (repeatable)",
    )
    t.add_argument(
        "--seeds",
        default=None,
        help="train these seeds in one process (e.g. 0-7 or 0,2,5) into OUT/seed_S, each "
        "bit for bit its own single run (on several cores, `sweep PRESET --seeds S "
        "--vectorized --workers N` splits them over N such processes, faster)",
    )
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    t.set_defaults(func=train_cmd)


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge evaluate`."""
    e = sub.add_parser("evaluate", help="evaluate a saved policy greedily")
    e.add_argument(
        "policy",
        help="hold, idm, gap, a run folder / policy.pt file, or one policy as the grid names it "
        "(gap@shield, quadq@shield:RUN)",
    )
    e.add_argument(
        "--episodes",
        type=_at_least(1),
        default=200,
        help="episodes; under ramp flow, about this many ramp vehicles",
    )
    e.add_argument("--seed", type=_at_least(0), default=1_000_000, help="first held-out road seed")
    e.add_argument("--worlds", type=_at_least(1), default=50, help="episodes run in parallel")
    e.add_argument("--scenario", default=None, help="evaluate on another scenario preset")
    e.add_argument(
        "--highway",
        default=None,
        help="a saved highway policy (run folder or highway_policy.pt) driving the highway "
        "agents, or a scripted driver: 'edge' (at a plausible envelope's edge) or 'pace' "
        "(keeps beside the ramp vehicle)",
    )
    e.add_argument(
        "--fairness",
        action="store_true",
        help="with --highway: gap acceptance drives the same roads too; the ego's failures it "
        "does not share are the highway policy's fair finds",
    )
    e.set_defaults(func=evaluate_cmd)


def _add_cotrain(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge cotrain`."""
    c = sub.add_parser("cotrain", help="co-train learned highway agents and the ego")
    c.add_argument("preset", help="co-training preset in trainers/ (e.g. cotrain) or a .toml path")
    c.add_argument("--out", default=None, help="run folder (default runs/<name>)")
    c.add_argument("--resume", action="store_true", help="continue from the run's checkpoint")
    c.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a CoTrainConfig field, e.g. --set seed=1 (repeatable)",
    )
    c.add_argument(
        "--seeds",
        default=None,
        help="co-train these seeds in one process (e.g. 0-3 or 0,2,5) into OUT/seed_S, each "
        "bit for bit its own single run",
    )
    c.add_argument("--no-progress", action="store_true", help="no progress bar")
    c.set_defaults(func=cotrain_cmd)


def _add_grid(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge grid`."""
    g = sub.add_parser("grid", help="robustness grid: policies x traffic conditions")
    g.add_argument(
        "--policy",
        action="append",
        metavar="SPEC",
        help="hold, idm, gap, or [label=]quadq|dqn|td3:RUN_GLOB; @filter / @nofilter after the "
        "kind turns the safety filter on / off (gap@filter), @shield puts the policy behind gap "
        "acceptance's judgement (quadq@shield:runs/x_s*), @shield-left behind the shield that "
        "also watches the left lane (gap@shield-left) (repeatable; default: the three rules)",
    )
    g.add_argument(
        "--condition",
        action="append",
        metavar="SPEC",
        help="scenario preset (a glob such as 'grid_*' expands to presets), or "
        "[label=]PRESET+highway:RUN_GLOB for learned highway agents (repeatable; default: every "
        "envs/grid_*.toml)",
    )
    g.add_argument("--episodes", type=_at_least(1), default=30, help="episodes per condition")
    g.add_argument("--seed", type=_at_least(0), default=2_000_000, help="first evaluation seed")
    g.add_argument("--worlds", type=_at_least(1), default=50, help="episodes run in parallel")
    g.add_argument("--out", default="runs/grid")
    g.add_argument(
        "--ramp-hours",
        type=float,
        default=0.25,
        help="conditions with ramp flow: simulated hours per world",
    )
    g.add_argument(
        "--ramp-worlds", type=_at_least(1), default=4, help="conditions with ramp flow: worlds"
    )
    g.add_argument("--no-progress", action="store_true")
    g.add_argument(
        "--estimator",
        choices=("mc", "is"),
        default="mc",
        help="is: add each cell's importance-sampled collision rate to summary.md "
        "(scripted traffic; see marlmerge estimate)",
    )
    _backend_args(g)
    g.set_defaults(func=grid_cmd)


def _add_stress(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge stress`."""
    st = sub.add_parser("stress", help="search the traffic space for where a policy fails")
    st.add_argument("policy", help="hold, idm, gap, KIND:RUN (one run) or a run folder")
    st.add_argument("--scenario", default="default", help="the traffic the space varies")
    st.add_argument("--seed", type=_at_least(0), default=0)
    st.add_argument("--points", type=_at_least(1), default=512, help="conditions per round")
    st.add_argument("--episodes-per-point", type=_at_least(1), default=4)
    st.add_argument("--regions", type=_at_least(1), default=8, help="regions to look for")
    st.add_argument("--rounds", type=_at_least(1), default=4, help="focusing rounds per region")
    st.add_argument("--box", type=float, default=0.05, help="a region's half-width (unit cube)")
    st.add_argument("--verify-episodes", type=_at_least(1), default=200)
    st.add_argument("--worlds", type=_at_least(1), default=512, help="worlds stepped at once")
    st.add_argument("--budget-s", type=float, default=600.0, help="no new region after 80 %%")
    st.add_argument("--out", default="runs/stress")
    st.add_argument("--no-clip", action="store_true", help="no video of the first failures")
    st.set_defaults(func=stress_cmd)


def _add_estimate(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge estimate`."""
    es = sub.add_parser("estimate", help="a policy's collision rate, with rare-event sampling")
    es.add_argument("policy", help="as evaluate takes it: hold, idm, gap, a run, gap@shield, ...")
    es.add_argument("--scenario", default=None, help="the traffic (default: the policy's own)")
    es.add_argument(
        "--method",
        choices=("is", "mc", "split"),
        default="is",
        help="is: importance sampling; mc: plain Monte Carlo; split: branch at the attention "
        "lapses that could close the ego's gap (scenarios with driver.lapse_rate_per_h > 0)",
    )
    es.add_argument("--event", choices=("collision", "failure"), default="collision")
    es.add_argument(
        "--rel-ci",
        type=float,
        default=None,
        help="stop when the 95 %% half-width <= this x rate (default 0.2 unless --episodes)",
    )
    es.add_argument(
        "--episodes",
        type=_at_least(1),
        default=None,
        help="final episodes instead (split: trunks, each with its branches)",
    )
    es.add_argument(
        "--max-episodes", type=_at_least(1), default=None, help="with --rel-ci (default 2,000,000)"
    )
    es.add_argument("--seed", type=_at_least(0), default=0)
    es.add_argument("--worlds", type=_at_least(1), default=500, help="episodes run at once")
    es.add_argument("--batch", type=_at_least(1), default=5000, help="episodes per batch")
    es.add_argument(
        "--rounds", type=_at_least(1), default=None, help="is: cross-entropy rounds at most (8)"
    )
    es.add_argument(
        "--round-episodes", type=_at_least(1), default=None, help="is: episodes per round (2,000)"
    )
    es.add_argument("--out", default="runs/estimate", help="batches and report.json (resumable)")
    es.set_defaults(func=estimate_cmd)


def _add_rampflow(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge rampflow`."""
    rf = sub.add_parser("rampflow", help="ramp flow: many merging vehicles, the merge measured")
    rf.add_argument(
        "policy",
        help="drives every ramp vehicle: hold, idm, gap, a run folder; or a mix, gap=0.5,RUN=0.5",
    )
    rf.add_argument(
        "--scenario", default=None, help="the traffic (default: the policy's own; rules: default)"
    )
    rf.add_argument(
        "--ramp-flow",
        default=None,
        help="ramp demand(s), veh/h, e.g. 200,600,1000 (a curve); default: the scenario's",
    )
    rf.add_argument(
        "--mainline-flow", type=float, default=None, help="veh/h/lane (default: scenario's)"
    )
    rf.add_argument("--hours", type=float, default=1.0, help="measured simulated time per world")
    rf.add_argument("--skip", type=float, default=300.0, help="settling time before counting, s")
    rf.add_argument("--worlds", type=_at_least(1), default=4)
    rf.add_argument("--seed", type=_at_least(0), default=0)
    rf.add_argument("--out", default=None, help="also write report.json here")
    rf.set_defaults(func=rampflow_cmd)


def _add_plot(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge plot`."""
    pl = sub.add_parser("plot", help="regenerate the loss and reward figures of a run")
    pl.add_argument("run", help="run folder")
    pl.set_defaults(func=plot_cmd)


def _add_simulate(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge simulate`."""
    s = sub.add_parser("simulate", help="drive ramp vehicles through scripted traffic")
    s.add_argument("--scenario", default="default", help="preset name in envs/ or a .toml path")
    s.add_argument("--episodes", type=_at_least(1), default=20)
    s.add_argument("--seed", type=_at_least(0), default=0)
    s.add_argument(
        "--ego",
        choices=("hold", "idm", "random"),
        default="hold",
        help="hold: keep speed; idm: plain car following that ignores the merge; "
        "random: uniform accelerations",
    )
    s.add_argument("--out", default="runs/simulate", help="output folder")
    s.set_defaults(func=simulate)


def _add_sweep(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge sweep`."""
    w = sub.add_parser("sweep", help="train a preset over many seeds, summarise across seeds")
    w.add_argument("preset", help="training preset in trainers/ (or a .toml path)")
    w.add_argument("--seeds", default="0-4", help="e.g. 0-9, 0,2,5 or 0-3,10-12 (default 0-4)")
    w.add_argument("--out", default=None, help="sweep folder (default runs/sweep_<preset>)")
    w.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a field"
    )
    w.add_argument("--no-progress", action="store_true")
    w.add_argument(
        "--vectorized",
        action="store_true",
        help="train all seeds in this process, updated together (train recipes; "
        "each seed bit for bit its own run)",
    )
    _backend_args(w)
    w.set_defaults(func=sweep_cmd)


def _add_render(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge render`."""
    r = sub.add_parser("render", help="record greedy episodes as a video (.mp4 or .gif)")
    r.add_argument("policy", help="as evaluate takes it: hold, idm, gap, a run, gap@shield, ...")
    r.add_argument("--scenario", default="default", help="preset name in envs/ or a .toml path")
    r.add_argument("--episodes", type=_at_least(1), default=1)
    r.add_argument(
        "--seed", type=_at_least(0), default=1_000_000, help="first road seed (held-out)"
    )
    r.add_argument("--view", choices=("merge", "follow"), default="merge")
    r.add_argument(
        "--highway", default=None, help="a saved highway policy driving the agents, edge or pace"
    )
    r.add_argument("--out", default="runs/episode.mp4", help="video file (.mp4 or .gif)")
    r.set_defaults(func=render_cmd)


def _add_validate(sub: argparse._SubParsersAction) -> None:
    """The arguments of `marlmerge validate`."""
    v = sub.add_parser("validate", help="compare the simulator with SUMO, write docs/validation")
    v.add_argument("--scenario", default="default", help="preset name in envs/ or a .toml path")
    v.add_argument("--out", default="docs/validation", help="report folder")
    mode = v.add_mutually_exclusive_group()
    mode.add_argument("--sumo", action="store_true", help="require SUMO (default: if installed)")
    mode.add_argument(
        "--reference", action="store_true", help="use the committed SUMO outputs even if installed"
    )
    v.add_argument(
        "--update-reference",
        action="store_true",
        help="with SUMO: also replace the shipped SUMO reference (marlmerge/validation/reference)",
    )
    v.add_argument(
        "--merge",
        action="store_true",
        help="merge capacity and ramp delay under ramp flow (report: docs/validation/merge)",
    )
    v.set_defaults(func=validate_cmd)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="marlmerge", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    _add_train(sub)
    _add_evaluate(sub)
    _add_cotrain(sub)
    _add_grid(sub)
    _add_stress(sub)
    _add_estimate(sub)
    _add_rampflow(sub)
    _add_plot(sub)
    _add_simulate(sub)
    _add_sweep(sub)
    _add_render(sub)
    _add_validate(sub)
    return p


def check_out(out: str | None, is_file: bool = False) -> None:
    """`--out` that cannot be written is refused before any work starts: the folder (for a
    file, its folder) or its nearest existing ancestor must be a writable folder."""
    if out is None:
        return
    path = Path(out)
    if not is_file and path.exists() and not path.is_dir():
        raise ValueError(f"--out {out!r}: exists and is not a folder")
    ancestor = path.parent if is_file else path
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise ValueError(f"--out {out!r}: {str(ancestor)!r} is not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise ValueError(f"--out {out!r}: {str(ancestor)!r} is not writable")


def main(argv: list[str] | None = None) -> int:
    # torchrl logs INFO lines (buffer set-up, ...) in colour; a command prints its own progress
    os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")
    args = build_parser().parse_args(argv)
    try:
        check_out(getattr(args, "out", None), is_file=args.command == "render")
        return args.func(args)
    except ValueError as err:
        print(f"marlmerge: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
