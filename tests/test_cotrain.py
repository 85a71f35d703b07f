"""Co-training at a tiny budget: both phases run, both groups are checkpointed, a kill resumes;
seeds co-trained in one process are their single runs."""

import csv
import dataclasses
import json

import numpy as np
import pytest
import torch

import marlmerge
from marlmerge.cli import main
from marlmerge.io import files
from marlmerge.learners.loading import load_policy
from marlmerge.training.cotrain import (
    CoTrainConfig,
    cotrain,
    cotrain_seeds,
    load_cotrain_config,
    load_highway_policy,
)

TINY = dict(
    ego_pretrain_sim_steps=4_096,
    rounds=2,
    adversary_sim_steps=3_072,
    ego_sim_steps=3_072,
    num_worlds=8,
    learning_starts=256,
    replay_capacity=20_000,
    update_path="fast",
    checkpoint_every_sim_steps=2_048,
    eval_episodes=6,
    eval_worlds=3,
    select_episodes=3,
)


def _tiny(**kw):
    return load_cotrain_config("cotrain", **{**TINY, **kw})


def _phases_logged(path):
    with open(path, newline="") as fh:
        return [r["phase"] for r in csv.DictReader(fh)]


@pytest.mark.slow
def test_the_preset_at_a_tiny_budget_runs_both_phases_and_writes_both_groups(tmp_path):
    cfg = _tiny()
    assert [k for k, _ in cfg.phases()] == ["pretrain", "adversary", "ego", "adversary", "ego"]
    result = cotrain(cfg, tmp_path, progress=False)
    assert result.pool_size == 2
    for name in ("policy.pt", "policy_last.pt", "policy_pretrained.pt", "highway_policy.pt"):
        assert (tmp_path / name).exists(), name
    assert len(list((tmp_path / "pool").glob("adversary_*.pt"))) == 2
    # the candidates for policy.pt: the ego after pretraining and after each ego phase
    assert sorted(p.name for p in (tmp_path / "pool").glob("ego_*.pt")) == [
        "ego_0.pt",
        "ego_2.pt",
        "ego_4.pt",
    ]
    ckpt = files.load(tmp_path / "checkpoint.pt")
    for group in ("ego", "highway"):  # weights, target, optimiser and replay of both groups
        state = ckpt[group]["learner"]
        assert ckpt[group]["updates"] > 0 and state["optimizer"] is not None
        assert any("target" in k for k in state["loss"])
    logged = set(_phases_logged(tmp_path / "highway.csv"))
    assert logged == {"pretrain", "adversary", "ego"}
    # highway transitions were learned from only in the adversary phases
    with open(tmp_path / "loss.csv", newline="") as fh:
        groups = {r["group"] for r in csv.DictReader(fh)}
    assert groups == {"ego", "highway"}
    ev = json.loads((tmp_path / "evaluation.json").read_text())
    assert set(ev) == {"selection", "scripted", "latest_highway_policy"}
    sel = ev["selection"]
    assert sel["candidate_phase_index"] == [0, 2, 4]
    assert sel["opponents"] == ["scripted", "pool_0", "pool_1"]
    assert np.array(sel["failures"]).shape == (3, 3)
    totals = [sum(row) for row in sel["failures"]]
    best = sel["candidate_phase_index"].index(sel["chosen_phase_index"])
    assert totals[best] == min(totals) and totals[best + 1 :].count(min(totals)) == 0
    chosen = files.load(tmp_path / "pool" / f"ego_{sel['chosen_phase_index']}.pt")
    saved = files.load(tmp_path / "policy.pt")
    chosen, saved = chosen["policy_state"]["net"], saved["policy_state"]["net"]
    assert all(torch.equal(chosen[k], saved[k]) for k in saved)
    # saved policies load through the common interfaces
    ego = load_policy(tmp_path)
    assert ego(torch.zeros(5, 7)).shape == (5, 1)
    hw = load_highway_policy(tmp_path)
    assert hw(torch.zeros(2, 4, 12)).shape == (2, 4, 1)
    # the learned highway policy drives the PettingZoo env's highway agents, like a scripted one
    env = marlmerge.parallel_env()
    obs, _ = env.reset(seed=3)
    while env.agents:
        actions = {
            a: np.zeros(1, np.float32) if a == "ramp_0" else hw(torch.as_tensor(obs[a])).numpy()
            for a in env.agents
        }
        obs, rewards, _, _, infos = env.step(actions)
        assert all(np.isfinite(r) for r in rewards.values())


@pytest.mark.slow
def test_a_killed_run_resumes_from_its_checkpoint_to_the_same_result(tmp_path):
    cfg = _tiny(rounds=1)
    full = tmp_path / "full"
    cut = tmp_path / "cut"
    cotrain(cfg, full, progress=False)
    # killed mid-way through the adversary phase (after a checkpoint at 6,144 steps)
    cotrain(cfg, cut, progress=False, stop_after_sim_steps=6_700)
    ckpt = files.load(cut / "checkpoint.pt")
    assert ckpt["phase_index"] == 1 and ckpt["phase_done"] > 0  # inside the adversary phase
    assert not (cut / "policy.pt").exists()
    cotrain(cfg, cut, resume=True, progress=False)
    a = files.load(full / "policy.pt")["policy_state"]["net"]
    b = files.load(cut / "policy.pt")["policy_state"]["net"]
    for k in a:
        assert torch.equal(a[k], b[k]), k
    ha = files.load(full / "highway_policy.pt")["policy_state"]["net"]
    hb = files.load(cut / "highway_policy.pt")["policy_state"]["net"]
    for k in ha:
        assert torch.equal(ha[k], hb[k]), k
    assert (full / "egos.csv").read_text() == (cut / "egos.csv").read_text()
    # resuming the finished run changes nothing and says so
    before = {p.name: p.read_bytes() for p in cut.glob("*") if p.is_file()}
    again = cotrain(cfg, cut, resume=True, progress=False)
    assert again.already_finished and again.evaluation == json.loads(before["evaluation.json"])
    assert {p.name: p.read_bytes() for p in cut.glob("*") if p.is_file()} == before
    with pytest.raises(ValueError, match="other values of seed"):
        cotrain(_tiny(rounds=1, seed=5), cut, resume=True, progress=False)


def test_bad_config_and_cli_errors_name_the_value(tmp_path, capsys):
    with pytest.raises(ValueError, match="profile"):
        CoTrainConfig(profile="kamikaze")
    with pytest.raises(ValueError, match="unknown"):
        load_cotrain_config("cotrain", no_such_key=1)
    assert main(["cotrain", "cotrain", "--set", "rounds=-1", "--out", str(tmp_path)]) == 2
    assert "rounds" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_runs_the_preset_and_reports_the_selection(tmp_path, capsys):
    sets = [a for k, v in {**TINY, "rounds": 1}.items() for a in ("--set", f"{k}={v}")]
    out = tmp_path / "run"
    assert main(["cotrain", "cotrain", *sets, "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "ego selection" in printed and "selected ego vs scripted traffic" in printed
    assert (out / "policy.pt").exists()


def _files(folder):
    """Every file a run wrote (but the checkpoint), by path, as bytes."""
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != "checkpoint.pt"
    }


@pytest.mark.slow
def test_cotrained_seeds_are_their_single_runs_and_resume_exactly(tmp_path):
    # PPO adversaries shaped by the ego's value: the highway group's sampling, its on-policy
    # rollouts and the batch changed in place, each seed on its own slice of the worlds
    cfg = _tiny(rounds=1, highway_algorithm="ppo", ego_value_shaping=0.5)
    cotrain(dataclasses.replace(cfg, seed=5), tmp_path / "single", progress=False)
    both = cotrain_seeds(cfg, [0, 5], tmp_path / "both", progress=False)
    assert [r.out_dir.name for r in both] == ["seed_0", "seed_5"]
    assert (tmp_path / "both" / "seeds_checkpoint.pt").exists()
    single = _files(tmp_path / "single")
    assert set(single) >= {"policy.pt", "highway_policy.pt", "egos.csv", "evaluation.json"}
    assert _files(tmp_path / "both" / "seed_5") == single
    assert _files(tmp_path / "both" / "seed_0") != single
    # killed inside the adversary phase, then resumed: every seed as if never stopped
    cut = tmp_path / "cut"
    cotrain_seeds(cfg, [0, 5], cut, progress=False, stop_after_sim_steps=6_700)
    assert not (cut / "seed_5" / "policy.pt").exists()
    with pytest.raises(ValueError, match="already holds a run"):
        cotrain_seeds(cfg, [0, 5], cut, progress=False)
    with pytest.raises(ValueError, match="seeds \\[0, 5\\], not \\[0, 6\\]"):
        cotrain_seeds(cfg, [0, 6], cut, resume=True, progress=False)
    cotrain_seeds(cfg, [0, 5], cut, resume=True, progress=False)
    for seed in (0, 5):
        assert _files(cut / f"seed_{seed}") == _files(tmp_path / "both" / f"seed_{seed}")
    again = cotrain_seeds(cfg, [0, 5], cut, resume=True, progress=False)
    assert all(r.already_finished for r in again)


def test_bad_seeds_for_cotraining_are_named(tmp_path, capsys):
    with pytest.raises(ValueError, match="distinct seeds"):
        cotrain_seeds(_tiny(), [1, 1], tmp_path)
    sets = ["--set", "seed=2", "--seeds", "0-1", "--out", str(tmp_path)]
    assert main(["cotrain", "cotrain", *sets]) == 2
    assert "give one of them" in capsys.readouterr().err
    assert main(["cotrain", "cotrain", "--seeds", "3-1", "--out", str(tmp_path)]) == 2
    assert "3-1" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())  # refused before any work
    # a folder holds runs of one kind: a single run's is not continued as seeds, nor the reverse
    (tmp_path / "one").mkdir()
    (tmp_path / "one" / "checkpoint.pt").touch()
    assert main(["cotrain", "cotrain", "--seeds", "0-1", "--out", str(tmp_path / "one")]) == 2
    assert "holds a run of one seed" in capsys.readouterr().err
    (tmp_path / "many").mkdir()
    (tmp_path / "many" / "seeds_checkpoint.pt").touch()
    assert main(["train", "--resume", "--out", str(tmp_path / "many")]) == 2
    assert "holds a run of several seeds" in capsys.readouterr().err


@pytest.mark.slow
def test_a_vectorised_sweep_of_a_cotraining_recipe_runs_its_seeds_in_one_process(tmp_path, capsys):
    sets = [a for k, v in {**TINY, "rounds": 1}.items() for a in ("--set", f"{k}={v}")]
    out = tmp_path / "sweep"
    args = ["sweep", "cotrain", "--seeds", "0-1", "--vectorized", "--backend", "serial"]
    assert main([*args, *sets, "--out", str(out), "--no-progress"]) == 0
    assert (out / "seeds_checkpoint_0_1.pt").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["seeds"] == [0, 1]
    for seed in (0, 1):  # the scripted-traffic evaluation of each seed's selected ego
        ev = json.loads((out / f"seed_{seed}" / "evaluation.json").read_text())
        assert summary["per_seed"][str(seed)] == ev["scripted"]
    assert main(["cotrain", "cotrain", *sets, "--seeds", "0,1", "--out", str(tmp_path / "cli"),
                 "--no-progress"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    assert "seeds 0, 1" in printed and printed.count("ego selection") == 2
    cli = tmp_path / "cli"
    for seed in (0, 1):
        assert _files(cli / f"seed_{seed}") == _files(out / f"seed_{seed}")
