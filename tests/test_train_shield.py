"""Gap acceptance's shield in the training loop (`TrainConfig.shield`): the vehicles drive what it
lets through, the replay stores that, the run is evaluated behind it, and what cannot take it is
refused before any work. A judging shield (`shield_penalty`) lets the ego drive its own command,
prices the overrule in the replay's reward, and its run is evaluated bare."""

import json

import numpy as np
import pytest
import torch
from test_ramp_training import TINY as TINY_RAMP
from test_train import TINY

from marlmerge.cli import main
from marlmerge.config.training import TrainConfig
from marlmerge.evaluation.registry import bare_shield_note
from marlmerge.training.loop import GroupPolicy, transition_rows
from marlmerge.training.ramp import RampGroupPolicy
from marlmerge.training.shield import SHIELD_COST, make_train_shield, shielded
from marlmerge.training.train import train
from marlmerge.views.ramp_flow_torchrl import RampFlowTorchEnv
from marlmerge.views.torchrl_env import BatchedMergeEnv

THROTTLE = 2.5  # m/s^2: a learner that floors it, which the shield must overrule in dense traffic


class FloorIt:
    """A learning group's `act` that always asks for full throttle."""

    def act(self, obs: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"action": torch.full((*obs.shape[:-1], 1), THROTTLE)}


def test_the_ego_drives_what_the_shield_lets_through():
    env = BatchedMergeEnv("grid_dense_adversarial", num_worlds=16, seed=0)
    shield = make_train_shield(TrainConfig(shield="shield"), env.cfg)
    policy = GroupPolicy(FloorIt(), shield)  # type: ignore[arg-type]
    td, overruled = env.reset(), 0
    for _ in range(80):
        td = policy(td)
        asked = np.full((16, 1), THROTTLE)
        expected = shield.shield(td["observation"].numpy(), asked)
        assert np.array_equal(td["action"].numpy(), expected)  # what the env steps with
        overruled += int((td["action"] != THROTTLE).sum())
        td = env.step(td)["next"]
    assert overruled > 0


def test_every_merging_vehicle_drives_what_the_shield_lets_through():
    env = RampFlowTorchEnv(overrides={"ramp.flow_vph": 900.0}, num_worlds=4, seed=3)
    shield = make_train_shield(TrainConfig(scenario="ramp_flow", shield="shield"), env.cfg)
    policy = RampGroupPolicy(FloorIt(), shield)  # type: ignore[arg-type]
    td, overruled = env.reset(), 0
    for _ in range(120):
        td = policy(td)
        obs, mask = td["ramp", "observation"], td["ramp", "mask"]
        flat = obs.reshape(-1, obs.shape[-1]).numpy()
        expected = shield.shield(flat, np.full((flat.shape[0], 1), THROTTLE)).reshape(4, -1, 1)
        assert np.array_equal(td["ramp", "action"].numpy(), expected)
        overruled += int(((td["ramp", "action"] != THROTTLE).squeeze(-1) & mask).sum())
        td = env.step(td)["next"]
    assert overruled > 0


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"shield": "always"}, "shield must be one of"),
        ({"shield": "shield", "algorithm": "dqn"}, "dqn's discrete levels"),
        ({"shield_penalty": 1.0}, r"shield_penalty = 1.0 needs a shield"),
        ({"shield_imitation": 2.0}, r"shield_imitation = 2.0 needs a shield to teach"),
        (
            {"shield": "shield", "shield_imitation": 2.0, "algorithm": "td3"},
            r"shield_imitation = 2.0 trains the quadratic Q's fast path: .* got 'td3' on",
        ),
        (
            {"shield": "shield", "shield_imitation": 2.0, "update_path": "torchrl"},
            r"got 'quadq' on 'torchrl'",
        ),
        ({"shield": "shield", "shield_penalty": -1.0}, "shield_penalty"),
    ],
)
def test_bad_shield_settings_are_named(values, message):
    with pytest.raises(ValueError, match=message):
        TrainConfig(**values)


@pytest.mark.parametrize(
    ("values", "message"),
    [
        ({"shield": "shield-left"}, "reads the left-lane features; ego.observation = 'paper'"),
        ({"shield": "shield", "scenario": "chosen_join"}, "leaves the join to the policy"),
        (
            {"shield": "shield", "shield_penalty": 1.0, "scenario": "ramp_flow"},
            "shield_penalty = 1.0 on scenario 'ramp_flow': a judging shield",
        ),
        (
            {"shield": "shield", "shield_imitation": 1.0, "scenario": "ramp_flow"},
            "shield_imitation = 1.0 on scenario 'ramp_flow': a judging shield",
        ),
    ],
)
def test_a_scenario_the_shield_cannot_judge_is_refused_before_any_work(tmp_path, values, message):
    cfg = TrainConfig(**{**TINY, **values})
    with pytest.raises(ValueError, match=message):
        train(cfg, tmp_path / "run", progress=False)
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_a_shielded_ramp_flow_run_is_evaluated_behind_its_shield(tmp_path, capsys):
    values = {**TINY_RAMP, "shield": "shield", "eval_episodes": 30, "eval_worlds": 2}
    quote = {k: f'"{v}"' if isinstance(v, str) else v for k, v in values.items()}
    run = tmp_path / "run"
    sets = [f"--set={k}={v}" for k, v in quote.items()]
    assert main(["train", "--out", str(run), "--no-progress", *sets]) == 0
    assert f"drive it the same way, as quadq@shield:{run}" in capsys.readouterr().out
    evaluation = json.loads((run / "evaluation.json").read_text())
    assert evaluation["driver"] == f"quadq@shield:{run}"
    assert evaluation["shield_judged"] > 0 and 0.0 <= evaluation["shield_changed_share"] <= 1.0
    assert json.loads((run / "config.json").read_text())["shield"] == "shield"
    # driven without its shield, the commands say how to drive it as trained
    note = "was trained behind the shield (shield) and drives here without it; as trained: "
    rampflow = ["rampflow", "--hours", "0.02", "--worlds", "1", "--skip", "0"]
    for spec in (str(run), f"quadq:{run}", f"{run}=0.5,gap=0.5"):
        assert main([*rampflow, spec]) == 0
        assert f"{note}quadq@shield:{run}" in capsys.readouterr().err
    assert main([*rampflow, f"quadq@shield:{run}"]) == 0
    assert "trained behind the shield" not in capsys.readouterr().err


PENALTY = 0.5  # reward per m/s^2 between the command and the shield's


def test_a_judging_shield_lets_the_ego_drive_its_command_and_prices_the_overrule():
    env = BatchedMergeEnv("grid_dense_adversarial", num_worlds=16, seed=0)
    shield = make_train_shield(TrainConfig(shield="shield", shield_penalty=PENALTY), env.cfg)
    assert shield is not None
    rollout = env.rollout(80, GroupPolicy(FloorIt(), shield), break_when_any_done=False)  # type: ignore[arg-type]
    assert torch.all(rollout["action"] == THROTTLE)  # the env stepped with the learner's command
    obs = rollout["observation"].reshape(-1, rollout["observation"].shape[-1]).numpy()
    overruled = shield.shield(obs, np.full((obs.shape[0], 1), THROTTLE))
    cost = rollout[SHIELD_COST].reshape(-1, 1).numpy()
    assert np.allclose(cost, PENALTY * np.abs(overruled - THROTTLE), atol=1e-6)
    assert (cost > 0).any() and (cost == 0).any()
    rows = transition_rows(rollout)  # [B * T, obs | action | reward | terminated | next_obs]
    reward = rows[:, obs.shape[-1] + 1].numpy()
    env_reward = rollout["next", "reward"].reshape(-1).numpy()
    assert np.array_equal(reward, env_reward - cost[:, 0])


def test_a_shield_that_only_teaches_leaves_the_commands_as_they_are():
    env = BatchedMergeEnv("grid_dense_adversarial", num_worlds=16, seed=0)
    shield = make_train_shield(TrainConfig(shield="shield", shield_imitation=1.0), env.cfg)
    acted = FloorIt().act(env.reset()["observation"])
    assert shielded(shield, env.reset()["observation"], acted) is acted


@pytest.mark.slow  # a training run
def test_a_run_with_a_judging_shield_is_evaluated_bare(tmp_path, capsys):
    values = {**TINY, "scenario": "grid_dense_adversarial", "shield": "shield"}
    values["shield_penalty"] = PENALTY
    quote = {k: f'"{v}"' if isinstance(v, str) else v for k, v in values.items()}
    run = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "--out",
                str(run),
                "--no-progress",
                *[f"--set={k}={v}" for k, v in quote.items()],
            ]
        )
        == 0
    )
    assert "drive it the same way" not in capsys.readouterr().out
    evaluation = json.loads((run / "evaluation.json").read_text())
    assert "shield_judged" not in evaluation  # driven bare, as it is meant to drive
    assert json.loads((run / "config.json").read_text())["shield_penalty"] == PENALTY
    assert bare_shield_note(str(run)) is None


IMITATING = {**TINY, "scenario": "grid_dense_adversarial", "shield": "shield", "eval_episodes": 0}


@pytest.mark.slow
def test_a_shield_that_teaches_changes_the_learning_not_the_driving_and_resumes_exactly(tmp_path):
    cfg = TrainConfig(**IMITATING, shield_imitation=5.0)
    straight = train(cfg, tmp_path / "a", progress=False)
    bare = train(TrainConfig(**{**IMITATING, "shield": "none"}), tmp_path / "bare", progress=False)
    assert straight.updates == bare.updates
    assert _read(tmp_path / "a" / "loss.csv") != _read(tmp_path / "bare" / "loss.csv")
    # killed after 5,120 steps (checkpoint at 4,096): resumed, the teacher is still there
    train(cfg, tmp_path / "b", progress=False, stop_after_sim_steps=5_120)
    train(cfg, tmp_path / "b", resume=True, progress=False)
    for name in ("loss.csv", "egos.csv"):
        assert _read(tmp_path / "a" / name) == _read(tmp_path / "b" / name), name


def _read(path):
    return path.read_text().splitlines()
