"""Checkpoint selection (`[select]`, `marlmerge.config.training.SelectConfig`): the run keeps
the greedy policy with the fewest failures on its own validation roads, not the last one.

    selection = Selection(cfg.select, scenario, cfg.total_sim_steps, cfg.eval_worlds)
    if selection.due(sim_steps):          # after each batch
        selection.consider(sim_steps, learner)
    selection.best_state                  # the policy_state policy.pt is written from

Validation roads are the training scenario's (or `select.scenario`'s, which may not be a held-out
set), seeded from `select.seed`: never the roads of the final evaluation (`eval_seed`) or of a
held-out set, so choosing on them tunes nothing that is reported. The history and the best
policy live in the checkpoint: a resumed run selects as the uninterrupted one.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

from torch import Tensor

from marlmerge.config import ScenarioConfig
from marlmerge.config.training import SelectConfig
from marlmerge.learners.base import Learner, host_greedy

Evaluate = Callable[[Callable[[Tensor], Tensor], ScenarioConfig, int, int, int], dict[str, Any]]
"""`marlmerge.evaluation.rollout.evaluate_policy`: (greedy, scenario, episodes, first seed,
worlds) -> the evaluation's rates."""


class Selection:
    """The best greedy policy of a run so far (see the module docstring)."""

    def __init__(
        self,
        cfg: SelectConfig,
        scenario: ScenarioConfig,
        total_sim_steps: int,
        worlds: int,
        evaluate: Evaluate | None = None,
    ) -> None:
        if cfg.every_sim_steps <= 0:
            raise ValueError("Selection needs select.every_sim_steps > 0")
        self.cfg, self.scenario, self.total, self.worlds = cfg, scenario, total_sim_steps, worlds
        self._evaluate = evaluate
        self.start = int(cfg.start_fraction * total_sim_steps)
        self.next_at = self._first_at()
        self.history: list[dict[str, float]] = []
        """One row per candidate: `sim_step`, `failures`, `success_rate`, `collision_rate`."""
        self.best_state: dict[str, Any] | None = None
        """The `policy_state` of `best`."""

    def _first_at(self) -> int:
        every = self.cfg.every_sim_steps
        return max(every, -(-self.start // every) * every)

    def due(self, sim_steps: int) -> bool:
        """Whether the policy after `sim_steps` is a candidate (a selection point was crossed,
        or the run is over)."""
        return sim_steps >= self.next_at or sim_steps >= self.total

    def consider(self, sim_steps: int, learner: Learner) -> None:
        """Drive the validation roads greedily; keep the policy if it fails no more often
        than the best so far."""
        result = self.evaluate(host_greedy(learner))
        failures = round(self.cfg.episodes * (1.0 - result["success_rate"]))
        self.history.append(
            {
                "sim_step": sim_steps,
                "failures": failures,
                "success_rate": result["success_rate"],
                "collision_rate": result["collision_rate"],
            }
        )
        if self.best["sim_step"] == sim_steps:
            self.best_state = copy.deepcopy(learner.policy_state())
        while self.next_at <= sim_steps:
            self.next_at += self.cfg.every_sim_steps

    @property
    def best(self) -> dict[str, float]:
        """The candidate kept so far: the fewest failures, the latest on ties."""
        return min(reversed(self.history), key=lambda h: h["failures"])

    def evaluate(self, greedy: Callable[[Tensor], Tensor]) -> dict[str, Any]:
        if self._evaluate is None:  # the evaluation layer, imported when first needed
            from marlmerge.evaluation.rollout import evaluate_policy

            self._evaluate = evaluate_policy
        c = self.cfg
        return self._evaluate(greedy, self.scenario, c.episodes, c.seed, self.worlds)

    def summary(self) -> dict[str, Any]:
        """selection.json: the candidates and the one kept."""
        return {"kept_sim_step": self.best["sim_step"], "episodes": self.cfg.episodes,
                "candidates": self.history}  # fmt: skip

    def state_dict(self) -> dict[str, Any]:
        return {
            "next_at": self.next_at,
            "history": copy.deepcopy(self.history),
            "best_state": copy.deepcopy(self.best_state),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.next_at = state["next_at"]
        self.history = copy.deepcopy(state["history"])
        self.best_state = copy.deepcopy(state["best_state"])
