"""`benchmarks/shared_roads.py`: a grid's road driven again alone is the grid's road, and the
collision it reports is classified by who hit whom."""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from marlmerge.evaluation.grid import Cell, Condition, run_cell
from marlmerge.evaluation.metrics import EpisodeTrajectory, episode_metrics
from marlmerge.evaluation.registry import parse_policy
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_SUCCESS

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
spec = importlib.util.spec_from_file_location("shared_roads", BENCH / "shared_roads.py")
sr = importlib.util.module_from_spec(spec)  # type: ignore[arg-type]
spec.loader.exec_module(sr)  # type: ignore[union-attr]


def _trajectory(x_m, d_front_m, d_back_m, outcome: int) -> EpisodeTrajectory:
    n = len(x_m)
    return EpisodeTrajectory(
        dt_s=0.1,
        x_m=np.asarray(x_m, dtype=float),
        v_mps=np.linspace(20.0, 25.0, n),
        a_mps2=np.zeros(n),
        d_front_m=np.asarray(d_front_m, dtype=float),
        v_front_mps=np.full(n, 20.0),
        d_back_m=np.asarray(d_back_m, dtype=float),
        v_back_mps=np.full(n, 10.0),
        a_back_mps2=np.zeros(n),
        outcome=outcome,
        zone_start_m=-100.0,
    )


def test_crash_says_who_hit_whom():
    x = [-60.0, -55.0, -50.0]
    assert sr.crash(_trajectory(x, [30, 10, -0.2], [20, 20, 20], OUTCOME_COLLISION)) == "front"
    assert sr.crash(_trajectory(x, [30, 30, 30], [5, 1, -1.5], OUTCOME_COLLISION)) == "back"
    assert sr.crash(_trajectory(x, [30, 30, 30], [5, 5, 5], OUTCOME_COLLISION)) == "side"
    assert sr.crash(_trajectory(x, [30, 10, -0.2], [5, 5, 5], OUTCOME_SUCCESS)) == "-"


def test_at_join_reads_the_first_sample_past_the_join_point():
    tr = _trajectory([-60.0, -52.0, -49.0, -40.0], [9, 8, 7, 6], [12, 11, 5, 4], OUTCOME_SUCCESS)
    got = sr.at_join(tr, -50.0)
    assert got["lead"] == 7 and got["lag"] == 5 and got["lag_s"] == pytest.approx(0.5)
    assert got["t"] == pytest.approx(0.2) and got["v"] == pytest.approx(tr.v_mps[2])
    assert np.isnan(sr.at_join(tr, -10.0)["v"])  # never reached


def test_shared_roads_keeps_the_roads_enough_seeds_collide_on(tmp_path):
    path = tmp_path / "episodes.csv"
    rows = [  # (policy, run, condition, episode, success, collision, truncation)
        ("hardened", "runs/a", "heldout7 06", 0, 0, 1, 0),
        ("hardened", "runs/b", "heldout7 06", 0, 0, 1, 0),
        ("hardened", "runs/a", "heldout7 06", 1, 0, 1, 0),
        ("hardened", "runs/b", "heldout7 06", 1, 1, 0, 0),
        ("gap", "-", "heldout7 06", 0, 0, 0, 1),
        ("gap", "-", "heldout7 06", 1, 1, 0, 0),
    ]
    keys = ("policy", "run", "condition", "episode", "success", "collision", "truncation")
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(keys)
        w.writerows(rows)
    roads, gap = sr.shared_roads(str(path), "hardened", 2)
    assert roads == {("heldout7 06", 0): ["runs/a", "runs/b"]}
    assert gap == {("heldout7 06", 0): "truncation", ("heldout7 06", 1): "success"}
    assert len(sr.shared_roads(str(path), "hardened", 1)[0]) == 2


def test_a_road_driven_again_is_the_grids_road():
    """`drive` seeds its one world as the grid seeds that episode's world."""
    preset, root = "grid_dense_adversarial", 2_000_000
    cell = Cell(parse_policy("gap"), None, Condition(preset, preset), None, 4, root, 4)
    rows = run_cell(cell)
    for e in (1, 3):
        tr, ret = sr.drive("gap", None, preset, e, root)
        again = episode_metrics(tr)
        assert again == {k: v for k, v in rows[e].items() if k in again}
        # another reward scores the same motion differently
        scored, ret2 = sr.drive("gap", None, preset, e, root, sr.reward_of("hardened_mix"))
        assert np.array_equal(scored.x_m, tr.x_m) and ret2 != ret
