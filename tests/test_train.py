"""The training recipe end to end at tiny budgets, checkpoints and resume."""

import csv
import json

import pytest
import torch

from marlmerge.cli import main
from marlmerge.io import files
from marlmerge.training.train import TrainConfig, load_train_config, train

TINY = dict(
    name="tiny",
    total_sim_steps=6_400,
    num_worlds=8,
    env_steps_per_batch=4,
    learning_starts=256,
    replay_capacity=5_000,
    update_path="fast",
    checkpoint_every_sim_steps=2_048,
    eval_episodes=8,
    eval_worlds=4,
)


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.reader(fh))


@pytest.mark.slow
def test_tiny_run_writes_logs_plots_checkpoint_and_evaluation(tmp_path):
    result = train(TrainConfig(**TINY), tmp_path, progress=False)
    for name in (
        "loss.csv",
        "egos.csv",
        "checkpoint.pt",
        "policy.pt",
        "evaluation.json",
        "fig3_loss.png",
        "fig4_total_reward.png",
        "fig5_reward_terms.png",
        "timing.json",
        "config.json",
    ):
        assert (tmp_path / name).exists(), name
    # one update per simulator step; the fast path runs them 10 at a time, so < 10 are left over
    assert result.sim_steps >= 6_400 and 0 <= result.sim_steps - result.updates < 10
    loss = _rows(tmp_path / "loss.csv")
    assert loss[0] == ["update", "sim_step", "loss"]
    updates = [int(r[0]) for r in loss[1:]]
    assert updates and all(u % 5 == 0 for u in updates) and updates == sorted(updates)
    egos = _rows(tmp_path / "egos.csv")
    header = egos[0]
    assert header[:6] == ["ego", "sim_step", "world", "outcome", "time_s", "total_reward"]
    assert len(egos) - 1 == result.egos > 0
    for r in egos[1:]:
        terms = [float(x) for x in r[6:]]
        assert float(r[5]) == pytest.approx(sum(terms), abs=1e-6)
    ev = json.loads((tmp_path / "evaluation.json").read_text())
    assert ev["episodes"] == 8
    assert ev["success_rate"] + ev["collision_rate"] + ev["truncation_rate"] == pytest.approx(1)


@pytest.mark.slow
def test_killed_run_resumes_and_continues_the_same_curves(tmp_path):
    cfg = TrainConfig(**{**TINY, "eval_episodes": 0})
    straight = train(cfg, tmp_path / "a", progress=False)
    # killed after 5,120 steps; its last checkpoint is at 4,096 and its logs run past it
    train(cfg, tmp_path / "b", progress=False, stop_after_sim_steps=5_120)
    killed_rows = len(_rows(tmp_path / "b" / "egos.csv"))
    saved = files.load(tmp_path / "b" / "checkpoint.pt")
    assert saved["sim_steps"] == 4_096 and saved["ego_rows"] < killed_rows - 1
    resumed = train(cfg, tmp_path / "b", resume=True, progress=False)
    assert resumed.sim_steps == straight.sim_steps and resumed.updates == straight.updates
    assert _rows(tmp_path / "a" / "egos.csv") == _rows(tmp_path / "b" / "egos.csv")
    assert _rows(tmp_path / "a" / "loss.csv") == _rows(tmp_path / "b" / "loss.csv")
    wa = files.load(tmp_path / "a" / "policy.pt")["policy_state"]["net"]
    wb = files.load(tmp_path / "b" / "policy.pt")["policy_state"]["net"]
    assert all(torch.equal(wa[k], wb[k]) for k in wa)


@pytest.mark.slow
def test_a_run_of_two_banded_peaks_resumes_exactly_and_saves_a_policy_of_them(tmp_path):
    from marlmerge.learners.loading import load_policy

    cfg = TrainConfig(
        **{**TINY, "peaks": 2, "peak_share": 0.1, "peak_bands": True, "eval_episodes": 0}
    )
    train(cfg, tmp_path / "a", progress=False)
    train(cfg, tmp_path / "b", progress=False, stop_after_sim_steps=5_120)
    train(cfg, tmp_path / "b", resume=True, progress=False)
    assert _rows(tmp_path / "a" / "loss.csv") == _rows(tmp_path / "b" / "loss.csv")
    saved = files.load(tmp_path / "a" / "policy.pt")["policy_state"]
    assert saved["peaks"] == 2 and saved["net"]["head_bias"].shape == (6,)
    assert saved["peak_bands"] is True
    obs = torch.randn(5, 7, generator=torch.Generator().manual_seed(0))
    command = load_policy(tmp_path / "a")(obs)  # [5, 1], the B of the larger C
    assert command.shape == (5, 1) and bool(((command > -4.5) & (command < 2.5)).all())


@pytest.mark.slow
def test_a_run_with_a_decaying_learning_rate_resumes_exactly(tmp_path):
    cfg = TrainConfig(**{**TINY, "lr_end_fraction": 0.1, "eval_episodes": 0})
    train(cfg, tmp_path / "a", progress=False)
    train(cfg, tmp_path / "b", progress=False, stop_after_sim_steps=5_120)
    train(cfg, tmp_path / "b", resume=True, progress=False)
    assert _rows(tmp_path / "a" / "loss.csv") == _rows(tmp_path / "b" / "loss.csv")
    constant = TrainConfig(**{**TINY, "eval_episodes": 0})
    train(constant, tmp_path / "c", progress=False)
    assert _rows(tmp_path / "a" / "loss.csv") != _rows(tmp_path / "c" / "loss.csv")


def test_a_decaying_learning_rate_is_refused_where_it_has_no_schedule():
    with pytest.raises(ValueError, match="lr_end_fraction = 0.1 schedules"):
        TrainConfig(**{**TINY, "lr_end_fraction": 0.1, "update_path": "torchrl"})
    with pytest.raises(ValueError, match="lr_end_fraction = 0.1 schedules"):
        TrainConfig(**{**TINY, "lr_end_fraction": 0.1, "algorithm": "dqn"})
    with pytest.raises(ValueError, match="lr_end_fraction"):
        TrainConfig(**{**TINY, "lr_end_fraction": 0.0})


@pytest.mark.slow  # two training runs
def test_flushed_updates_train_the_same_run(tmp_path):
    """A tiny run with `flush_denormals` gives the plain run's bits (no subnormal arises in
    it)."""
    cfg = TrainConfig(**{**TINY, "eval_episodes": 0})
    train(cfg, tmp_path / "plain", progress=False)
    flushed = TrainConfig(**{**TINY, "eval_episodes": 0, "flush_denormals": True})
    train(flushed, tmp_path / "flushed", progress=False)
    for name in ("loss.csv", "egos.csv"):
        plain = (tmp_path / "plain" / name).read_bytes()
        assert plain == (tmp_path / "flushed" / name).read_bytes(), name
    nets = [
        files.load(tmp_path / run / "policy.pt")["policy_state"]["net"]
        for run in ("plain", "flushed")
    ]
    assert nets[0].keys() == nets[1].keys()
    assert all(torch.equal(nets[0][k], nets[1][k]) for k in nets[0])


def test_flushed_updates_are_refused_where_there_is_no_fast_path_update():
    for bad in ({"update_path": "torchrl"}, {"algorithm": "dqn"}):
        with pytest.raises(ValueError, match="flush_denormals = true flushes"):
            TrainConfig(**{**TINY, "flush_denormals": True, **bad})


def test_several_peaks_with_a_chosen_join_are_refused_before_anything_is_written(tmp_path):
    cfg = TrainConfig(**{**TINY, "peaks": 2, "scenario": "chosen_join"})
    with pytest.raises(ValueError, match="peaks = 2 shapes a Q of one action component"):
        train(cfg, tmp_path / "r", progress=False)
    assert not (tmp_path / "r").exists()


@pytest.mark.slow
def test_torchrl_update_path_runs(tmp_path):
    cfg = TrainConfig(
        **{**TINY, "update_path": "torchrl", "total_sim_steps": 2_048, "eval_episodes": 4}
    )
    result = train(cfg, tmp_path, progress=False)
    assert result.updates == result.sim_steps
    assert len(_rows(tmp_path / "loss.csv")) > 1


def test_presets_load_strictly(tmp_path):
    assert load_train_config("paper").total_sim_steps == 1_600_000
    assert load_train_config("quick").total_sim_steps < 1_600_000
    bad = tmp_path / "bad.toml"
    bad.write_text('kind = "train"\ntotal_steps = 5\n')
    with pytest.raises(ValueError, match="'total_steps'"):
        load_train_config(bad)
    bad.write_text("total_sim_steps = 5\n")
    with pytest.raises(ValueError, match=r"bad\.toml: kind must name the preset's schema"):
        load_train_config(bad)
    with pytest.raises(ValueError, match="update_path"):
        TrainConfig(update_path="jit")


@pytest.mark.slow
def test_cli_train_refuses_to_overwrite_and_resumes(tmp_path, capsys):
    out = tmp_path / "run"
    sets = [
        f"--set={k}={v!r}" if isinstance(v, str) else f"--set={k}={v}"
        for k, v in {**TINY, "eval_episodes": 4}.items()
    ]
    sets = [s.replace("'", '"') for s in sets]
    assert main(["train", "--out", str(out), "--no-progress", *sets]) == 0
    assert "greedy evaluation on 4 held-out episodes" in capsys.readouterr().out
    assert main(["train", "--out", str(out), "--no-progress", *sets]) == 2
    assert "--resume" in capsys.readouterr().err
    assert main(["evaluate", str(out), "--episodes", "4", "--worlds", "4"]) == 0
    # one policy in the grid's notation: the same run behind the shield, with the safety filter
    assert main(["evaluate", f"quadq@shield:{out}", "--episodes", "4", "--worlds", "4"]) == 0
    assert "greedy evaluation on 4 held-out episodes" in capsys.readouterr().out
    assert main(["evaluate", f"dqn:{out}", "--episodes", "4"]) == 2
    assert "holds a quadq policy" in capsys.readouterr().err
    assert main(["evaluate", f"quadq:{tmp_path}/r*", "--episodes", "4"]) == 0
    assert main(["plot", str(out)]) == 0


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


@pytest.mark.slow
def test_resuming_a_finished_run_changes_nothing_and_says_so(tmp_path, capsys):
    out = tmp_path / "run"
    sets = [
        f"--set={k}={v!r}".replace("'", '"') if isinstance(v, str) else f"--set={k}={v}"
        for k, v in {**TINY, "eval_episodes": 4}.items()
    ]
    assert main(["train", "--out", str(out), "--no-progress", *sets]) == 0
    before = _snapshot(out)
    capsys.readouterr()
    assert main(["train", "--out", str(out), "--no-progress", "--resume", *sets]) == 0
    assert "nothing to do, nothing changed" in capsys.readouterr().out
    assert _snapshot(out) == before


@pytest.mark.slow
def test_a_run_killed_during_its_final_evaluation_is_evaluated_on_resume(tmp_path):
    cfg = TrainConfig(**{**TINY, "eval_episodes": 4})
    full = train(cfg, tmp_path, progress=False)
    (tmp_path / "evaluation.json").unlink()  # as if killed while evaluating
    policy = (tmp_path / "policy.pt").read_bytes()
    resumed = train(cfg, tmp_path, resume=True, progress=False)
    assert not resumed.already_finished and resumed.sim_steps == full.sim_steps
    assert json.dumps(resumed.evaluation) == json.dumps(full.evaluation)  # NaN-safe
    assert (tmp_path / "policy.pt").read_bytes() == policy


def test_resume_refuses_a_set_that_differs_from_the_checkpoint(tmp_path, capsys):
    cfg = TrainConfig(**{**TINY, "eval_episodes": 0})
    train(cfg, tmp_path, progress=False, stop_after_sim_steps=2_048)
    other = TrainConfig(**{**TINY, "eval_episodes": 0, "lr": 0.5, "hidden": 8})
    with pytest.raises(
        ValueError, match=r"checkpoint\.pt: the run was made with other values of lr, hidden"
    ):
        train(other, tmp_path, resume=True, progress=False)
    argv = ["train", "--out", str(tmp_path), "--resume", "--no-progress", "--set=lr=0.5"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "--set lr=0.5 differs from the run being resumed" in err and "lr = 0.001" in err
    # a preset named on the command line must be the run's (TINY's name is the default's)
    before = _snapshot(tmp_path)
    assert main(["train", "quick", "--out", str(tmp_path), "--resume", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert f"the run in {tmp_path} was trained from preset '{cfg.name}', not 'quick'" in err
    assert _snapshot(tmp_path) == before  # nothing written


@pytest.mark.parametrize("damage", ["deleted", "cut"])
@pytest.mark.slow
def test_resume_refuses_missing_or_cut_logs_naming_the_file(tmp_path, damage):
    cfg = TrainConfig(**{**TINY, "eval_episodes": 0})
    train(cfg, tmp_path, progress=False, stop_after_sim_steps=4_096)
    log = tmp_path / "egos.csv"
    if damage == "deleted":
        log.unlink()
    else:
        log.write_text("\n".join(log.read_text().splitlines()[:2]) + "\n")
    with pytest.raises(ValueError, match=r"egos\.csv: "):
        train(cfg, tmp_path, resume=True, progress=False)


class _Board:
    """Stands in for TensorBoard's SummaryWriter: records (tag, value, step)."""

    def __init__(self):
        self.points = []

    def add_scalar(self, tag, value, step):
        self.points.append((tag, value, step))

    def close(self):
        pass


@pytest.mark.slow
def test_tensorboard_gets_each_loss_and_each_ego_once(tmp_path, monkeypatch):
    import marlmerge.training.train as training

    board = _Board()
    monkeypatch.setattr(training, "tensorboard", lambda out: board)
    result = train(TrainConfig(**{**TINY, "eval_episodes": 0}), tmp_path, progress=False)
    by_tag = {}
    for tag, value, step in board.points:
        by_tag.setdefault(tag, []).append((step, value))
    losses = [(int(r[0]), float(r[2])) for r in _rows(tmp_path / "loss.csv")[1:]]
    assert by_tag["losses/td_loss"] == losses
    egos = _rows(tmp_path / "egos.csv")[1:]
    assert [s for s, _ in by_tag["charts/total_reward"]] == list(range(result.egos))
    assert [v for _, v in by_tag["charts/total_reward"]] == [float(r[5]) for r in egos]
    assert [v for _, v in by_tag["charts/success"]] == [float(r[3] == "success") for r in egos]
    assert {t for t in by_tag if t.startswith("charts/")} >= {"charts/gap_front", "charts/speed"}


@pytest.mark.slow
def test_a_slow_first_call_says_it_is_compiling(capsys):
    import time

    from marlmerge.learners.compiling import notice_if_slow

    with notice_if_slow("compiling...", after_s=0.05):
        time.sleep(0.3)
    with notice_if_slow("never shown", after_s=0.5):
        pass
    time.sleep(0.6)
    err = capsys.readouterr().err
    assert "compiling..." in err and "never shown" not in err


@pytest.mark.slow
def test_the_paper_learner_learns_to_beat_holding_its_speed(tmp_path):
    """A small budget (200 k simulator steps, an eighth of the paper's) in light adversarial
    traffic: the greedy policy must succeed clearly more often than holding speed on the same
    held-out roads (seed 0 measured 93 % vs 84 %)."""
    import torch

    from marlmerge.config.presets import resolve_config
    from marlmerge.evaluation.rollout import evaluate_policy

    cfg = TrainConfig(
        name="learn",
        scenario="grid_light_adversarial",
        total_sim_steps=200_000,
        num_worlds=16,
        learning_starts=500,
        update_path="fast",
        eval_episodes=100,
        checkpoint_every_sim_steps=1_000_000,
    )
    learned = train(cfg, tmp_path, progress=False).evaluation
    hold = evaluate_policy(
        lambda obs: torch.zeros(obs.shape[0], 1),
        resolve_config(cfg.scenario),
        cfg.eval_episodes,
        cfg.eval_seed,
        cfg.eval_worlds,
    )
    assert learned["success_rate"] >= hold["success_rate"] + 0.05


def test_a_preset_of_the_other_kind_names_its_command(capsys):
    assert main(["train", "cotrain"]) == 2
    err = capsys.readouterr().err
    assert "is a 'cotrain' preset: run it with `marlmerge cotrain cotrain`" in err
    assert main(["cotrain", "paper"]) == 2
    assert "is a 'train' preset: run it with `marlmerge train paper`" in capsys.readouterr().err
