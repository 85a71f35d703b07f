"""Splitting at attention lapses (`estimate --method split`): each branch's exact weight, the
trunk and its branches weighing exactly 1 together, replays that match, resume and refusal."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from marlmerge.cli import main
from marlmerge.config import ScenarioConfig
from marlmerge.config.presets import resolve_config
from marlmerge.evaluation import splitting
from marlmerge.evaluation.estimate import EstimateSettings, Estimator
from marlmerge.evaluation.registry import policy_from_spec
from marlmerge.sim import layout as L
from marlmerge.sim.core import TrafficCore
from marlmerge.sim.proposal import Proposal

LAPSING = resolve_config("lapses").replace(**{"driver.lapse_rate_per_h": 600.0})
N = L.N_LAPSE_CLASSES


def _run(branches: np.ndarray, r: tuple[float, ...], calls: int = 60) -> TrafficCore:
    seeds = [np.random.SeedSequence(11, spawn_key=(e,)) for e in range(branches.size)]
    proposal = replace(Proposal.natural(LAPSING), lapse_split=r)
    core = TrafficCore(LAPSING, batch_size=branches.size, seed=seeds, proposal=proposal)
    core.set_lapse_branches(branches)
    for _ in range(calls):
        core.rollout(np.full(branches.size, 0.4))
    return core


def test_each_branch_weighs_exactly_and_replays_its_trunk():
    """Trunk: (1 - p) per critical step, no lapse begun. Branch j: the trunk's first j branch
    points passed, the lapse begun at the next, weight (1 - p)^k p / r_c for the k critical
    steps before it; with every step a branch point (r = 1), k = j."""
    p = L.lapse_step_probability(LAPSING)
    b = 200
    trunk = _run(np.full(b, -1), (1.0,) * N)
    steps = trunk.wf[:, L.WF_LAPSE_STEPS : L.WF_LAPSE_STEPS + N].sum(axis=1)
    points = trunk.wf[:, L.WF_LAPSE_N : L.WF_LAPSE_N + N].sum(axis=1)
    assert np.array_equal(points, steps) and points.max() >= 3
    assert np.allclose(trunk.wf[:, L.WF_LAPSE_LOGW], steps * math.log1p(-p), atol=1e-12)
    j = np.where(points >= 3, 2, -1).astype(np.int64)  # the third point, where there is one
    branch = _run(j, (1.0,) * N)
    hit = j >= 0
    got = branch.wf[hit, L.WF_LAPSE_N : L.WF_LAPSE_N + N].sum(axis=1)
    assert np.all(got == 3)  # stopped counting once its lapse began
    want = 2 * math.log1p(-p) + math.log(p)
    assert np.allclose(branch.wf[hit, L.WF_LAPSE_LOGW], want, atol=1e-12)
    assert np.array_equal(branch.wf[~hit], trunk.wf[~hit])  # the trunks replay bit for bit


def test_branch_points_are_drawn_with_their_class_probability():
    r = (0.5, 0.5, 0.5, 0.5)
    core = _run(np.full(300, -1), r)
    steps = core.wf[:, L.WF_LAPSE_STEPS : L.WF_LAPSE_STEPS + N].sum()
    points = core.wf[:, L.WF_LAPSE_N : L.WF_LAPSE_N + N].sum()
    assert steps > 400
    assert abs(points / steps - 0.5) < 4 * math.sqrt(0.25 / steps)


def test_a_trunk_and_all_its_branches_weigh_exactly_one(monkeypatch):
    """With every critical step a branch point, the leaves enumerate the first lapse's start:
    (1 - p)^K + sum_k (1 - p)^k p = 1 for each episode, whatever the policy did."""
    monkeypatch.setattr(splitting, "BRANCH_P", (1.0,) * N)
    policy = policy_from_spec("gap", LAPSING)
    seeds = [np.random.SeedSequence(5, spawn_key=(e,)) for e in range(120)]
    batch = splitting.split_batch(policy, LAPSING, seeds, 60, "collision")
    assert batch["branch_of"].size > 50 and batch["branch_replayed"].all()
    z, w = splitting.episode_values(batch)
    assert np.allclose(w, 1.0, rtol=0, atol=1e-12)
    assert np.all((z >= 0) & (z <= w + 1e-12))


def test_splitting_refuses_what_it_cannot_split(tmp_path):
    cfg = ScenarioConfig()
    with pytest.raises(ValueError, match="lapse_rate_per_h = 0"):
        Estimator(
            policy_from_spec("gap", cfg), "gap", cfg, EstimateSettings(method="split"), tmp_path
        )
    assert not tmp_path.joinpath("request.json").exists()
    natural = Proposal.natural(LAPSING)
    with pytest.raises(ValueError, match="not both"):
        replace(natural, lapse_p=(0.1,) * N, lapse_split=(1.0,) * N)
    with pytest.raises(ValueError, match=r"lapse_split must be 4 probabilities in \(0, 1\]"):
        replace(natural, lapse_split=(1.0, 0.0, 0.5, 0.5))
    with pytest.raises(ValueError, match="lapse_split"):
        TrafficCore(LAPSING, 2, seed=0).set_lapse_branches(np.array([0, -1]))
    core = TrafficCore(LAPSING, 2, seed=0, proposal=replace(natural, lapse_split=(1.0,) * N))
    with pytest.raises(ValueError, match="-1 or >= 0"):
        core.set_lapse_branches(np.array([0, -2]))
    with pytest.raises(ValueError, match="one integer per world"):
        core.set_lapse_branches(np.array([0.5, 1.0]))


def test_split_estimate_resumes_bit_for_bit_and_prints_its_cost(tmp_path, capsys):
    cfg = LAPSING.replace(**{"driver.lapse_s": 3.0})
    settings = EstimateSettings(method="split", episodes=80, batch=40, worlds=40)
    out = tmp_path / "split"
    policy = policy_from_spec("gap", cfg)
    first = Estimator(policy, "gap", cfg, settings, out).run()
    assert first["trunk_episodes"] == 80 and first["branch_episodes"] > 0
    assert first["episodes"] == first["episodes_run"] == 80 + first["branch_episodes"]
    assert first["replay_mismatches"] == 0 and first["fitting_episodes"] == 0
    (last,) = (out / "batches").glob("4_1_*.pt")
    last.unlink()
    again = Estimator(policy, "gap", cfg, settings, out).run()
    assert 40 < again["episodes_run"] < first["episodes"]
    assert again["rate"] == first["rate"] and again["ci95"] == first["ci95"]
    cfg_file = tmp_path / "lapsing.toml"
    cfg_file.write_text(
        'name = "lapsing"\n[driver]\nlapse_rate_per_h = 600.0\nlapse_s = 3.0\n'
        "lane_change_sees_ramp = true\n"
    )
    argv = ["estimate", "gap", "--scenario", str(cfg_file), "--method", "split"]
    assert main([*argv, "--episodes", "40", "--worlds", "40", "--out", str(tmp_path / "c")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert "trunks" in lines[-2] and "branches" in lines[-2]
    last_line = json.loads(lines[-1])
    assert last_line["method"] == "split" and last_line["episodes"] >= 40


def test_importance_sampling_on_lapsing_drivers_points_to_splitting(tmp_path, capsys):
    argv = ["estimate", "gap", "--scenario", "lapses", "--episodes", "20", "--rounds", "1"]
    argv += ["--round-episodes", "20", "--worlds", "20", "--out", str(tmp_path / "is")]
    assert main(argv) == 0
    assert "--method split usually needs several times fewer" in capsys.readouterr().err
    argv[3] = "grid_moderate_neutral"  # importance sampling again, on drivers who never lapse
    argv[-1] = str(tmp_path / "is_no_lapses")
    assert main(argv) == 0
    assert "--method split" not in capsys.readouterr().err
