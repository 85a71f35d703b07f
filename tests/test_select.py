"""Checkpoint selection (`[select]`): the run keeps its best greedy policy on its own validation
roads, without changing the training, and a killed run selects as the uninterrupted one."""

import json

import pytest
import torch
from test_train import TINY as TRAIN_TINY

from marlmerge.config import ScenarioConfig
from marlmerge.config.presets import load_scenario, preset_dir
from marlmerge.config.training import SelectConfig, TrainConfig
from marlmerge.io import files
from marlmerge.learners.base import Learner
from marlmerge.training.select import Selection
from marlmerge.training.train import load_train_config, make_selection, train

TINY = {**TRAIN_TINY, "eval_episodes": 0}
SELECT = {"every_sim_steps": 1_024, "episodes": 8, "start_fraction": 0.25}


class FakeLearner(Learner):
    """A learner whose greedy policy is a label; its policy_state is that label."""

    def __init__(self) -> None:
        self.label = 0

    def greedy(self, obs):
        return self.label

    def policy_state(self):
        return {"net": {"w": torch.tensor([float(self.label)])}}


def scripted_evaluate(success_by_label):
    def evaluate(greedy, scenario, episodes, seed, worlds):
        assert seed == 5_000_000 and episodes == 10
        return {"success_rate": success_by_label[greedy(None)], "collision_rate": 0.0}

    return evaluate


def test_selection_keeps_the_fewest_failures_and_the_latest_on_ties():
    cfg = SelectConfig(every_sim_steps=100, episodes=10, start_fraction=0.5)
    success = {1: 0.7, 2: 0.9, 3: 0.8, 4: 0.9}
    sel = Selection(cfg, ScenarioConfig(), 400, 4, scripted_evaluate(success))
    learner = FakeLearner()
    assert not sel.due(150) and sel.due(200)  # the first candidate is at half the run
    for label, step in ((1, 200), (2, 300), (3, 400), (4, 400)):
        learner.label = label
        sel.consider(step, learner)
    assert [h["failures"] for h in sel.history] == [3, 1, 2, 1]
    assert sel.best_state["net"]["w"].item() == 4.0  # tied with label 2, later
    state = sel.state_dict()
    other = Selection(cfg, ScenarioConfig(), 400, 4, scripted_evaluate(success))
    other.load_state_dict(state)
    assert other.summary() == sel.summary() and other.next_at == sel.next_at


def test_selection_needs_a_period():
    with pytest.raises(ValueError, match="every_sim_steps"):
        Selection(SelectConfig(), ScenarioConfig(), 100, 4)


def test_a_bad_select_value_names_its_key():
    with pytest.raises(ValueError, match=r"select\.episodes.*0"):
        load_train_config("quick", **{"select.episodes": 0})
    with pytest.raises(ValueError, match=r"select\.nope"):
        load_train_config("quick", **{"select.nope": 1})


def _weights(path):
    return files.load(path)["policy_state"]["net"]


def _same(a, b):
    return all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.slow
def test_selection_changes_nothing_in_training_and_resumes_exactly(tmp_path):
    plain = TrainConfig(**TINY)
    chosen = TrainConfig(**{**TINY, "select": SelectConfig(**SELECT)})
    train(plain, tmp_path / "plain", progress=False)
    train(chosen, tmp_path / "a", progress=False)
    # the training is the same: the last policy is the plain run's policy
    assert _same(
        _weights(tmp_path / "plain" / "policy.pt"), _weights(tmp_path / "a" / "policy_last.pt")
    )
    summary = json.loads((tmp_path / "a" / "selection.json").read_text())
    steps = [c["sim_step"] for c in summary["candidates"]]
    assert steps[0] >= 1_600 and steps[-1] >= 6_400 and len(steps) == len(set(steps)) >= 4
    kept = min(summary["candidates"], key=lambda c: (c["failures"], -c["sim_step"]))
    assert summary["kept_sim_step"] == kept["sim_step"]
    # killed between checkpoints, resumed: the same candidates, the same policy kept
    train(chosen, tmp_path / "b", progress=False, stop_after_sim_steps=5_120)
    train(chosen, tmp_path / "b", resume=True, progress=False)
    assert json.loads((tmp_path / "b" / "selection.json").read_text()) == summary
    assert _same(_weights(tmp_path / "a" / "policy.pt"), _weights(tmp_path / "b" / "policy.pt"))


def test_the_validation_roads_can_be_another_scenarios_but_never_a_held_out_set():
    cfg = TrainConfig(**{**TINY, "select": SelectConfig(**SELECT, scenario="hardened_roads")})
    sel = make_selection(cfg, load_scenario(preset_dir("envs") / "default.toml"))
    assert sel is not None and sel.scenario.name == "hardened_roads"
    assert make_selection(TrainConfig(**{**TINY, "select": SelectConfig(**SELECT)}),
                          ScenarioConfig()).scenario == ScenarioConfig()  # fmt: skip
    for held_out in ("heldout11_03", "heldout_aggressive", "lapses_heldout2"):
        with pytest.raises(ValueError, match=f"select.scenario = '{held_out}' is a held-out set"):
            load_train_config("quick", **{"select.scenario": held_out})
    with pytest.raises(ValueError, match="select.scenario = 'nope': unknown scenario preset"):
        load_train_config("quick", **{"select.scenario": "nope"})
