"""One seed of a co-training run: `CoTrainSeed`, its state, phases and logs, and the ego it
keeps at the end (`select_ego`). `marlmerge.training.cotrain` steps the seeds of a process
through the schedule together."""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from tensordict import TensorDictBase
from torch import Tensor

from marlmerge.config import ScenarioConfig, to_dict
from marlmerge.config.cotraining import PROFILES, CoTrainConfig
from marlmerge.io import files
from marlmerge.learners.base import host_greedy
from marlmerge.learners.highway import (
    OFFSET_BOUNDS_MPS2,
    HighwayPolicy,
    frozen_net,
    make_driver,
    save_highway_policy,
)
from marlmerge.learners.ppo import PPOHighwayLearner
from marlmerge.policies.gap_acceptance import GapAcceptancePolicy
from marlmerge.sim import OUTCOME_NAMES
from marlmerge.sim.observation import HIGHWAY_FEATURES, ego_obs_size
from marlmerge.sim.reward import LEARNED_HIGHWAY_TERMS
from marlmerge.training.cotrain_groups import (
    JointPolicy,
    count_against_in_rule_worlds,
    ego_init_weights,
    explore,
    highway_bounds,
    highway_rows,
    highway_snapshot,
    make_group,
    make_ppo_group,
    ppo_highway_rows,
    rule_acting,
    save_ego_policy,
    shape_with_ego_value,
)
from marlmerge.training.logs import CsvLog
from marlmerge.training.loop import transition_rows
from marlmerge.views.torchrl_groups import GROUP, MultiAgentMergeEnv

EGO_LOG_FIELDS = (
    "ego",
    "phase_index",
    "phase",
    "sim_step",
    "world",
    "opponent",
    "outcome",
    "time_s",
    "total_reward",
)
HIGHWAY_LOG_FIELDS = (
    "phase_index",
    "phase",
    "sim_step",
    "agent_steps",
    "reward_per_agent_step",
    *(f"{t}_sum" for t in LEARNED_HIGHWAY_TERMS),
    "background_collisions",
)
LOSS_LOG_FIELDS = ("group", "update", "sim_step", "loss")
RULE_LOG_FIELDS = ("phase_index", "phase", "sim_step", "world", "opponent", "outcome", "time_s")
"""`rule.csv`: the episodes of gap acceptance in the adversary phases' rule worlds
(`CoTrainConfig.fairness_worlds`)."""


class CoTrainSeed:
    """The state of one seed of a co-training run, in its own folder: both groups, the pool,
    the egos kept for the selection, the schedule's position, the running returns of its
    worlds' egos and the logs."""

    def __init__(
        self, cfg: CoTrainConfig, out: Path, scen: ScenarioConfig, saved: dict[str, Any] | None
    ) -> None:
        self.cfg, self.out, self.scen = cfg, out, scen
        (out / "pool").mkdir(parents=True, exist_ok=True)
        files.write_text(out / "config.json", json.dumps(to_dict(cfg), indent=1))
        self.k = scen.sim.action_repeat
        self.n_rule = cfg.rule_worlds()  # the last worlds: gap acceptance in adversary phases
        self.ego = make_group(
            cfg, "ego", ego_obs_size(scen), scen.ego.accel_bounds_mps2, cfg.seed * 1000 + 10,
            cfg.ego_updates_per_sim_step, ego_init_weights(cfg, scen),
        )  # fmt: skip
        if cfg.highway_algorithm == "ppo":
            self.hw = make_ppo_group(
                cfg, len(HIGHWAY_FEATURES), ego_obs_size(scen), scen.sim.n_highway_agents,
                cfg.seed * 1000 + 20,
            )  # fmt: skip
        else:
            self.hw = make_group(
                cfg, GROUP, len(HIGHWAY_FEATURES), OFFSET_BOUNDS_MPS2, cfg.seed * 1000 + 20,
                cfg.highway_updates_per_sim_step,
            )  # fmt: skip
        self.phases = cfg.phases()
        self.pool: list[dict[str, Tensor]] = []
        self.egos_kept: list[tuple[int, dict[str, Tensor]]] = []  # (phase index, weights)
        self.phase_index = self.phase_done = self.total = self.egos = 0
        self.ep_sum = np.zeros(cfg.num_worlds)  # [B] running ego reward of the current egos
        self.ep_steps = np.zeros(cfg.num_worlds, dtype=np.int64)
        if saved is not None:
            self._restore(saved)
        rows = (saved["ego_rows"], saved["hw_rows"], saved["loss_rows"]) if saved else (None,) * 3
        self.ego_log = CsvLog(out / "egos.csv", EGO_LOG_FIELDS, rows[0])
        self.hw_log = CsvLog(out / "highway.csv", HIGHWAY_LOG_FIELDS, rows[1])
        self.loss_log = CsvLog(out / "loss.csv", LOSS_LOG_FIELDS, rows[2])
        self.rule_log = (
            CsvLog(out / "rule.csv", RULE_LOG_FIELDS, saved.get("rule_rows") if saved else None)
            if self.n_rule
            else None
        )
        for group in (self.ego, self.hw):
            group.on_loss = functools.partial(self._log_loss, group.name)
        if cfg.ego_init and saved is None:
            self.keep_ego(-1)  # the starting ego is a candidate too

    def _restore(self, saved: dict[str, Any]) -> None:
        self.ego.load_state_dict(saved["ego"])
        self.hw.load_state_dict(saved["highway"])
        self.pool, self.egos_kept = saved["pool"], saved["egos_kept"]
        self.phase_index, self.phase_done = saved["phase_index"], saved["phase_done"]
        self.total, self.egos = saved["total"], saved["egos"]
        self.ep_sum[:] = saved["ep_sum"]
        self.ep_steps[:] = saved["ep_steps"]

    def _logs(self) -> list[CsvLog]:
        return [log for log in (self.ego_log, self.hw_log, self.loss_log, self.rule_log) if log]

    def _log_loss(self, group: str, update: int, loss: float) -> None:
        self.loss_log.write([group, update, self.total, loss])

    def state_dict(self) -> dict[str, Any]:
        """This seed's part of the checkpoint (its logs flushed)."""
        for log in self._logs():
            log.flush()
        state = {
            "ego": self.ego.state_dict(),
            "highway": self.hw.state_dict(),
            "pool": self.pool,
            "egos_kept": self.egos_kept,
            "phase_index": self.phase_index,
            "phase_done": self.phase_done,
            "total": self.total,
            "egos": self.egos,
            "ep_sum": self.ep_sum.copy(),
            "ep_steps": self.ep_steps.copy(),
            "ego_rows": self.ego_log.rows,
            "hw_rows": self.hw_log.rows,
            "loss_rows": self.loss_log.rows,
        }
        if self.rule_log is not None:
            state["rule_rows"] = self.rule_log.rows
        return state

    def keep_ego(self, index: int) -> None:
        """The current ego becomes a candidate of the final selection (and `pool/ego_*.pt`)."""
        net = self.ego.learner.net
        self.egos_kept.append((index, {k: v.detach().clone() for k, v in net.state_dict().items()}))
        name = f"ego_{index}.pt" if index >= 0 else "ego_start.pt"
        save_ego_policy(self.out / "pool" / name, net, self.cfg, self.scen)

    # ---- one phase ---------------------------------------------------------------------------

    def setup_phase(
        self, kind: str, length: int, env: MultiAgentMergeEnv
    ) -> tuple[JointPolicy, list]:
        """Who explores, who learns and whom the ego meets in this phase: (policy, feeds)."""
        cfg, ego, hw = self.cfg, self.ego, self.hw
        ego.exploring = hw.exploring = False  # frozen groups act greedily
        opponents: list[HighwayPolicy] = []
        if kind == "adversary":
            env.set_opponent_mix(1, 0.0)
            if isinstance(hw.learner, PPOHighwayLearner):
                hw.exploring = True  # PPO learns from its own samples
                rows = functools.partial(
                    ppo_highway_rows, learner=hw.learner, critic=cfg.ppo.critic
                )
                residual = make_driver(cfg.highway_action, hw.act, self.scen, cfg.highway_envelope)
            else:
                explore(hw, cfg.highway_sigma_start, cfg.highway_sigma_end, length // 2)
                residual = make_driver(
                    cfg.highway_action,
                    lambda obs: hw.act(obs)["action"],
                    self.scen,
                    cfg.highway_envelope,
                )
                rows = functools.partial(highway_rows, residual=residual)
            feeds = [(hw, rows)]
            opponents = [residual]
        elif kind == "pretrain":
            env.set_opponent_mix(0, 1.0)
            explore(ego, cfg.ego_sigma_start, cfg.ego_sigma_end, length // 2)
            feeds = [(ego, transition_rows)]
        else:
            env.set_opponent_mix(len(self.pool), cfg.scripted_fraction if self.pool else 1.0)
            explore(ego, cfg.ego_sigma_cotrain, cfg.ego_sigma_cotrain, 1)
            opponents = [self.snapshot(s) for s in self.pool]
            feeds = [(ego, transition_rows)]
        ego.explore_step = hw.explore_step = self.phase_done
        acting: Callable[[Tensor], Tensor] = lambda obs: ego.act(obs)["action"]  # noqa: E731
        if kind == "adversary" and self.n_rule:
            acting = rule_acting(acting, GapAcceptancePolicy(self.scen), self.n_rule)
        return JointPolicy(acting, opponents), feeds

    def on_batch(
        self, kind: str, batch: TensorDictBase, sim_steps: int, background_collisions: int
    ) -> None:
        """Count this seed's part of a batch [B, T]; log its highway group's rewards and its
        finished egos."""
        self.phase_done += sim_steps
        self.total += sim_steps
        self.ego.explore_step = self.hw.explore_step = self.phase_done
        if kind == "adversary" and self.n_rule:
            count_against_in_rule_worlds(
                batch, self.n_rule, self.cfg.fairness_weight, self.scen.interaction
            )
        if kind == "adversary" and self.cfg.ego_value_shaping > 0.0:
            shape_with_ego_value(
                batch, self.ego.learner.net, self.cfg.gamma, self.cfg.ego_value_shaping,
                PROFILES[self.cfg.profile],
            )  # fmt: skip
        self._log_highway(kind, batch, background_collisions)
        self._log_egos(kind, batch)

    def _log_highway(self, kind: str, batch: TensorDictBase, background_collisions: int) -> None:
        nxt = batch.get("next")
        valid = batch.get((GROUP, "mask")) & (batch.get("opponent") >= 0)  # [B, T, K]
        reward = nxt.get((GROUP, "reward")).squeeze(-1)  # [B, T, K]
        terms = nxt.get((GROUP, "reward_terms"))
        n_valid = int(valid.sum())
        self.hw_log.write(
            [
                self.phase_index,
                kind,
                self.total,
                n_valid,
                float(reward[valid].mean()) if n_valid else 0.0,
                *(float(terms.get(t).squeeze(-1)[valid].sum()) for t in LEARNED_HIGHWAY_TERMS),
                background_collisions,
            ]
        )

    def _log_egos(self, kind: str, batch: TensorDictBase) -> None:
        nxt = batch.get("next")
        rew = nxt.get("reward").reshape(batch.batch_size).numpy()  # [B, T]
        done = nxt.get("done").reshape(batch.batch_size).numpy()
        outcome = nxt.get("outcome").reshape(batch.batch_size).numpy()
        opp = batch.get("opponent").reshape(batch.batch_size).numpy()
        b, t_len = batch.batch_size
        first_rule = b - self.n_rule if kind == "adversary" else b  # the rule drives from here
        for t in range(t_len):
            self.ep_sum += rew[:, t]
            self.ep_steps += 1
            sim_step = self.total - (t_len - 1 - t) * b * self.k
            for w in np.flatnonzero(done[:, t]):
                ended = [
                    int(w),
                    int(opp[w, t]),
                    OUTCOME_NAMES[int(outcome[w, t])],
                    round(float(self.ep_steps[w] * self.k * self.scen.sim.dt_s), 3),
                ]
                if w >= first_rule:
                    assert self.rule_log is not None
                    self.rule_log.write([self.phase_index, kind, sim_step, *ended])
                else:
                    total = float(self.ep_sum[w])
                    self.ego_log.write([self.egos, self.phase_index, kind, sim_step, *ended, total])
                    self.egos += 1
                self.ep_sum[w] = 0.0
                self.ep_steps[w] = 0

    def end_phase(self) -> None:
        """Snapshots of the finished phase; on to the next one."""
        kind, _ = self.phases[self.phase_index]
        cfg, out, scen = self.cfg, self.out, self.scen
        if kind == "pretrain":
            save_ego_policy(out / "policy_pretrained.pt", self.ego.learner.net, cfg, scen)
        if kind in ("pretrain", "ego"):
            self.keep_ego(self.phase_index)
        if kind == "adversary":
            weights = self.hw.learner.policy_state()["net"]
            self.pool.append({k: v.detach().clone() for k, v in weights.items()})
            self.pool = self.pool[-cfg.pool_size :]
            bounds = highway_bounds(cfg)
            save_highway_policy(out / "highway_policy.pt", self.pool[-1], cfg, scen, bounds)
            save_highway_policy(
                out / "pool" / f"adversary_{self.phase_index}.pt", self.pool[-1], cfg, scen, bounds
            )
        self.phase_index += 1
        self.phase_done = 0  # the next phase's collector starts fresh egos in every world
        self.ep_sum[:] = 0.0
        self.ep_steps[:] = 0

    def snapshot(self, weights: dict[str, Tensor]) -> HighwayPolicy:
        """The greedy highway policy of pool weights of this run's highway learner."""
        return highway_snapshot(self.cfg, self.scen, weights)

    def close(self) -> None:
        for log in self._logs():
            log.close()

    # ---- the end -----------------------------------------------------------------------------

    def finish(self) -> dict[str, Any]:
        """The ego selection, the policies and the evaluation of a finished schedule."""
        from marlmerge.evaluation.rollout import evaluate_policy

        cfg, out, scen, net = self.cfg, self.out, self.scen, self.ego.learner.net
        save_ego_policy(out / "policy_last.pt", net, cfg, scen)
        evaluation: dict[str, Any] = {}
        if cfg.select_episodes > 0 and len(self.egos_kept) > 1:
            evaluation["selection"] = select_ego(self.egos_kept, self.pool, cfg, scen)
            net.load_state_dict(dict(self.egos_kept)[evaluation["selection"]["chosen_phase_index"]])
        save_ego_policy(out / "policy.pt", net, cfg, scen)
        if cfg.eval_episodes > 0:
            greedy = host_greedy(self.ego.learner)  # the selected ego, on any device
            args = (greedy, scen, cfg.eval_episodes, cfg.eval_seed, cfg.eval_worlds)
            evaluation["scripted"] = evaluate_policy(*args)
            if self.pool:
                latest = self.snapshot(self.pool[-1])
                evaluation["latest_highway_policy"] = evaluate_policy(*args, highway_policy=latest)
        files.write_text(out / "evaluation.json", json.dumps(evaluation, indent=1))
        return evaluation


def select_ego(
    candidates: list[tuple[int, dict[str, Tensor]]],
    pool: list[dict[str, Tensor]],
    cfg: CoTrainConfig,
    scen: ScenarioConfig,
) -> dict[str, Any]:
    """Score each candidate ego (phase index, weights) by its failures (collisions +
    truncations) in `cfg.select_episodes` greedy episodes against scripted traffic and against
    each pool snapshot, the same episodes for all; the fewest failures wins, the latest on ties."""
    from marlmerge.evaluation.rollout import evaluate_policy

    opponents: list[HighwayPolicy | None] = [None] + [highway_snapshot(cfg, scen, s) for s in pool]
    failures: list[list[int]] = []
    for _, weights in candidates:
        net = frozen_net(weights, ego_obs_size(scen), cfg.hidden, scen.ego.accel_bounds_mps2)
        row = []
        for opp in opponents:
            r = evaluate_policy(
                net.greedy, scen, cfg.select_episodes, cfg.select_seed, cfg.eval_worlds, opp
            )
            row.append(round((r["collision_rate"] + r["truncation_rate"]) * r["episodes"]))
        failures.append(row)
    totals = [sum(row) for row in failures]
    best = min(range(len(candidates)), key=lambda i: (totals[i], -i))
    return {
        "episodes_per_opponent": cfg.select_episodes,
        "opponents": ["scripted"] + [f"pool_{i}" for i in range(len(pool))],
        "candidate_phase_index": [i for i, _ in candidates],
        "failures": failures,
        "chosen_phase_index": candidates[best][0],
    }
