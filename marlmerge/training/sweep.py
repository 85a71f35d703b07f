"""`marlmerge sweep`: one training recipe over many seeds, on any backend, with a summary.

    marlmerge sweep paper --seeds 0-9 --backend process --out runs/sweep_paper

Each seed is one task (`marlmerge.evaluation.backends`; one CPU, one thread): it trains the preset
with `seed = S` into `OUT/seed_S` (a normal run folder: `policy.pt`, logs, checkpoints) and
evaluates the greedy policy on the preset's held-out roads (`eval_episodes` from `eval_seed`: the
same roads for every seed). A sweep run again skips finished seeds and resumes interrupted ones from
their checkpoints. `OUT/summary.md` and `summary.json` give, for every evaluation measure, the
mean over seeds, the spread (standard deviation), a 95 % interval of the mean (Student t) and
the worst seed. The run folders are ordinary: `marlmerge grid --policy "quadq:OUT/seed_*"` and
`--set ego_init=OUT/seed_S/policy.pt` for co-training read them as they are.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from marlmerge.evaluation.backends import check_backend, run_tasks
from marlmerge.io.files import write_text

MEASURES = (
    ("success_rate", True, (0.0, 1.0)),
    ("collision_rate", False, (0.0, 1.0)),
    ("truncation_rate", False, (0.0, 1.0)),
    ("mean_merge_time_s", False, (0.0, math.inf)),
    ("mean_abs_accel_mps2", False, (0.0, math.inf)),
)
"""Evaluation measures summarised: name, whether higher is better (for the worst seed) and the
values it can take (its interval is cut to them: a t interval of few seeds reaches past them,
e.g. below a rate of 0)."""
# two-sided 95 % Student t quantiles for 1..30 degrees of freedom (normal beyond)
_T95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179,
        2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064,
        2.060, 2.056, 2.052, 2.048, 2.045, 2.042)  # fmt: skip


MAX_SEEDS = 10_000
"""Seeds one `--seeds` spec may name (a range is checked before it is expanded)."""


def parse_seeds(text: str) -> list[int]:
    """`0-9`, `3`, `0,2,5` or `0-3,10-12` -> the seeds, each once, in order (at most
    `MAX_SEEDS`)."""
    seeds: list[int] = []
    for part in text.split(","):
        seeds += _seed_part(part.strip(), text, MAX_SEEDS - len(seeds))
    if not seeds or min(seeds) < 0:
        raise ValueError(f"--seeds: need one or more seeds >= 0, got {text!r}")
    return list(dict.fromkeys(seeds))


def _seed_part(part: str, text: str, room: int) -> list[int]:
    """One comma-separated part of the `--seeds` spec `text`, N or LO-HI; a range is checked
    against the `room` left before it is expanded."""
    lo, dash, hi = part.partition("-")
    try:
        first, last = int(lo), int(hi if dash else lo)
    except ValueError:
        raise ValueError(f"--seeds: expected e.g. 0-9 or 0,2,5, got {text!r}") from None
    if last < first:
        raise ValueError(f"--seeds: the range {part!r} in {text!r} is empty")
    if last - first + 1 > room:
        raise ValueError(f"--seeds: {text!r} names more than {MAX_SEEDS:,} seeds")
    return list(range(first, last + 1))


@dataclass(frozen=True)
class SeedTask:
    kind: str
    preset: str
    overrides: tuple[tuple[str, Any], ...]
    seed: int
    out_dir: str


def _load(task: SeedTask):  # noqa: ANN202 - a TrainConfig or a CoTrainConfig
    kw = dict(task.overrides, seed=task.seed)
    if task.kind == "train":
        from marlmerge.training.train import load_train_config

        return load_train_config(task.preset, **kw)
    from marlmerge.training.cotrain import load_cotrain_config

    return load_cotrain_config(task.preset, **kw)


def run_seed(task: SeedTask) -> dict[str, Any]:
    """Train (or resume, or reuse) one seed; returns its evaluation (the scripted-traffic
    evaluation of a co-training run)."""
    out = Path(task.out_dir)
    done = out / "evaluation.json"
    if not done.exists():
        cfg = _load(task)
        resume = (out / "checkpoint.pt").exists()
        if task.kind == "train":
            from marlmerge.training.train import train

            train(cfg, out, resume=resume, progress=False)
        else:
            from marlmerge.training.cotrain import cotrain

            cotrain(cfg, out, resume=resume, progress=False)
    if not done.exists():
        raise ValueError(f"{out}: the run wrote no evaluation.json (eval_episodes = 0?)")
    return scripted_evaluation(out)


def scripted_evaluation(folder: Path) -> dict[str, Any]:
    """A run folder's evaluation: a co-training run's against scripted traffic."""
    evaluation = json.loads((folder / "evaluation.json").read_text())
    return evaluation.get("scripted", evaluation)


def interval95(values: np.ndarray) -> tuple[float, float]:
    """95 % interval of the mean (Student t); (nan, nan) for fewer than two values."""
    n = values.size
    if n < 2:
        return math.nan, math.nan
    t = _T95[n - 2] if n - 2 < len(_T95) else 1.96
    half = t * float(values.std(ddof=1)) / math.sqrt(n)
    return float(values.mean()) - half, float(values.mean()) + half


def summarize(evaluations: dict[int, dict[str, Any]]) -> dict[str, Any]:
    """Per measure: mean, std, 95 % interval and the worst seed over the seeds."""
    seeds = sorted(evaluations)
    out: dict[str, Any] = {"seeds": seeds, "per_seed": {str(s): evaluations[s] for s in seeds}}
    for name, higher_better, (low, high) in MEASURES:
        v = np.array([float(evaluations[s].get(name, math.nan)) for s in seeds])
        ok = np.isfinite(v)
        if not ok.any():
            continue
        worst_i = int(np.argmin(np.where(ok, v, np.inf)) if higher_better else np.argmax(
            np.where(ok, v, -np.inf)
        ))  # fmt: skip
        lo, hi = interval95(v[ok])
        lo, hi = (lo, hi) if math.isnan(lo) else (max(lo, low), min(hi, high))
        out[name] = {
            "mean": float(v[ok].mean()),
            "std": float(v[ok].std(ddof=1)) if ok.sum() > 1 else 0.0,
            "ci95": [lo, hi],
            "worst_seed": seeds[worst_i],
            "worst": float(v[worst_i]),
        }
    return out


def summary_markdown(summary: dict[str, Any], preset: str, backend: str, wall_s: float) -> str:
    seeds = summary["seeds"]
    lines = [
        f"# Sweep of `{preset}` over {len(seeds)} seeds",
        "",
        f"Seeds {', '.join(map(str, seeds))}; each evaluated greedily on the preset's held-out "
        f"roads. {backend} backend, {wall_s:.0f} s for the seeds run here.",
        "",
        "| measure | mean | std | 95 % interval of the mean | worst seed |",
        "|---|---|---|---|---|",
    ]
    for name, _, _ in MEASURES:
        if name in summary:
            m = summary[name]
            lo, hi = m["ci95"]
            lines.append(
                f"| {name} | {m['mean']:.4g} | {m['std']:.3g} | {lo:.4g} – {hi:.4g} | "
                f"{m['worst']:.4g} (seed {m['worst_seed']}) |"
            )
    lines += ["", "| seed | " + " | ".join(n for n, _, _ in MEASURES) + " |"]
    lines.append("|---" * (len(MEASURES) + 1) + "|")
    for s in seeds:
        ev = summary["per_seed"][str(s)]
        cells = [f"{float(ev.get(n, math.nan)):.4g}" for n, _, _ in MEASURES]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def sweep(
    preset: str,
    seeds: list[int],
    out_dir: str | Path,
    overrides: dict[str, Any] | None = None,
    backend: str = "process",
    workers: int | None = None,
    address: str | None = None,
    progress: bool = True,
    vectorized: bool = False,
) -> dict[str, Any]:
    """Train `preset` once per seed on `backend` and summarise; see the module docstring. The
    preset's `kind` says whether it is a `train` or a `cotrain` recipe. `vectorized`: all seeds
    in one process per worker (`marlmerge.training.seeds`, `cotrain_seeds`), not one task
    each."""
    import time

    from marlmerge.config.presets import preset_kind

    kind = preset_kind(preset)
    check_backend(backend, workers, address)
    overrides = dict(overrides or {})
    if "seed" in overrides:
        raise ValueError("sweep: give the seeds with --seeds, not --set seed=...")
    out = Path(out_dir)
    if vectorized:
        t0 = time.perf_counter()
        groups = seed_groups(seeds, backend, workers)
        sets = tuple(sorted(overrides.items()))
        tasks_v = [GroupTask(kind, str(preset), sets, g, str(out)) for g in groups]
        check_group_tasks(tasks_v)
        runs = run_tasks(run_group, tasks_v, backend, None, workers, address)
        results = [ev for group in runs for ev in group]
        where = f"{backend} (vectorized: {len(groups)} group{'s' * (len(groups) > 1)})"
        return _write_summary(out, seeds, results, str(preset), kind, where, t0, groups)
    tasks = [
        SeedTask(kind, str(preset), tuple(sorted(overrides.items())), s, str(out / f"seed_{s}"))
        for s in seeds
    ]
    first = _load(tasks[0])  # a bad preset or override fails here, before any work starts
    if kind == "train" and backend != "ray":  # Ray's workers may have devices this host lacks
        from marlmerge.learners.common import resolve_device

        resolve_device(first.device)
    out.mkdir(parents=True, exist_ok=True)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(tasks), unit="seed", desc=f"sweep ({backend})", dynamic_ncols=True)
    t0 = time.perf_counter()
    results = run_tasks(
        run_seed,
        tasks,
        backend,
        (lambda i, r: bar.update(1)) if bar is not None else None,
        workers,
        address,
    )
    if bar is not None:
        bar.close()
    return _write_summary(out, seeds, results, str(preset), kind, backend, t0)


def _write_summary(
    out: Path, seeds: list[int], results: list[dict], preset: str, kind: str, backend: str,
    t0: float, groups: list[list[int]] | None = None,
) -> dict[str, Any]:  # fmt: skip
    """summary.json and summary.md; `groups`: the seeds of each process of a vectorised sweep
    (one process per seed otherwise)."""
    import time

    wall = time.perf_counter() - t0
    summary = summarize(dict(zip(seeds, results, strict=True)))
    summary.update(preset=preset, kind=kind, backend=backend, wall_s=wall)
    if groups is not None:
        summary["groups"] = groups
    write_text(out / "summary.json", json.dumps(summary, indent=1))
    (out / "summary.md").write_text(summary_markdown(summary, preset, backend, wall))
    return summary


@dataclass(frozen=True)
class GroupTask:
    """Seeds trained together in one process (`train_seeds` or `cotrain_seeds`, by the
    recipe's `kind`), one task of a vectorised sweep."""

    kind: str
    preset: str
    overrides: tuple[tuple[str, Any], ...]
    seeds: list[int]
    out_dir: str

    @property
    def checkpoint_name(self) -> str:
        return f"seeds_checkpoint_{'_'.join(map(str, self.seeds))}.pt"


def seed_groups(seeds: list[int], backend: str, workers: int | None) -> list[list[int]]:
    """The seeds split into one group per worker (consecutive, sizes differing by one at most):
    all in one group on the serial backend."""
    import os

    n = 1 if backend == "serial" else min(len(seeds), workers or os.cpu_count() or 1)
    size, extra = divmod(len(seeds), n)
    groups, start = [], 0
    for g in range(n):
        end = start + size + (g < extra)
        groups.append(seeds[start:end])
        start = end
    return groups


def check_group_tasks(tasks: list[GroupTask]) -> None:
    """Before any work: the recipe loads and can be vectorised, and the sweep folder holds no
    run that these groups would not continue (single runs, or other groups)."""
    from marlmerge.training.seeds import check_seeds

    out = Path(tasks[0].out_dir)
    first = tasks[0]
    cfg = _load(SeedTask(first.kind, first.preset, first.overrides, first.seeds[0], ""))
    if first.kind == "train":
        check_seeds(cfg, [s for t in tasks for s in t.seeds])
    single = [s for t in tasks for s in t.seeds if (out / f"seed_{s}" / "checkpoint.pt").exists()]
    if single:
        raise ValueError(
            f"sweep --vectorized: {out} holds single runs of seeds {single} (a sweep without "
            "--vectorized): finish it as it started, or use another --out"
        )
    mine = {t.checkpoint_name for t in tasks}
    other = sorted(p.name for p in out.glob("seeds_checkpoint_*.pt") if p.name not in mine)
    if other:
        raise ValueError(
            f"sweep --vectorized: {out} holds seed groups {other}, not these: run it again with "
            "the seeds and --workers it started with, or use another --out"
        )


def run_group(task: GroupTask) -> list[dict[str, Any]]:
    """Train (or resume, or reuse) one group of seeds in this process; returns each seed's
    evaluation."""
    from marlmerge.training.cotrain import cotrain_seeds
    from marlmerge.training.seeds import train_seeds

    out = Path(task.out_dir)
    cfg = _load(SeedTask(task.kind, task.preset, task.overrides, task.seeds[0], ""))
    resume = (out / task.checkpoint_name).exists()
    run = train_seeds if task.kind == "train" else cotrain_seeds
    results = run(
        cfg,  # type: ignore[arg-type]
        task.seeds,
        out,
        resume=resume,
        progress=False,
        checkpoint_name=task.checkpoint_name,
    )
    missing = [s for s, r in zip(task.seeds, results, strict=True) if r.evaluation is None]
    if missing:
        raise ValueError(f"{out}: seeds {missing} wrote no evaluation (eval_episodes = 0?)")
    return [scripted_evaluation(out / f"seed_{s}") for s in task.seeds]
