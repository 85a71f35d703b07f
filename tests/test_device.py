"""The device option (`device = "cuda"`) of training and co-training: values checked, a missing
device refused before any work, the acting networks aliased through a move, files written on
the CPU, a run resumed on another device; on a machine with CUDA, whole runs there."""

import dataclasses
import json

import pytest
import torch
from test_train import TINY

from marlmerge.config import ScenarioConfig
from marlmerge.io import files
from marlmerge.learners.loading import load_policy
from marlmerge.training.cotrain import (
    cotrain,
    cotrain_seeds,
    load_cotrain_config,
    load_highway_policy,
)
from marlmerge.training.seeds import train_seeds
from marlmerge.training.train import TrainConfig, load_train_config, make_learner, train


@pytest.mark.parametrize("value", ["gpu", "cuda:x", "CPU", ""])
def test_device_values_are_checked(value):
    with pytest.raises(ValueError, match=f"device must be .* got {value!r}"):
        TrainConfig(device=value)
    with pytest.raises(ValueError, match="device"):
        load_train_config("paper", device=value)
    with pytest.raises(ValueError, match=f"device must be .* got {value!r}"):
        load_cotrain_config("adversary_ppo", device=value)


def test_a_device_the_machine_lacks_is_refused_before_any_work(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cfg = TrainConfig(**TINY, device="cuda")
    with pytest.raises(ValueError, match=r"device = 'cuda': .*is_available\(\) is False"):
        train(cfg, tmp_path / "run", progress=False)
    with pytest.raises(ValueError, match="device = 'cuda'"):
        train_seeds(cfg, [0, 1], tmp_path / "seeds", progress=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ValueError, match=r"device = 'cuda:3': this machine has 1 CUDA device"):
        train(dataclasses.replace(cfg, device="cuda:3"), tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists() and not (tmp_path / "seeds").exists()
    co = load_cotrain_config("cotrain", device="cuda")
    with pytest.raises(ValueError, match="device = 'cuda:3'"):
        cotrain(dataclasses.replace(co, device="cuda:3"), tmp_path / "co", progress=False)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="device = 'cuda'"):
        cotrain_seeds(co, [0, 1], tmp_path / "co", progress=False)
    assert not (tmp_path / "co").exists()


def _acting_and_loss_params(learner):
    """The acting network's parameters and the loss module's online parameters."""
    if learner.algorithm == "quadq":
        return learner.net, learner.loss_module.value_network_params
    if learner.algorithm == "dqn":
        return learner.q_mlp, learner.loss.value_network_params
    return learner.actor_net, learner.loss.actor_network_params


@pytest.mark.parametrize("algorithm", ["quadq", "dqn", "td3"])
def test_acting_network_stays_the_losss_parameters_through_a_move(algorithm):
    """A learner is built on the CPU and its loss moved (`loss.to(device)`) before anything is
    built on the parameters; the network it acts with must still be the loss's parameters. A
    dtype change goes through the same `Module._apply` as a device move: checked with it."""
    cfg = TrainConfig(**{**TINY, "update_path": "torchrl"}, algorithm=algorithm)
    learner = make_learner(cfg, ScenarioConfig(), torch.Generator().manual_seed(0), 7)
    net, params = _acting_and_loss_params(learner)
    loss = learner.loss_module if algorithm == "quadq" else learner.loss
    loss.to(torch.float64)
    ptrs = {t.data_ptr() for t in params.values(True, True)}
    assert all(p.dtype == torch.float64 and p.data_ptr() in ptrs for p in net.parameters())


def _recorded_on_cuda(path):
    """Make a checkpoint say its run was trained on CUDA."""
    ckpt = files.load(path, "checkpoint")
    ckpt["config"]["device"] = "cuda"
    files.save(ckpt, path)


@pytest.mark.slow
def test_a_run_from_an_accelerator_resumes_on_the_cpu_exactly(tmp_path, capsys, monkeypatch):
    """Checkpoints and policies hold CPU tensors whatever the device, and `device` is the one
    key a resumed run may change: a run recorded as trained on CUDA (its saved config says so)
    continues on this machine with `--set device=cpu`, bit for bit the uninterrupted run."""
    from marlmerge.cli import main

    cfg = TrainConfig(**TINY)
    train(cfg, tmp_path / "whole", progress=False)
    train(cfg, tmp_path / "cut", progress=False, stop_after_sim_steps=3_000)
    _recorded_on_cuda(tmp_path / "cut" / "checkpoint.pt")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    args = ["train", "--out", str(tmp_path / "cut"), "--resume", "--no-progress"]
    assert main(args) == 2  # without --set: the run's own device, which this machine lacks
    assert "device = 'cuda'" in capsys.readouterr().err
    assert main([*args, "--set", "device=cpu"]) == 0
    for name in ("loss.csv", "egos.csv", "evaluation.json"):
        assert (tmp_path / "cut" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes()


@pytest.mark.slow
def test_a_cotraining_run_from_an_accelerator_resumes_on_the_cpu_exactly(tmp_path, monkeypatch):
    """The same for co-training, with PPO adversaries: the learners' device moves rollouts,
    noise and minibatch orders through the same code on every device."""
    from test_cotrain import TINY as CO_TINY

    from marlmerge.cli import main

    sets = {**CO_TINY, "rounds": 1, "highway_algorithm": "ppo"}
    cfg = load_cotrain_config("cotrain", **sets)
    cotrain(cfg, tmp_path / "whole", progress=False)
    cotrain(cfg, tmp_path / "cut", progress=False, stop_after_sim_steps=6_700)
    _recorded_on_cuda(tmp_path / "cut" / "checkpoint.pt")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    args = ["cotrain", "cotrain", "--out", str(tmp_path / "cut"), "--resume", "--no-progress"]
    assert main(args) == 2  # the run's own device, which this machine lacks
    assert main([*args, "--set", "device=cpu"]) == 0
    for name in ("loss.csv", "egos.csv", "highway.csv", "evaluation.json"):
        assert (tmp_path / "cut" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes()


ON_CUDA = [("quadq", "compiled"), ("dqn", "fast"), ("td3", "fast")]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("algorithm,path", ON_CUDA)
def test_whole_run_on_cuda(tmp_path, algorithm, path):
    cfg = TrainConfig(**{**TINY, "update_path": path}, algorithm=algorithm, device="cuda")
    result = train(cfg, tmp_path, progress=False)
    assert result.sim_steps >= cfg.total_sim_steps
    policy = load_policy(tmp_path / "policy.pt")  # written on the CPU: loads anywhere
    assert policy(torch.zeros(3, 7)).device.type == "cpu"
    assert json.loads((tmp_path / "evaluation.json").read_text())["episodes"] == 8


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_vectorised_seeds_run_on_cuda(tmp_path):
    """`train --seeds` on the device: every seed's folder written as a single run writes it,
    policies on the CPU, the seeds different. (Bit-for-bit equality with the single runs is
    the CPU's promise: on CUDA the batched products may round differently, docs/training.md.)"""
    from test_vectorized_seeds import SMALL, _read

    cfg = TrainConfig(**SMALL, device="cuda")
    results = train_seeds(cfg, [0, 3], tmp_path, progress=False)
    assert [r.sim_steps >= cfg.total_sim_steps for r in results] == [True, True]
    for seed in (0, 3):
        policy = load_policy(tmp_path / f"seed_{seed}" / "policy.pt")
        assert policy(torch.zeros(3, 7)).device.type == "cpu"
    assert _read(tmp_path / "seed_0" / "egos.csv") != _read(tmp_path / "seed_3" / "egos.csv")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("highway", ["quadq", "ppo"])
def test_cotraining_seeds_run_on_cuda(tmp_path, highway):
    """Co-training on the device, one seed and two in one process: policies written on the CPU,
    evaluations made, the seeds different."""
    from test_cotrain import TINY as CO_TINY

    cfg = load_cotrain_config(
        "cotrain", **{**CO_TINY, "rounds": 1, "highway_algorithm": highway, "device": "cuda"}
    )
    assert cotrain(cfg, tmp_path / "one", progress=False).evaluation is not None
    results = cotrain_seeds(cfg, [0, 3], tmp_path / "two", progress=False)
    assert all(r.evaluation is not None for r in results)
    for folder in (tmp_path / "one", tmp_path / "two" / "seed_3"):
        policy = load_policy(folder / "policy.pt")
        assert policy(torch.zeros(3, 7)).device.type == "cpu"
        assert load_highway_policy(folder)(torch.zeros(2, 4, 12)).device.type == "cpu"
    egos = [(tmp_path / "two" / f"seed_{s}" / "egos.csv").read_text() for s in (0, 3)]
    assert egos[0] != egos[1]
