"""Regenerate every result the repository reports, from the manifest `docs/regenerate.toml`.

When the simulator changes, every number in the README and `docs/` changes with it. The
manifest lists each command that remakes one of them (the trainings first, then the grids,
evaluations and benchmarks that read them), with the steps it needs, the files it leaves, how
many cores it uses and how long it takes on the 2-core reference machine. This script runs them
in order:

- **Resumable.** A finished step leaves a marker `STATE/done/NAME` holding the hash of its
  command; a rerun skips it while the command is unchanged and its outputs exist, so a killed
  regeneration continues where it stopped. `--state` names the round (default
  `runs/regenerate`): a new round starts from nothing.
- **Fresh folders.** Before a step runs, the folders in its `fresh` (under `runs/` only) are
  deleted, so a training never meets a folder from an earlier round.
- **Side by side.** `--jobs 2` runs steps whose needs are done two at a time while their
  `cores` fit (two one-thread trainings; a grid alone), as the docs' times were measured.
- **One machine.** A learned run's bits depend on the CPU that trains it (the kernels torch
  compiles for it), so a round records its machine in `STATE/machine.json` and refuses to go on
  elsewhere, naming what differs.
- **Logged.** Each step's output goes to `STATE/logs/NAME.log`, its wall time to
  `STATE/times.jsonl`. A failed step is named with its log; what needs it is not run, the rest
  goes on (a round of many hours does not stop at one missing extra, such as libsumo).

    python benchmarks/regenerate.py --dry-run                 # the plan and its time
    python benchmarks/regenerate.py --jobs 2                  # everything (hours)
    python benchmarks/regenerate.py --only "paper_*" --only report_grid   # these and their needs
    python benchmarks/regenerate.py --from hardened   # it, what reads it, and their needs

The last line printed is JSON: `run`, `skipped`, `failed`, `not_run` (step names), `wall_s`.
"""

from __future__ import annotations

import argparse
import fnmatch
import hashlib
import json
import os
import platform
import re
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from marlmerge.config import from_dict, read_toml

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "docs" / "regenerate.toml"
STEP_KEYS = {"name", "run", "needs", "fresh", "outputs", "cores", "minutes", "reports"}
NAME = re.compile(r"[a-z0-9_]+")


@dataclass(frozen=True)
class Step:
    """One command of the manifest (see the module docstring for the keys)."""

    name: str
    run: str
    needs: tuple[str, ...]
    fresh: tuple[str, ...]
    outputs: tuple[str, ...]
    cores: int
    minutes: float
    reports: tuple[str, ...]

    @property
    def digest(self) -> str:
        """What the done marker holds: a step whose command changed runs again."""
        return hashlib.sha256(self.run.encode()).hexdigest()[:16]


def _step(i: int, raw: dict) -> Step:
    """Step number `i` of the manifest: every key present, typed by the project's strict
    config loading (`from_dict`), its values checked."""
    where = f"step {i + 1} ({raw.get('name', '?')!r})"
    unknown, missing = set(raw) - STEP_KEYS, STEP_KEYS - set(raw)
    if unknown or missing:
        raise ValueError(f"{where}: unknown keys {sorted(unknown)}, missing {sorted(missing)}")
    step = from_dict(Step, raw, _prefix=f"{where}: ")
    if not NAME.fullmatch(step.name):
        raise ValueError(f"{where}: name must match [a-z0-9_]+, got {step.name!r}")
    if step.cores not in (1, 2):
        raise ValueError(f"{where}: cores must be 1 or 2, got {step.cores!r}")
    if step.minutes <= 0:
        raise ValueError(f"{where}: minutes must be a positive number, got {step.minutes!r}")
    if not step.run.strip():
        raise ValueError(f"{where}: run must be a command, got {step.run!r}")
    for path in step.fresh:
        if not path.startswith("runs/") or ".." in Path(path).parts or path.rstrip("/") == "runs":
            raise ValueError(f"{where}: fresh {path!r} is not a folder under runs/")
    return step


def load_manifest(path: Path = MANIFEST) -> list[Step]:
    """The steps of a manifest, in its order, refused with a message naming the step where a key
    is wrong, a name repeats, a need is unknown or comes later, or two steps write one output."""
    data = read_toml(path)
    if set(data) != {"version", "step"} or data["version"] != 1:
        raise ValueError(f"{path}: need `version = 1` and [[step]] tables only, got {sorted(data)}")
    steps, seen, owner = [], set(), {}
    for i, raw in enumerate(data["step"]):
        step = _step(i, raw)
        if step.name in seen:
            raise ValueError(f"{path}: step name {step.name!r} appears twice")
        for need in step.needs:
            if need not in seen:
                raise ValueError(f"{path}: step {step.name!r} needs {need!r}, not an earlier step")
        for out in step.outputs:
            if out in owner:
                raise ValueError(f"{path}: {out!r} is written by {owner[out]!r} and {step.name!r}")
            owner[out] = step.name
        seen.add(step.name)
        steps.append(step)
    return steps


def _matching(steps: list[Step], patterns: list[str], option: str) -> set[str]:
    """The names of the steps matching any pattern (fnmatch); one that matches none is an error."""
    names: set[str] = set()
    for pat in patterns:
        hits = [s.name for s in steps if fnmatch.fnmatchcase(s.name, pat)]
        if not hits:
            raise ValueError(f"{option} {pat!r}: no step of the manifest matches")
        names.update(hits)
    return names


def select(steps: list[Step], patterns: list[str], since: Sequence[str] = ()) -> list[Step]:
    """The steps matching any pattern of `patterns` (`--only`), those matching `since`
    (`--from`) and every step that reads them, directly or not, then everything all of these
    need, in the manifest's order; all steps without patterns. A pattern that matches nothing
    is an error."""
    if not patterns and not since:
        return steps
    by_name = {s.name: s for s in steps}
    wanted = _matching(steps, patterns, "--only")
    changed = _matching(steps, list(since), "--from")
    grew = True
    while grew:  # every step that reads a changed one, directly or not
        readers = {s.name for s in steps if changed.intersection(s.needs)} - changed
        changed |= readers
        grew = bool(readers)
    wanted |= changed
    todo = list(wanted)
    while todo:
        for need in by_name[todo.pop()].needs:
            if need not in wanted:
                wanted.add(need)
                todo.append(need)
    return [s for s in steps if s.name in wanted]


def command_lines(script: str) -> list[list[str]]:
    """The script's simple commands as words (continuation lines joined, `&&`, `;` and `|`
    split), for the checks; lines that are not plain words (heredocs, ...) are left out."""
    joined = re.sub(r"\\\n", " ", script)
    out = []
    for line in joined.splitlines():
        for part in re.split(r"&&|\|\||;|\|", line):
            try:
                words = shlex.split(part, comments=True)
            except ValueError:
                continue
            while words and words[0] in ("do", "then", "else", "time"):
                words = words[1:]
            if words:
                out.append(words)
    return out


def check_step(step: Step, root: Path = ROOT) -> list[str]:
    """What is wrong with a step's command without running it: bash syntax, `marlmerge`
    commands its parser refuses, training presets and scripts that do not exist."""
    from marlmerge.cli import build_parser

    problems = []
    syntax = subprocess.run(["bash", "-n", "-c", step.run], capture_output=True, text=True)
    if syntax.returncode:
        problems.append(f"bash: {syntax.stderr.strip()}")
    for words in command_lines(step.run):
        if words[0] == "marlmerge":
            try:
                args = build_parser().parse_args(words[1:])
            except SystemExit:
                problems.append(f"marlmerge refuses: {shlex.join(words)}")
                continue
            preset = getattr(args, "preset", None)
            if args.command in ("train", "cotrain") and preset and "/" not in preset:
                if not (root / "trainers" / f"{preset}.toml").exists():
                    problems.append(f"no preset trainers/{preset}.toml: {shlex.join(words)}")
        elif words[0] in ("python", "python3") and len(words) > 1 and words[1].endswith(".py"):
            if not (root / words[1]).exists():
                problems.append(f"no script {words[1]}")
    return [f"step {step.name!r}: {p}" for p in problems]


def machine() -> dict[str, str]:
    """What a learned run's bits depend on besides the code: the CPU and the kernels torch
    picks for it (its vector width, MKL's code path), and the versions."""
    import numba
    import torch
    from torch._inductor.cpu_vec_isa import pick_vec_isa

    model = next(
        (line.split(":", 1)[1].strip() for line in _cpuinfo() if line.startswith("model name")),
        platform.processor(),
    )
    return {
        "cpu": model, "cores": str(len(os.sched_getaffinity(0))), "arch": platform.machine(),
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "compiled_isa": str(pick_vec_isa()), "torch": torch.__version__,
        "numba": numba.__version__, "python": platform.python_version(),
    }  # fmt: skip


def _cpuinfo() -> list[str]:
    try:
        return Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:  # pragma: no cover - not Linux
        return []


class Round:
    """The state of one regeneration round: done markers, logs and times under `state`, and
    the machine it runs on (`machine.json`)."""

    def __init__(self, root: Path, state: Path) -> None:
        self.root, self.state = root, state

    def check_machine(self, here: dict[str, str]) -> None:
        """Record the machine a new round runs on; refuse to continue one started on another:
        learned runs differ in their bits from machine to machine, and a round's results must
        come from one."""
        path = self.state / "machine.json"
        if not path.exists():
            self.state.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(here, indent=1) + "\n")
            return
        then = json.loads(path.read_text())
        diff = {k: (then.get(k), here.get(k)) for k in then.keys() | here.keys()}
        diff = {k: v for k, v in diff.items() if v[0] != v[1]}
        if diff:
            shown = "; ".join(f"{k}: {a!r} then, {b!r} here" for k, (a, b) in sorted(diff.items()))
            raise SystemExit(
                f"{self.state} is a round started on another machine ({shown}): learned runs "
                "differ by machine, so a round runs on one; start a new one with --state"
            )

    def done(self, step: Step) -> bool:
        """Finished in this round with the same command, its outputs still there."""
        marker = self.state / "done" / step.name
        if not marker.exists() or marker.read_text().strip() != step.digest:
            return False
        return all((self.root / out).exists() for out in step.outputs)

    def start(self, step: Step) -> subprocess.Popen:
        """Clear the step's fresh folders and start its command, logging to its log file."""
        for sub in ("done", "logs"):
            (self.state / sub).mkdir(parents=True, exist_ok=True)
        (self.state / "done" / step.name).unlink(missing_ok=True)
        for folder in step.fresh:
            target = self.root / folder
            if target.is_symlink() or target.is_file():
                target.unlink()
            elif target.exists():
                shutil.rmtree(target)
        with open(self.state / "logs" / f"{step.name}.log", "w") as log:  # the child keeps a copy
            return subprocess.Popen(
                ["bash", "-c", "set -euo pipefail\n" + step.run],
                cwd=self.root, stdout=log, stderr=subprocess.STDOUT,
            )  # fmt: skip

    def finish(self, step: Step, rc: int, wall_s: float) -> str | None:
        """Record a step that ended; returns why it failed, or None."""
        missing = [o for o in step.outputs if not (self.root / o).exists()]
        why = f"exit status {rc}" if rc else (f"outputs missing: {missing}" if missing else None)
        with open(self.state / "times.jsonl", "a") as f:
            row = {"step": step.name, "wall_s": round(wall_s, 1), "minutes_stated": step.minutes}
            f.write(json.dumps({**row, "ok": why is None}) + "\n")
        if why is None:
            (self.state / "done" / step.name).write_text(step.digest + "\n")
        return why


def plan_minutes(steps: list[Step], jobs: int) -> float:
    """Wall minutes of `steps` with `jobs` cores, as the docs' times add up: one-core steps
    share the cores, the others take them all."""
    one = sum(s.minutes for s in steps if s.cores == 1 or jobs == 1)
    rest = sum(s.minutes for s in steps if s.cores > 1 and jobs > 1)
    return one / jobs + rest


def run_round(rnd: Round, steps: list[Step], jobs: int, force: bool) -> dict:
    """Run the steps not done yet, up to `jobs` cores at a time. A failed step leaves the
    steps that need it (directly or not) unrun and the others going. Returns the summary the
    script prints."""
    todo = [s for s in steps if force or not rnd.done(s)]
    skipped = [s.name for s in steps if s not in todo]
    finished = set(skipped)
    running: dict[str, tuple[Step, subprocess.Popen, float]] = {}
    ran, failed, t0 = [], [], time.perf_counter()
    while todo or running:
        for step in _ready(todo, finished, running, jobs):
            print(f"[{time.strftime('%H:%M:%S')}] {step.name} ({step.minutes:g} min)", flush=True)
            running[step.name] = (step, rnd.start(step), time.perf_counter())
            todo.remove(step)
        if not running:
            break  # what is left needs a step that failed
        time.sleep(0.2)
        for name, (step, proc, t_start) in list(running.items()):
            if proc.poll() is None:
                continue
            del running[name]
            why = rnd.finish(step, proc.returncode, time.perf_counter() - t_start)
            if why is None:
                finished.add(name)
                ran.append(name)
            else:
                failed.append(name)
                print(f"{name} failed ({why}): see {rnd.state / 'logs' / (name + '.log')}")
    not_run = [s.name for s in todo]
    return {"run": ran, "skipped": skipped, "failed": failed, "not_run": not_run,
            "wall_s": round(time.perf_counter() - t0, 1)}  # fmt: skip


def _ready(todo: list[Step], finished: set[str], running: dict, jobs: int) -> list[Step]:
    """The next steps to start: needs finished and cores free (a step wider than `jobs` runs
    alone). Steps that build on finished ones go first, then those that need nothing (the
    trainings), each kind in the manifest's order: a report is made as soon as its runs are.
    A ready step that does not fit yet holds back the ones after it, so a grid waiting for both
    cores is not starved by one training after another."""
    free = jobs - sum(step.cores for step, _, _ in running.values())
    ready = [s for s in todo if all(n in finished for n in s.needs)]
    out = []
    for step in sorted(ready, key=lambda s: not s.needs):  # stable: the manifest's order within
        width = min(step.cores, jobs)
        if width > free:
            break
        out.append(step)
        free -= width
    return out


def print_plan(rnd: Round, steps: list[Step], jobs: int) -> None:
    """One line per step (done or not, cores, minutes) and the time left."""
    left = [s for s in steps if not rnd.done(s)]
    for s in steps:
        mark = "done" if s not in left else "todo"
        print(
            f"{mark}  {s.name:32s} {s.cores} core{'s' if s.cores > 1 else ' '} {s.minutes:7.1f} min"
        )
    hours = plan_minutes(left, jobs) / 60
    print(f"{len(left)} of {len(steps)} steps left, about {hours:.1f} h with --jobs {jobs}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--manifest", type=Path, default=MANIFEST)
    ap.add_argument("--state", type=Path, default=ROOT / "runs" / "regenerate",
                    help="the round's folder: done markers, logs, times")  # fmt: skip
    ap.add_argument("--only", action="append", default=[], metavar="GLOB",
                    help="steps by name (fnmatch) and what they need; repeatable")  # fmt: skip
    ap.add_argument("--from", dest="since", action="append", default=[], metavar="GLOB",
                    help="steps by name, every step that reads them and what those need; "
                    "repeatable (remake what a change invalidates)")  # fmt: skip
    ap.add_argument("--jobs", type=int, default=1, help="cores to fill (1 or 2 on this machine)")
    ap.add_argument("--force", action="store_true", help="rerun the selected steps even if done")
    ap.add_argument("--dry-run", action="store_true", help="print the plan, run nothing")
    ap.add_argument("--check", action="store_true",
                    help="check the commands, running none (syntax, options, presets)")  # fmt: skip
    args = ap.parse_args(argv)
    if args.jobs < 1:
        raise SystemExit(f"--jobs must be at least 1, got {args.jobs}")
    steps = select(load_manifest(args.manifest), args.only, args.since)
    if args.check:
        problems = [p for s in steps for p in check_step(s)]
        print("\n".join(problems) or f"{len(steps)} steps: every command checks")
        return 1 if problems else 0
    rnd = Round(ROOT, args.state)
    print_plan(rnd, steps, args.jobs)
    if args.dry_run:
        return 0
    rnd.check_machine(machine())
    summary = run_round(rnd, steps, args.jobs, args.force)
    print(json.dumps(summary))
    return 1 if summary["failed"] or summary["not_run"] else 0


if __name__ == "__main__":
    sys.exit(main())
