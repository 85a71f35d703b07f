"""The regeneration runner (`benchmarks/regenerate.py`) and its manifest `docs/regenerate.toml`."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load_runner():
    spec = importlib.util.spec_from_file_location(
        "regenerate", ROOT / "benchmarks" / "regenerate.py"
    )
    module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
    sys.modules["regenerate"] = module
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


rg = _load_runner()


def write(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "manifest.toml"
    path.write_text("version = 1\n" + body)
    return path


def step(name: str, run: str, needs=(), outputs=(), fresh=(), cores=1) -> str:
    q = lambda xs: "[" + ", ".join(f'"{x}"' for x in xs) + "]"  # noqa: E731
    return (
        f'[[step]]\nname = "{name}"\nrun = """{run}"""\nneeds = {q(needs)}\nfresh = {q(fresh)}\n'
        f"outputs = {q(outputs)}\ncores = {cores}\nminutes = 1.0\nreports = []\n\n"
    )


# ----------------------------------------------------------------------------------------------
# The committed manifest
# ----------------------------------------------------------------------------------------------


def test_the_committed_manifest_loads_and_every_command_checks():
    steps = rg.load_manifest()
    assert len(steps) > 20
    problems = [p for s in steps for p in rg.check_step(s)]
    assert problems == []


def test_the_committed_manifest_names_existing_reports_and_fresh_run_folders():
    steps = rg.load_manifest()
    for s in steps:
        for page in s.reports:
            assert (ROOT / page).exists(), (s.name, page)
        for out in s.outputs:
            assert out.startswith(("runs/", "docs/")), (s.name, out)
        for words in rg.command_lines(s.run):
            if words[:2] in (["marlmerge", "train"], ["marlmerge", "cotrain"]) and "--out" in words:
                out = words[words.index("--out") + 1]
                assert out in s.fresh, f"{s.name}: trains into {out} without clearing it first"
    reported = {page for s in steps for page in s.reports}
    assert {"docs/results.md", "docs/robustness.md", "docs/stress.md"} <= reported


# ----------------------------------------------------------------------------------------------
# Loading: every mistake named before anything runs
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (step("a", "true") + step("a", "true"), "appears twice"),
        (step("a", "true", needs=["b"]) + step("b", "true"), "not an earlier step"),
        (
            step("a", "true", outputs=["runs/x"]) + step("b", "true", outputs=["runs/x"]),
            "written by",
        ),
        (step("a", "true", fresh=["docs"]), "not a folder under runs/"),
        (step("a", "true", fresh=["runs/../docs"]), "not a folder under runs/"),
        (step("a", "true", cores=3), "cores must be 1 or 2"),
        (step("a", "true").replace("cores = 1", "cores = true"), "must be an integer"),
        (step("A b", "true"), "name must match"),
        (step("a", "true").replace("reports = []", "reports = []\nowner = 'x'"), "unknown keys"),
    ],
)
def test_a_bad_manifest_is_refused_naming_the_step(tmp_path, body, message):
    with pytest.raises(ValueError, match=message):
        rg.load_manifest(write(tmp_path, body))


def test_only_selects_the_matching_steps_and_what_they_need(tmp_path):
    steps = rg.load_manifest(
        write(tmp_path, step("a", "true") + step("b", "true", needs=["a"]) + step("c", "true"))
    )
    assert [s.name for s in rg.select(steps, ["b"])] == ["a", "b"]
    assert [s.name for s in rg.select(steps, [])] == ["a", "b", "c"]
    with pytest.raises(ValueError, match="no step"):
        rg.select(steps, ["zz*"])


def test_check_finds_bad_commands(tmp_path):
    steps = rg.load_manifest(
        write(
            tmp_path,
            step("a", "marlmerge train no_such_preset --out runs/a")
            + step("b", "marlmerge grid --no-such-option 1")
            + step("c", "python benchmarks/no_such_script.py")
            + step("d", "if then fi")
            + step("e", "marlmerge train paper --set seed=$s --out runs/p_s$s && echo ok"),
        )
    )
    found = {s.name: rg.check_step(s) for s in steps}
    assert "no preset" in found["a"][0]
    assert "refuses" in found["b"][0]
    assert "no script" in found["c"][0]
    assert "bash" in found["d"][0]
    assert found["e"] == []


# ----------------------------------------------------------------------------------------------
# Running: order, resume, failures, fresh folders
# ----------------------------------------------------------------------------------------------


def run(tmp_path: Path, body: str, jobs: int = 1, only=(), force=False) -> dict:
    steps = rg.select(rg.load_manifest(write(tmp_path, body)), list(only))
    return rg.run_round(rg.Round(tmp_path, tmp_path / "state"), steps, jobs, force)


def test_steps_run_in_order_and_a_rerun_skips_what_is_done(tmp_path):
    body = step("a", "echo a >> order.txt; mkdir -p runs && touch runs/a", outputs=["runs/a"])
    body += step("b", "echo b >> order.txt; touch runs/b", needs=["a"], outputs=["runs/b"])
    first = run(tmp_path, body)
    assert first["run"] == ["a", "b"] and first["failed"] == []
    assert (tmp_path / "order.txt").read_text() == "a\nb\n"
    again = run(tmp_path, body)
    assert again["run"] == [] and again["skipped"] == ["a", "b"]
    (tmp_path / "runs" / "b").unlink()  # an output gone: the step runs again
    assert run(tmp_path, body)["run"] == ["b"]
    changed = body.replace("echo b >>", "echo B >>")  # a changed command runs again
    assert run(tmp_path, changed)["run"] == ["b"]
    assert run(tmp_path, changed, only=["a"], force=True)["run"] == ["a"]
    times = (tmp_path / "state" / "times.jsonl").read_text().splitlines()
    assert len(times) == 5


def test_a_failed_step_stops_only_what_needs_it_and_leaves_no_marker(tmp_path):
    body = step("a", "exit 3") + step("b", "touch b", needs=["a"]) + step("c", "true")
    out = run(tmp_path, body)
    assert out["failed"] == ["a"] and out["not_run"] == ["b"] and out["run"] == ["c"]
    assert not (tmp_path / "b").exists()
    assert not (tmp_path / "state" / "done" / "a").exists()
    assert (tmp_path / "state" / "logs" / "a.log").exists()


def test_a_step_that_leaves_no_output_fails(tmp_path):
    out = run(tmp_path, step("a", "true", outputs=["runs/never"]))
    assert out["failed"] == ["a"]


def test_fresh_folders_are_cleared_before_the_step(tmp_path):
    old = tmp_path / "runs" / "x"
    old.mkdir(parents=True)
    (old / "stale.txt").write_text("from an earlier round")
    out = run(tmp_path, step("a", "mkdir -p runs/x && ls runs/x > listing.txt", fresh=["runs/x"]))
    assert out["run"] == ["a"]
    assert not (old / "stale.txt").exists() and (tmp_path / "listing.txt").read_text() == ""


def test_two_jobs_start_one_core_steps_together_and_a_wide_step_alone():
    steps = [
        rg.Step("a", "true", (), (), (), 1, 1.0, ()),
        rg.Step("b", "true", (), (), (), 1, 1.0, ()),
        rg.Step("c", "true", (), (), (), 2, 1.0, ()),
        rg.Step("d", "true", ("a",), (), (), 1, 1.0, ()),
    ]
    assert [s.name for s in rg._ready(steps, set(), {}, 2)] == ["a", "b"]
    assert [s.name for s in rg._ready(steps[2:3], {"a"}, {}, 2)] == ["c"]
    busy = {"a": (steps[0], None, 0.0)}
    assert [s.name for s in rg._ready(steps[1:], set(), busy, 2)] == ["b"]
    assert [s.name for s in rg._ready(steps[2:3], {"a"}, {}, 1)] == ["c"]  # alone on one core
    # a ready two-core step waits for both cores, and the one-core steps after it wait with it
    assert rg._ready([steps[2], steps[1]], set(), busy, 2) == []
    # what builds on finished steps goes before the next step that needs nothing
    assert [s.name for s in rg._ready(steps[1:], {"a"}, {}, 2)] == ["d", "b"]
    assert rg.plan_minutes(steps, 2) == pytest.approx(3 / 2 + 1)


def test_a_round_stays_on_the_machine_it_started_on(tmp_path):
    rnd = rg.Round(tmp_path, tmp_path / "state")
    here = {"cpu": "x", "compiled_isa": "avx512", "torch": "2.13.0+cpu"}
    rnd.check_machine(here)
    rnd.check_machine(dict(here))  # the same machine goes on
    with pytest.raises(SystemExit, match="compiled_isa: 'avx512' then, 'avx2' here"):
        rnd.check_machine({**here, "compiled_isa": "avx2"})
    assert set(rg.machine()) >= {"cpu", "compiled_isa", "torch_cpu_capability", "torch"}


def test_from_selects_the_steps_that_read_a_changed_one_and_what_they_need(tmp_path):
    steps = rg.load_manifest(
        write(
            tmp_path,
            step("a", "true")
            + step("b", "true")
            + step("c", "true", needs=["a", "b"])
            + step("d", "true", needs=["c"])
            + step("e", "true", needs=["b"]),
        )
    )
    assert [s.name for s in rg.select(steps, [], ["a"])] == ["a", "b", "c", "d"]
    assert [s.name for s in rg.select(steps, ["e"], ["a"])] == ["a", "b", "c", "d", "e"]
    with pytest.raises(ValueError, match="--from 'zz'"):
        rg.select(steps, [], ["zz"])
