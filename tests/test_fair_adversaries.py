"""Adversaries trained to be fair (`CoTrainConfig.fairness_worlds`): gap acceptance drives the
ramp vehicle of some worlds in the adversary phases, and there its failures cost the whole
highway group."""

import csv
import dataclasses

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from test_cotrain import _files, _tiny

from marlmerge.config import ScenarioConfig
from marlmerge.config.cotraining import CoTrainConfig
from marlmerge.config.scenario import InteractionConfig
from marlmerge.policies.gap_acceptance import GapAcceptancePolicy
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_TRUNCATED
from marlmerge.sim.reward import HIGHWAY_TERMS, LEARNED_HIGHWAY_TERMS
from marlmerge.training.cotrain import cotrain, cotrain_seeds
from marlmerge.training.cotrain_groups import count_against_in_rule_worlds, rule_acting
from marlmerge.views.torchrl_groups import GROUP, MultiAgentMergeEnv


def test_fairness_settings_are_checked_before_any_work():
    assert CoTrainConfig(num_worlds=8, fairness_worlds=0.25).rule_worlds() == 2
    with pytest.raises(ValueError, match="fairness_worlds = 0.05 of num_worlds = 8 gives no"):
        CoTrainConfig(num_worlds=8, fairness_worlds=0.05)
    with pytest.raises(ValueError, match="needs profile = 'adversarial', got 'cooperative'"):
        CoTrainConfig(fairness_worlds=0.25, profile="cooperative")
    with pytest.raises(ValueError, match="the schedule has none"):
        CoTrainConfig(fairness_worlds=0.25, adversary_sim_steps=0)
    with pytest.raises(ValueError, match="fairness_worlds"):
        CoTrainConfig(fairness_worlds=0.75)  # the learned ego keeps most worlds
    with pytest.raises(ValueError, match="fairness_weight"):
        CoTrainConfig(fairness_weight=-1.0)


def test_the_rule_drives_the_last_worlds_on_their_own_observations():
    env = MultiAgentMergeEnv(num_worlds=6, seed=3)
    obs = env.reset()["observation"]  # [6, d]
    rule = GapAcceptancePolicy(ScenarioConfig())

    def ego(o):
        return torch.full((o.shape[0], 1), 1.7)

    acted = rule_acting(ego, rule, 2)(obs)
    assert torch.equal(acted[:4], torch.full((4, 1), 1.7))
    expected = torch.as_tensor(rule(obs[4:].numpy()), dtype=acted.dtype)
    assert torch.equal(acted[4:], expected)
    assert not torch.equal(acted[4:], torch.full((2, 1), 1.7))  # the rule's own commands


def test_the_rules_failures_are_the_whole_groups_in_its_worlds():
    g = torch.Generator().manual_seed(0)
    b, t, k = 5, 3, 4
    terms = {name: torch.rand(b, t, k, 1, generator=g) for name in LEARNED_HIGHWAY_TERMS}
    for name in HIGHWAY_TERMS:
        terms[name] = -terms[name]  # own driving terms are costs
    reward = sum(terms.values())
    done = torch.zeros(b, t, 1, dtype=torch.bool)
    outcome = torch.zeros(b, t, 1, dtype=torch.int64)
    done[3, 1], outcome[3, 1] = True, OUTCOME_COLLISION  # the rule collides in world 3
    done[4, 2], outcome[4, 2] = True, OUTCOME_TRUNCATED  # and runs out of time in world 4
    done[0, 2], outcome[0, 2] = True, OUTCOME_COLLISION  # the ego's world: not the rule's
    mask = torch.rand(b, t, k, generator=g) > 0.3
    batch = TensorDict(
        {
            GROUP: {"mask": mask},
            "next": {
                GROUP: {"reward": reward.clone(), "reward_terms": dict(terms)},
                "done": done,
                "outcome": outcome,
            },
        },
        batch_size=[b, t],
    )
    inter = InteractionConfig()
    count_against_in_rule_worlds(batch, 2, 3.0, inter)
    after = batch.get(("next", GROUP, "reward"))
    assert torch.equal(after[:3], reward[:3])  # the ego's worlds: untouched
    near = terms["ego_hard_brake"] + terms["ego_unsafe_gap"]
    own = sum(terms[n] for n in HIGHWAY_TERMS)
    expected = (own + near)[3:].clone()  # the failure terms no longer pay in the rule's worlds
    expected[0, 1] -= 3.0 * inter.w_ego_collision * mask[3, 1].unsqueeze(-1)
    expected[1, 2] -= 3.0 * inter.w_ego_stall * mask[4, 2].unsqueeze(-1)
    torch.testing.assert_close(after[3:], expected)


@pytest.mark.slow
def test_fair_adversaries_log_the_rule_apart_and_seeds_resume_as_their_single_runs(tmp_path):
    cfg = _tiny(rounds=1, fairness_worlds=0.25, fairness_weight=2.0)
    cotrain(dataclasses.replace(cfg, seed=5), tmp_path / "single", progress=False)
    single = tmp_path / "single"
    with open(single / "rule.csv", newline="") as fh:
        rule_rows = list(csv.DictReader(fh))
    assert rule_rows and {r["world"] for r in rule_rows} <= {"6", "7"}
    assert {r["phase"] for r in rule_rows} == {"adversary"}
    with open(single / "egos.csv", newline="") as fh:
        ego_rows = list(csv.DictReader(fh))
    adversary_worlds = {r["world"] for r in ego_rows if r["phase"] == "adversary"}
    assert adversary_worlds and not adversary_worlds & {"6", "7"}
    assert {"6", "7"} <= {r["world"] for r in ego_rows if r["phase"] == "ego"}
    # the same seed without fairness learns other adversaries
    plain = tmp_path / "plain"
    cotrain(dataclasses.replace(cfg, seed=5, fairness_worlds=0.0), plain, progress=False)
    assert not (plain / "rule.csv").exists()
    assert (plain / "highway.csv").read_bytes() != (single / "highway.csv").read_bytes()
    # seeds in one process, killed inside the adversary phase and resumed
    cut = tmp_path / "cut"
    cotrain_seeds(cfg, [0, 5], cut, progress=False, stop_after_sim_steps=6_700)
    cotrain_seeds(cfg, [0, 5], cut, resume=True, progress=False)
    assert _files(cut / "seed_5") == _files(single)
    rewards = np.loadtxt(single / "highway.csv", delimiter=",", skiprows=1, usecols=4)
    assert np.isfinite(rewards).all()
