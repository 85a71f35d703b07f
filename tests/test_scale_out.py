"""Scale-out: the grid and the sweep give the same answer on every backend, resume, and survive a
killed worker."""

import json
import multiprocessing
import os
import signal
import threading
import time

import pytest

from marlmerge.evaluation.grid import parse_policy, run_grid
from marlmerge.training.sweep import parse_seeds, sweep

POLICIES = ["hold", "gap"]
CONDITIONS = ["grid_light_cooperative", "grid_dense_adversarial"]
TINY = {
    "total_sim_steps": 2048,
    "num_worlds": 8,
    "learning_starts": 256,
    "update_path": "fast",
    "eval_episodes": 6,
    "eval_worlds": 3,
    "checkpoint_every_sim_steps": 1024,
}


def _grid(out, backend, episodes=3, **kw):
    return run_grid(
        [parse_policy(p) for p in POLICIES],
        CONDITIONS,
        episodes=episodes,
        worlds=3,
        out_dir=out,
        progress=False,
        backend=backend,
        **kw,
    )


@pytest.fixture(scope="module")
def serial_csv(tmp_path_factory):
    out = tmp_path_factory.mktemp("serial")
    _grid(out, "serial")
    return (out / "episodes.csv").read_bytes()


@pytest.mark.parametrize("method", ["fork", "spawn"])
@pytest.mark.slow
def test_process_backend_gives_the_serial_csv_byte_for_byte(
    tmp_path, serial_csv, method, monkeypatch
):
    import marlmerge.evaluation.backends as backends

    monkeypatch.setattr(backends, "start_method", lambda: method)  # forked or spawned workers
    res = _grid(tmp_path, "process", workers=2)
    assert res.backend == "process" and res.cells_run == 4
    assert (tmp_path / "episodes.csv").read_bytes() == serial_csv


@pytest.mark.slow
def test_workers_are_forked_only_before_a_parallel_kernel_ran(tmp_path):
    import subprocess
    import sys

    code = (
        "import numpy as np; from marlmerge.evaluation.backends import start_method; "
        "from marlmerge import ScenarioConfig, TrafficCore; a = start_method(); "
        "c = TrafficCore(ScenarioConfig(), batch_size=128, seed=0); c.rollout(np.zeros(128)); "
        "print(a, start_method())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == (["fork", "spawn"] if sys.platform == "linux" else ["spawn"] * 2)


@pytest.mark.slow
def test_forked_workers_compile_the_kernels_they_need(tmp_path):
    # workers that compile (an empty kernel cache: a fresh install) re-read Numba's config
    # before any thread starts, so compiling does not trip over the one-thread setting
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    args = ["grid", "--policy", "hold", "--condition", "grid_light_mixed", "--episodes", "2"]
    args += ["--worlds", "2", "--out", str(tmp_path / "grid"), "--no-progress"]
    run = subprocess.run(
        [sys.executable, "-m", "marlmerge", *args], env=env, capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert (tmp_path / "grid" / "episodes.csv").exists()


@pytest.mark.slow
def test_ray_backend_gives_the_serial_csv_byte_for_byte(tmp_path, serial_csv):
    ray = pytest.importorskip("ray")
    try:
        res = _grid(tmp_path / "local", "ray", workers=2)
        assert res.cells_run == 4
        assert (tmp_path / "local" / "episodes.csv").read_bytes() == serial_csv
    finally:
        ray.shutdown()
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1})
    cluster.add_node(num_cpus=1)
    try:
        _grid(tmp_path / "cluster", "ray", address=cluster.address)
        assert (tmp_path / "cluster" / "episodes.csv").read_bytes() == serial_csv
    finally:
        ray.shutdown()
        cluster.shutdown()


def test_an_interrupted_grid_resumes_and_skips_finished_cells(tmp_path, serial_csv):
    _grid(tmp_path, "serial")
    cells = sorted((tmp_path / "cells").glob("*.csv"))
    assert len(cells) == 4
    cells[2].unlink()  # as if the run was killed before this cell finished
    (tmp_path / "episodes.csv").unlink()
    res = _grid(tmp_path, "serial")
    assert (res.cells_run, res.cells_reused) == (1, 3)
    assert (tmp_path / "episodes.csv").read_bytes() == serial_csv


@pytest.mark.slow
def test_a_killed_worker_is_retried_without_losing_or_duplicating_rows(tmp_path):
    episodes = 6
    want = tmp_path / "want"
    _grid(want, "serial", episodes=episodes)
    got = tmp_path / "got"
    errors = []

    def run():
        try:
            _grid(got, "process", episodes=episodes, workers=2)
        except Exception as err:  # noqa: BLE001 - reported below
            errors.append(err)

    thread = threading.Thread(target=run)
    thread.start()
    killed = False
    deadline = time.time() + 300
    while thread.is_alive() and time.time() < deadline and not killed:
        children = multiprocessing.active_children()
        started = (got / "cells").exists() and any((got / "cells").glob("*.csv"))
        if children and started:  # a cell has finished: kill a worker during the next ones
            os.kill(children[0].pid, signal.SIGKILL)
            killed = True
        time.sleep(0.05)
    thread.join(timeout=600)
    assert killed, "the grid finished before a worker could be killed"
    assert not errors, errors
    assert (got / "episodes.csv").read_bytes() == (want / "episodes.csv").read_bytes()


def test_parse_seeds_and_bad_sweeps():
    assert parse_seeds("0-3,7,2") == [0, 1, 2, 3, 7]
    with pytest.raises(ValueError, match="--seeds"):
        parse_seeds("a-b")
    with pytest.raises(ValueError, match="the range '3-1' in '0,3-1' is empty"):
        parse_seeds("0,3-1")
    with pytest.raises(ValueError, match="names more than 10,000 seeds"):
        parse_seeds("0-99999999999")  # refused before the range is expanded
    with pytest.raises(ValueError, match="--backend"):
        sweep("quick", [0], "x", backend="threads")
    with pytest.raises(ValueError, match="not --set seed"):
        sweep("quick", [0], "x", {"seed": 3})
    with pytest.raises(ValueError, match="unknown config key"):
        sweep("quick", [0], "x", {"no_such_key": 1})


def test_a_summary_interval_stays_within_what_its_measure_can_be():
    from marlmerge.training.sweep import summarize

    ev = {0: {"success_rate": 0.0, "mean_merge_time_s": 1.0},
          1: {"success_rate": 0.9, "mean_merge_time_s": 30.0}}  # fmt: skip
    s = summarize(ev)
    # the t interval of two seeds reaches far past 0 and 1: cut to the rates' range
    assert s["success_rate"]["ci95"] == [0.0, 1.0]
    lo, hi = s["mean_merge_time_s"]["ci95"]
    assert lo == 0.0 and 30.0 < hi < float("inf")
    one = summarize({0: {"success_rate": 0.5}})  # one seed: no interval
    assert all(x != x for x in one["success_rate"]["ci95"])


@pytest.mark.slow
def test_sweep_summarises_seeds_and_resumes(tmp_path):
    s = sweep("quick", [0, 1], tmp_path, dict(TINY), backend="serial", progress=False)
    assert s["seeds"] == [0, 1]
    for seed in (0, 1):
        assert (tmp_path / f"seed_{seed}" / "policy.pt").exists()
    rate = s["success_rate"]
    assert rate["ci95"][0] <= rate["mean"] <= rate["ci95"][1]
    assert rate["worst"] == min(s["per_seed"][str(k)]["success_rate"] for k in (0, 1))
    assert "worst seed" in (tmp_path / "summary.md").read_text()
    # a second sweep reuses the finished seeds (no training: the logs are untouched)
    stamp = (tmp_path / "seed_0" / "egos.csv").stat().st_mtime_ns
    again = sweep("quick", [0, 1], tmp_path, dict(TINY), backend="process", progress=False)
    assert (tmp_path / "seed_0" / "egos.csv").stat().st_mtime_ns == stamp
    assert json.dumps(again["per_seed"]) == json.dumps(s["per_seed"])  # nan-safe comparison
