"""Plausibility of learned highway drivers: the counts on a constructed step, and on rollouts
with drivers built to fail each check."""

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from marlmerge.config.presets import resolve_config
from marlmerge.evaluation.plausibility import HighwayTally, fairness, summarize_highway
from marlmerge.evaluation.registry import policy_from_spec
from marlmerge.evaluation.rollout import evaluate_policy, run_episodes
from marlmerge.learners.highway import ResidualHighwayPolicy
from marlmerge.sim import OUTCOME_COLLISION, OUTCOME_SUCCESS, OUTCOME_TRUNCATED
from marlmerge.sim.observation import HIGHWAY_SCALE


def _step(speed, gap, limit, accel, collision, mask):
    """One env step of B = 1 world with K agents, in physical units."""
    k = len(speed)
    raw = np.zeros((1, k, 12))
    raw[0, :, 0], raw[0, :, 2], raw[0, :, 11] = speed, gap, limit
    obs = torch.as_tensor(raw / HIGHWAY_SCALE, dtype=torch.float32)
    td = TensorDict(
        {
            ("highway", "observation"): obs,
            ("highway", "mask"): torch.tensor([mask]),
            ("highway", "action"): torch.tensor(accel, dtype=torch.float32).reshape(1, k, 1),
        },
        [1],
    )
    terms = torch.tensor(collision, dtype=torch.float32).reshape(1, k, 1)
    nxt = TensorDict({("highway", "reward_terms", "collision"): terms}, [1])
    return td, nxt


def test_the_counts_of_a_constructed_step():
    """Four agents at a 30 m/s limit: a hard braker with a 20 m gap at 25 m/s (0.8 s headway),
    a crawler at 12 m/s, one in a collision of its own making, and one masked out that would
    fail every check (it is not counted)."""
    scen = resolve_config("default")
    tally = HighwayTally(scen, 1)
    td, nxt = _step(
        speed=[25.0, 12.0, 30.0, 5.0],
        gap=[20.0, 100.0, 90.0, 1.0],
        limit=[30.0] * 4,
        accel=[-4.0, 0.0, 1.0, -9.0],
        collision=[0.0, 0.0, -100.0, -100.0],
        mask=[True, True, True, False],
    )
    tally.add(td, nxt, np.array([True]))
    rec = tally.records()
    assert rec["highway_agent_steps"][0] == 3
    assert rec["highway_own_fault_collisions"][0] == 1
    assert rec["highway_hard_brake_steps"][0] == 1
    assert rec["highway_slow_steps"][0] == 1
    assert rec["highway_short_headway_steps"][0] == 1
    assert rec["highway_min_headway_s"][0] == pytest.approx(0.8)
    tally.add(td, nxt, np.array([False]))  # a finished episode counts no more
    assert tally.records()["highway_agent_steps"][0] == 3
    summary = summarize_highway(tally.records())
    assert summary["highway_own_fault_collision_rate"] == 1.0
    assert summary["highway_hard_brake_share"] == 1 / 3
    # without an own-collision penalty the blame cannot be read: NaN, not a false 0
    blind = scen.replace(**{"interaction.own_collision_penalty": 0.0})
    tally = HighwayTally(blind, 1)
    tally.add(td, nxt, np.array([True]))
    assert np.isnan(summarize_highway(tally.records())["highway_own_fault_collision_rate"])


def test_drivers_built_to_fail_fail_their_checks_and_idm_passes_them():
    scen = resolve_config("default")
    ego = policy_from_spec("gap", scen)
    k = scen.sim.n_highway_agents

    def constant(a):
        return lambda obs: torch.full((*obs.shape[:-1], 1), a)

    idm = evaluate_policy(ego, scen, 40, 7, 20, ResidualHighwayPolicy(constant(0.0), scen))
    braking = evaluate_policy(ego, scen, 40, 7, 20, constant(-4.5))
    racing = evaluate_policy(ego, scen, 40, 7, 20, constant(2.5))
    assert idm["highway_own_fault_collision_rate"] == 0.0
    assert idm["highway_slow_share"] == 0.0 and idm["highway_hard_brake_share"] < 0.05
    assert braking["highway_hard_brake_share"] == 1.0 and braking["highway_slow_share"] > 0.2
    assert racing["highway_own_fault_collision_rate"] > 0.2
    assert racing["highway_short_headway_share"] > 5 * idm["highway_short_headway_share"]
    rec = run_episodes(ego, scen, 40, 7, 20, constant(-4.5))
    assert rec["highway_agent_steps"].max() <= k * rec["time_s"].max() / scen.sim.dt_s


def test_fairness_counts_only_the_failures_gap_acceptance_does_not_share():
    ok, hit, late = OUTCOME_SUCCESS, OUTCOME_COLLISION, OUTCOME_TRUNCATED
    ego = np.array([ok, hit, hit, late, ok, ok, ok, ok])
    gap = np.array([ok, hit, ok, ok, late, ok, ok, ok])
    assert fairness(ego, gap) == {
        "ego_failure_rate": 3 / 8,
        "rule_failure_rate": 2 / 8,
        "fair_failure_rate": 2 / 8,
    }


def test_evaluate_fairness_needs_a_highway_policy(capsys):
    from marlmerge.cli import main

    assert main(["evaluate", "hold", "--fairness", "--episodes", "3"]) == 2
    assert "--fairness needs --highway" in capsys.readouterr().err
