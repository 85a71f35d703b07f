"""`benchmarks/hardened_tables.py`'s count of the roads a policy's seeds share collisions on."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def _load():
    sys.path.insert(0, str(BENCH))  # it imports robustness_tables as a sibling script
    try:
        spec = importlib.util.spec_from_file_location(
            "hardened_tables", BENCH / "hardened_tables.py"
        )
        module = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
        spec.loader.exec_module(module)  # type: ignore[union-attr]
        return module
    finally:
        sys.path.remove(str(BENCH))


ht = _load()


def _episodes(runs: list[str], cond: list[str], episode: list[str], collision, truncation=None):
    n = len(runs)
    return {
        "run": np.array(runs),
        "condition": np.array(cond),
        "episode": np.array(episode),
        "collision": np.array(collision, dtype=float),
        "truncation": np.zeros(n) if truncation is None else np.array(truncation, dtype=float),
    }


def test_exactly_is_the_poisson_binomial():
    assert np.allclose(ht.exactly([0.5, 0.5]), [0.25, 0.5, 0.25])
    p = ht.exactly([0.1, 0.2, 0.3])
    assert np.isclose(p.sum(), 1.0) and np.isclose(p[3], 0.1 * 0.2 * 0.3)
    assert np.isclose(p[0], 0.9 * 0.8 * 0.7)


def test_shared_counts_roads_by_seeds_colliding_and_what_gap_did_there():
    # two seeds, one condition, four roads: both collide on road 0, seed a alone on road 1
    runs = ["a"] * 4 + ["b"] * 4
    roads = ["0", "1", "2", "3"] * 2
    g = {
        "p": _episodes(runs, ["c"] * 8, roads, [1, 1, 0, 0, 1, 0, 0, 0]),
        "gap": _episodes(["-"] * 4, ["c"] * 4, ["0", "1", "2", "3"], [0, 1, 0, 0], [0, 0, 1, 0]),
    }
    rows = ht.shared(g, "p")
    # seed a at 1/2, seed b at 1/4: exactly one of two 4 * (1/2 * 3/4 + 1/2 * 1/4) = 2, both 0.5
    assert rows[2] == "| 1 of 2 | 1 | 2 | 0 / 0 / 1 |"  # road 1: gap acceptance collided
    assert rows[3] == "| 2 of 2 | 1 | 0.5 | 1 / 0 / 0 |"  # road 0: gap acceptance merged
    assert rows[-1] == "Where most of the seeds collide, by condition: c (1)."


def test_shared_refuses_seeds_that_did_not_drive_every_road_once():
    g = {"p": _episodes(["a", "a", "b"], ["c"] * 3, ["0", "0", "0"], [1, 1, 1])}
    assert ht.shared(g, "p") == []
    one = {"p": _episodes(["a", "a"], ["c"] * 2, ["0", "1"], [1, 0])}
    assert ht.shared(one, "p") == []
    # as many episodes as seeds x roads, but each seed drove one road twice
    twice = {"p": _episodes(["a", "a", "b", "b"], ["c"] * 4, ["0", "0", "1", "1"], [1, 0, 1, 0])}
    assert ht.shared(twice, "p") == []


def _grid_csv(path: Path, policies: list[str]) -> Path:
    cols = "policy,run,condition,episode,success,collision,truncation,time_to_merge_s"
    lines = [cols + ",max_abs_jerk_mps3"]
    for policy in policies:
        for s in range(2):
            for e in range(3):
                lines.append(f"{policy},runs/{policy}/seed_{s},heldout7 01,{e},1,0,0,12.0,5.0")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_tables_without_the_default_policy_and_a_policy_not_in_the_grids(
    tmp_path, capsys, monkeypatch
):
    grid = str(_grid_csv(tmp_path / "episodes.csv", ["mine", "gap"]))
    # no `hardened` in the grid: its tables, no targets
    monkeypatch.setattr(sys, "argv", ["hardened_tables.py", grid])
    ht.main()
    out = capsys.readouterr().out
    assert "| mine |" in out and "Targets" not in out
    monkeypatch.setattr(sys, "argv", ["hardened_tables.py", grid, "--policy", "mine"])
    ht.main()
    assert "### Targets: `mine`" in capsys.readouterr().out
    monkeypatch.setattr(sys, "argv", ["hardened_tables.py", grid, "--policy", "hardened"])
    with pytest.raises(SystemExit):
        ht.main()
    assert "--policy 'hardened': not in the grids (their policies: mine, gap)" in (
        capsys.readouterr().err
    )
