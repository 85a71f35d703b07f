"""Co-training of learned highway agents and the ego: alternating phases on `MultiAgentMergeEnv`.

Two agent groups learn, each a `LearningGroup` of `marlmerge.training.loop` with its own
learner, torchrl `ReplayBuffer` and seeded generators, trained by the one loop (`run_loop`) once
per phase: the ego with the paper's quadratic-Q learner (`QuadQLearner`), the highway group with
it too or, with `highway_algorithm = "ppo"`, with IPPO / MAPPO (`PPOHighwayLearner`, `[ppo]`):

- `"ego"`: the ramp vehicle (observation [B, d]: 7 features, 16 in the extended layout;
  acceleration in the ego bounds);
- `"highway"`: one policy shared by the K highway agents of every world (observation [B, K, 12],
  acceleration in the vehicle limits); only agents that act (mask) give transitions, an agent that
  leaves the road ends its own episode (terminal), the end of the merge truncates it.

The schedule (`CoTrainConfig.phases()`), one torchrl `Collector` per phase:

    pretrain   the ego learns against scripted traffic (skipped when `ego_init` names a policy)
    adversary  the highway group learns against the frozen greedy ego; every world's K agents are
               the learning policy (with exploration noise). At the end its weights join the pool.
    ego        the ego learns against frozen opponents: each ego meets scripted traffic with
               probability `scripted_fraction`, else a snapshot drawn uniformly from the pool,
               so it does not forget ordinary traffic.
    (adversary, ego) x rounds

The highway reward is its own driving reward plus the interaction term of `InteractionConfig`
(`profile = "adversarial"`: +, `"cooperative"`: -). Everything is checkpointed (both groups'
weights, targets, optimisers and replays, the pool, the worlds and every generator) at
`checkpoint_every_sim_steps` and at every phase end; `resume=True` continues from there.

The quadratic-Q ego does not improve monotonically from phase to phase (one ego phase can leave
it weaker against some opponents than the one before). At the end every ego of the run (the
starting ego and the ego after each ego phase) is scored on greedy episodes against scripted
traffic and against every snapshot of the run's own pool (`select_episodes`), and the one with the
fewest failures becomes `policy.pt`: model selection on the training opponents, never on held-out
ones.

Outputs in the run folder: `policy.pt` (the selected ego, loadable by `load_policy` and the grid),
`policy_last.pt` (the ego at the end of the schedule), `policy_pretrained.pt` (the ego before any
co-training, when pretrained here), `highway_policy.pt` (the latest highway policy;
`load_highway_policy`), `pool/adversary_<i>.pt`, `pool/ego_start.pt` and `pool/ego_<i>.pt`
(the ego at the start and after each ego phase), `egos.csv`, `highway.csv`, `loss.csv`,
`checkpoint.pt`, `evaluation.json` (the selection's scores, then the selected ego against
scripted traffic and the latest highway policy).
"""

from __future__ import annotations

import functools
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torch import Tensor

from marlmerge.config import ScenarioConfig, to_dict
from marlmerge.config.cotraining import PROFILES, CoTrainConfig
from marlmerge.config.presets import load_cotrain_config, run_scenario
from marlmerge.io import files
from marlmerge.io.policy_file import read_policy, write_policy
from marlmerge.learners.highway import (
    OFFSET_BOUNDS_MPS2,
    HighwayPolicy,
    ResidualHighwayPolicy,
    frozen_net,
    load_highway_policy,
    make_driver,
    save_highway_policy,
    snapshot_policy,
)
from marlmerge.learners.ppo import PPOHighwayLearner, critic_observation, critic_size
from marlmerge.learners.quadq import GaussianExploration, QuadraticQNet
from marlmerge.learners.quadq_learner import QuadQLearner
from marlmerge.sim import OUTCOME_NAMES
from marlmerge.sim.observation import HIGHWAY_FEATURES, ego_obs_size
from marlmerge.sim.reward import INTERACTION_TERMS, LEARNED_HIGHWAY_TERMS
from marlmerge.training.checkpoint import open_checkpoint
from marlmerge.training.logs import CsvLog, progress_bar
from marlmerge.training.loop import (
    LearningGroup,
    make_collector,
    make_replay,
    run_loop,
    save_checkpoint,
    set_torch_threads,
    transition_rows,
)
from marlmerge.views.torchrl_groups import GROUP, MultiAgentMergeEnv

CHECKPOINT_VERSION = 3
"""Layout of `checkpoint.pt` (2: each group's learner, replay and generators under its name; 3:
eight reward terms, `jerk` added)."""


# ----------------------------------------------------------------------------------------------
# Collector policy: both groups at once
# ----------------------------------------------------------------------------------------------


class JointPolicy:
    """Sets the ego's `"action"` and the highway group's `("highway", "action")`.

    ego(obs [B, d]) -> [B, 1]; highway[o](obs [n, K, 12]) -> [n, K, 1] for the worlds whose
    `"opponent"` is o (worlds with -1 are scripted: their actions are ignored, zeros are sent).
    A highway policy may return a dict instead: `"action"` and what else its learner keeps from
    acting (PPO's pre-squash sample `"z"`), each [n, K, m], set under `("highway", key)`.
    """

    def __init__(
        self,
        ego: Callable[[Tensor], Tensor],
        highway: list[Callable[[Tensor], Tensor | dict[str, Tensor]]],
    ) -> None:
        self.ego = ego
        self.highway = highway

    @torch.no_grad()
    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        td.set("action", self.ego(td.get("observation")))
        obs = td.get((GROUP, "observation"))  # [B, K, 12]
        opp = td.get("opponent").reshape(-1)  # [B]
        out: dict[str, Tensor] = {"action": torch.zeros(*obs.shape[:-1], 1)}
        for o in torch.unique(opp).tolist():
            if o >= 0:
                sel = opp == o
                acted = self.highway[o](obs[sel])
                for key, value in (acted if isinstance(acted, dict) else {"action": acted}).items():
                    out.setdefault(key, torch.zeros(*obs.shape[:-1], value.shape[-1]))[sel] = value
        for key, value in out.items():
            td.set((GROUP, key), value)
        return td


# ----------------------------------------------------------------------------------------------
# Saving and loading policies
# ----------------------------------------------------------------------------------------------


def save_ego_policy(path: Path, net: QuadraticQNet, cfg: CoTrainConfig, scen: ScenarioConfig):
    """The ego in the `policy.pt` format of `train.py` (readable by `load_policy`, the grid)."""
    write_policy(
        path,
        "ego",
        "quadq",
        (net.action_low, net.action_high),
        {"net": net.state_dict(), "hidden": cfg.hidden},
        to_dict(cfg),
        to_dict(scen),
    )


# ----------------------------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------------------------

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


@dataclass
class CoTrainResult:
    out_dir: Path
    sim_steps: int
    egos: int
    wall_s: float
    pool_size: int
    evaluation: dict[str, Any] | None
    already_finished: bool = False
    """`--resume` found the run finished and evaluated: nothing was changed."""


def make_group(
    cfg: CoTrainConfig,
    name: str,
    obs_dim: int,
    bounds: tuple[float, float],
    seed: int,
    updates_per_sim_step: float,
    init_weights: dict[str, Tensor] | None = None,
) -> LearningGroup:
    """A quadratic-Q learning group: network from `seed`, exploration noise `seed + 1`,
    minibatches `seed + 2`; it explores only in the phases that say so (`explore`)."""
    sample_gen = torch.Generator().manual_seed(seed + 2)
    learner = QuadQLearner(
        obs_dim,
        cfg.hidden,
        *bounds,
        gamma=cfg.gamma,
        lr=cfg.lr,
        target_update_period=cfg.target_update_period,
        exploration=GaussianExploration(0.0, 0.0, 1, *bounds),
        update_path=cfg.update_path,
        updates_per_call=cfg.updates_per_call,
        seed=seed,
        sample_generator=sample_gen,
        init_weights=init_weights,
    )
    return LearningGroup(
        name,
        learner,
        make_replay(cfg.replay_capacity, sample_gen),
        noise_gen=torch.Generator().manual_seed(seed + 1),
        sample_gen=sample_gen,
        updates_per_sim_step=updates_per_sim_step,
        batch_size=cfg.batch_size,
        learning_starts=cfg.learning_starts,
        loss_log_every=cfg.loss_log_every,
        exploring=False,
    )


def make_ppo_group(cfg: CoTrainConfig, obs_dim: int, ego_dim: int, k: int, seed: int):
    """The highway group with the PPO learner of `[ppo]` (networks from `seed`, exploration
    noise `seed + 1`, minibatch order `seed + 2`); it always samples while it learns."""
    p = cfg.ppo
    learner = PPOHighwayLearner(
        obs_dim,
        critic_size(obs_dim, ego_dim, k, p.critic),
        cfg.hidden,
        *highway_bounds(cfg),
        gamma=cfg.gamma,
        lmbda=p.gae_lambda,
        lr=p.lr,
        clip_epsilon=p.clip_epsilon,
        entropy_coeff=p.entropy_coeff,
        critic_coeff=p.critic_coeff,
        epochs=p.epochs,
        minibatches=p.minibatches,
        max_grad_norm=p.max_grad_norm,
        init_std=p.init_std,
        seed=seed,
    )
    sample_gen = torch.Generator().manual_seed(seed + 2)
    rollout = cfg.num_worlds * cfg.env_steps_per_batch * k  # agent steps of one batch, at most
    return LearningGroup(
        GROUP,
        learner,
        make_replay(rollout, sample_gen),
        noise_gen=torch.Generator().manual_seed(seed + 1),
        sample_gen=sample_gen,
        updates_per_sim_step=0.0,
        batch_size=cfg.batch_size,
        learning_starts=0,
        loss_log_every=1,
        exploring=False,
    )


def highway_bounds(cfg: CoTrainConfig) -> tuple[float, float]:
    """What the highway learner's action is squashed into: the adjustment's m/s^2 or the
    desired-speed factor's range (`CoTrainConfig.highway_action`)."""
    if cfg.highway_action == "desired_speed":
        return cfg.highway_speed_factor_bounds
    return OFFSET_BOUNDS_MPS2


def highway_snapshot(
    cfg: CoTrainConfig, scen: ScenarioConfig, weights: dict[str, Tensor]
) -> HighwayPolicy:
    """The greedy highway policy of pool weights of `cfg`'s highway learner and action."""
    return snapshot_policy(
        weights,
        cfg.hidden,
        scen,
        highway_bounds(cfg),
        cfg.highway_algorithm,
        cfg.highway_action,
        cfg.highway_envelope,
    )


def explore(group: LearningGroup, start: float, end: float, decay_sim_steps: int) -> None:
    """The group explores this phase: Gaussian noise whose std falls linearly from `start` to
    `end` m/s^2 over `decay_sim_steps` of the phase (`explore_step`), then constant."""
    net = group.learner.net  # type: ignore[attr-defined]
    group.learner.exploration = GaussianExploration(  # type: ignore[attr-defined]
        start, end, max(decay_sim_steps, 1), net.action_low, net.action_high
    )
    group.exploring = start > 0.0 or end > 0.0


def ego_init_weights(cfg: CoTrainConfig, scen: ScenarioConfig) -> dict[str, Tensor] | None:
    """The network weights of `cfg.ego_init` (checked against the run's settings), or None."""
    if not cfg.ego_init:
        return None
    saved = read_policy(cfg.ego_init, "ego")
    if saved["algorithm"] != "quadq":
        raise ValueError(f"ego_init {cfg.ego_init!r} is not a quadratic-Q policy")
    hidden = saved["policy_state"]["hidden"]
    if hidden != cfg.hidden:
        raise ValueError(f"ego_init {cfg.ego_init!r} has hidden={hidden}, not {cfg.hidden}")
    if tuple(saved["action_bounds_mps2"]) != tuple(scen.ego.accel_bounds_mps2):
        raise ValueError(
            f"ego_init {cfg.ego_init!r} acts in {saved['action_bounds_mps2']} m/s^2, the "
            f"scenario's ego in {scen.ego.accel_bounds_mps2}"
        )
    return saved["policy_state"]["net"]


def highway_rows(batch: TensorDictBase, residual: ResidualHighwayPolicy) -> Tensor:
    """The learning highway agents' transitions of a batch [B, T, K]: acting agents only; an
    agent leaving downstream is dropped (an absorbing 0 would pay agents to race off the road), a
    collision is terminal with its penalty. The action is the adjustment the net learns (the
    applied acceleration, after clipping, minus the IDM part)."""
    nxt = batch.get("next")
    valid = batch.get((GROUP, "mask")) & (batch.get("opponent") >= 0)  # [B, T, K]
    keep = valid & ~nxt.get((GROUP, "exited"))
    obs = batch.get((GROUP, "observation"))[keep]
    return torch.cat(
        [
            obs,
            batch.get((GROUP, "action"))[keep] - residual.base(obs),
            nxt.get((GROUP, "reward"))[keep],
            nxt.get((GROUP, "left_road"))[keep].float().unsqueeze(-1),
            nxt.get((GROUP, "observation"))[keep],
        ],
        -1,
    )


def shape_with_ego_value(
    batch: TensorDictBase, net: QuadraticQNet, gamma: float, weight: float, sign: float
) -> Tensor:
    """Add `CoTrainConfig.ego_value_shaping` to the highway group's reward of a batch [B, T]
    in place: `sign * weight * (V(s) - gamma * (1 - terminated) * V(s'))` for every agent of
    the world, V = the ego network's max_a Q (C(s)) on the ego's observations. Returns the
    shaping [B, T, 1]."""
    nxt = batch.get("next")
    with torch.no_grad():
        value = net.max_value(batch.get("observation"))  # [B, T, 1]
        next_value = net.max_value(nxt.get("observation"))  # [B, T, 1]
    not_term = (~nxt.get("terminated")).to(value.dtype)  # [B, T, 1]
    shaping = sign * weight * (value - gamma * not_term * next_value)  # [B, T, 1]
    reward = nxt.get((GROUP, "reward"))  # [B, T, K, 1]
    nxt.set((GROUP, "reward"), reward + shaping.unsqueeze(-2).to(reward.dtype))
    return shaping


def ppo_highway_rows(batch: TensorDictBase, learner: PPOHighwayLearner, critic: str) -> Tensor:
    """The learning highway agents' rollout of a batch [B, T, K] as PPO rows (GAE advantages
    per agent slot; `PPOHighwayLearner.rollout_rows`), from the pre-squash samples `z` the
    policy acted with; `critic` ("local" / "central") is the learner's critic input."""
    nxt = batch.get("next")
    obs, next_obs = batch.get((GROUP, "observation")), nxt.get((GROUP, "observation"))
    valid = batch.get((GROUP, "mask")) & (batch.get("opponent") >= 0)  # [B, T, K]
    left, exited = nxt.get((GROUP, "left_road")), nxt.get((GROUP, "exited"))
    world_done = nxt.get("done").expand_as(valid)  # [B, T, 1] -> [B, T, K]
    return learner.rollout_rows(
        obs,
        critic_observation(obs, batch.get("observation"), critic),
        batch.get((GROUP, "z")),
        nxt.get((GROUP, "reward")),
        critic_observation(next_obs, nxt.get("observation"), critic),
        valid,
        left | world_done,
        left & ~exited,
        exited,
    )


def cotrain(
    cfg: CoTrainConfig,
    out_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
    stop_after_sim_steps: int | None = None,
) -> CoTrainResult:
    """Run (or resume) the co-training schedule of `cfg`; see the module docstring.

    `stop_after_sim_steps` ends the run abruptly at that total step count, as a kill would.
    """
    run_scenario(cfg)  # an unknown scenario fails before anything is written
    out = Path(out_dir)
    ckpt = None
    if resume:
        done = ("phase_index", len(cfg.phases()))
        ckpt = open_checkpoint(cfg, out / "checkpoint.pt", CHECKPOINT_VERSION, done)
    if ckpt is not None and ckpt["phase_index"] >= len(cfg.phases()):
        if (out / "evaluation.json").is_file():  # finished and evaluated: nothing to do
            evaluation = json.loads((out / "evaluation.json").read_text())
            return CoTrainResult(
                out, ckpt["total"], ckpt["egos"], 0.0, len(ckpt["pool"]), evaluation, True
            )
    (out / "pool").mkdir(parents=True, exist_ok=True)
    files.write_text(out / "config.json", json.dumps(to_dict(cfg), indent=1))
    set_torch_threads(cfg.threads)
    run = CoTrainRun(cfg, out, ckpt, progress)
    t0 = time.perf_counter()
    killed = False
    while run.phase_index < len(run.phases) and not killed:
        killed = run.run_phase(stop_after_sim_steps)
        if not killed:
            run.end_phase()
    run.close()
    wall = time.perf_counter() - t0
    evaluation = run.finish() if run.phase_index >= len(run.phases) else None
    return CoTrainResult(out, run.total, run.egos, wall, len(run.pool), evaluation)


class CoTrainRun:
    """The state of a co-training run (both groups, the pool, the schedule's position, the
    worlds and the logs), its phases and its checkpoints."""

    def __init__(
        self, cfg: CoTrainConfig, out: Path, ckpt: dict[str, Any] | None, progress: bool
    ) -> None:
        self.cfg, self.out = cfg, out
        self.env = MultiAgentMergeEnv(
            cfg.scenario,
            num_worlds=cfg.num_worlds,
            seed=cfg.seed,
            overrides={"interaction.sign": PROFILES[cfg.profile]},
        )
        self.scen = scen = self.env.cfg
        self.k = scen.sim.action_repeat
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
        self.resuming_mid_phase = ckpt is not None and ckpt["phase_done"] > 0
        if ckpt is not None:
            self._restore(ckpt)
        rows = (ckpt["ego_rows"], ckpt["hw_rows"], ckpt["loss_rows"]) if ckpt else (None,) * 3
        self.ego_log = CsvLog(out / "egos.csv", EGO_LOG_FIELDS, rows[0])
        self.hw_log = CsvLog(out / "highway.csv", HIGHWAY_LOG_FIELDS, rows[1])
        self.loss_log = CsvLog(out / "loss.csv", LOSS_LOG_FIELDS, rows[2])
        for group in (self.ego, self.hw):
            group.on_loss = functools.partial(self._log_loss, group.name)
        total_steps = sum(n for _, n in self.phases)
        self.bar = progress_bar(total_steps, self.total, progress, desc="cotrain")
        self.next_ckpt = self._next_checkpoint()
        if cfg.ego_init and ckpt is None:
            self.keep_ego(-1)  # the starting ego is a candidate too

    def _restore(self, ckpt: dict[str, Any]) -> None:
        self.ego.load_state_dict(ckpt["ego"])
        self.hw.load_state_dict(ckpt["highway"])
        self.pool, self.egos_kept = ckpt["pool"], ckpt["egos_kept"]
        self.phase_index, self.phase_done = ckpt["phase_index"], ckpt["phase_done"]
        self.total, self.egos = ckpt["total"], ckpt["egos"]
        self.env.load_sim_state(ckpt["env"])
        self.ep_sum[:] = ckpt["ep_sum"]
        self.ep_steps[:] = ckpt["ep_steps"]

    def _next_checkpoint(self) -> int:
        every = self.cfg.checkpoint_every_sim_steps
        return (self.total // every + 1) * every

    def _log_loss(self, group: str, update: int, loss: float) -> None:
        self.loss_log.write([group, update, self.total, loss])

    def checkpoint(self) -> None:
        for log in (self.ego_log, self.hw_log, self.loss_log):
            log.flush()
        save_checkpoint(
            self.out / "checkpoint.pt",
            {
                "version": CHECKPOINT_VERSION,
                "config": to_dict(self.cfg),
                "ego": self.ego.state_dict(),
                "highway": self.hw.state_dict(),
                "pool": self.pool,
                "egos_kept": self.egos_kept,
                "phase_index": self.phase_index,
                "phase_done": self.phase_done,
                "total": self.total,
                "egos": self.egos,
                "env": self.env.sim_state(),
                "ep_sum": self.ep_sum.copy(),
                "ep_steps": self.ep_steps.copy(),
                "ego_rows": self.ego_log.rows,
                "hw_rows": self.hw_log.rows,
                "loss_rows": self.loss_log.rows,
            },
        )

    def keep_ego(self, index: int) -> None:
        """The current ego becomes a candidate of the final selection (and `pool/ego_*.pt`)."""
        net = self.ego.learner.net
        self.egos_kept.append((index, {k: v.detach().clone() for k, v in net.state_dict().items()}))
        name = f"ego_{index}.pt" if index >= 0 else "ego_start.pt"
        save_ego_policy(self.out / "pool" / name, net, self.cfg, self.scen)

    # ---- one phase ---------------------------------------------------------------------------

    def setup_phase(self, kind: str, length: int) -> tuple[JointPolicy, list]:
        """Who explores, who learns and whom the ego meets in this phase: (policy, feeds)."""
        cfg, env, ego, hw = self.cfg, self.env, self.ego, self.hw
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
        return JointPolicy(lambda obs: ego.act(obs)["action"], opponents), feeds

    def run_phase(self, stop_after_sim_steps: int | None) -> bool:
        """Run the current phase to its end (True: stopped by `stop_after_sim_steps`)."""
        kind, length = self.phases[self.phase_index]
        policy, feeds = self.setup_phase(kind, length)
        if self.resuming_mid_phase:
            self.env.resume_without_reset()
        collector = make_collector(
            self.env,
            policy,
            self.cfg.num_worlds * self.cfg.env_steps_per_batch,
            length - self.phase_done,
            self.k,
            resumed_groups=[self.ego, self.hw] if self.resuming_mid_phase else [],
        )
        self.resuming_mid_phase = False
        self._bg_before = self.env.core.state.background_collisions.sum()
        killed = False

        def after_updates() -> bool:
            nonlocal killed
            if self.bar is not None:
                self.bar.update(self._last_sim_steps)
                self.bar.set_postfix(
                    phase=f"{self.phase_index + 1}/{len(self.phases)} {kind}", egos=self.egos
                )
            if self.phase_done >= length:
                return True
            if self.total >= self.next_ckpt:
                self.checkpoint()
                self.next_ckpt += self.cfg.checkpoint_every_sim_steps
            killed = stop_after_sim_steps is not None and self.total >= stop_after_sim_steps
            return killed

        run_loop(collector, feeds, self.k, functools.partial(self.on_batch, kind), after_updates)
        return killed

    def on_batch(self, kind: str, batch: TensorDictBase, sim_steps: int) -> None:
        """Count the batch's steps; log the highway group's rewards and the finished egos."""
        self._last_sim_steps = sim_steps
        self.phase_done += sim_steps
        self.total += sim_steps
        self.ego.explore_step = self.hw.explore_step = self.phase_done
        if kind == "adversary" and self.cfg.ego_value_shaping > 0.0:
            shape_with_ego_value(
                batch, self.ego.learner.net, self.cfg.gamma, self.cfg.ego_value_shaping,
                PROFILES[self.cfg.profile],
            )  # fmt: skip
        self._log_highway(kind, batch)
        self._log_egos(kind, batch)

    def _log_highway(self, kind: str, batch: TensorDictBase) -> None:
        nxt = batch.get("next")
        valid = batch.get((GROUP, "mask")) & (batch.get("opponent") >= 0)  # [B, T, K]
        reward = nxt.get((GROUP, "reward")).squeeze(-1)  # [B, T, K]
        terms = nxt.get((GROUP, "reward_terms"))
        n_valid = int(valid.sum())
        bg_now = self.env.core.state.background_collisions.sum()
        self.hw_log.write(
            [
                self.phase_index,
                kind,
                self.total,
                n_valid,
                float(reward[valid].mean()) if n_valid else 0.0,
                *(float(terms.get(t).squeeze(-1)[valid].sum()) for t in LEARNED_HIGHWAY_TERMS),
                int(bg_now - self._bg_before),
            ]
        )
        self._bg_before = bg_now

    def _log_egos(self, kind: str, batch: TensorDictBase) -> None:
        nxt = batch.get("next")
        rew = nxt.get("reward").reshape(batch.batch_size).numpy()  # [B, T]
        done = nxt.get("done").reshape(batch.batch_size).numpy()
        outcome = nxt.get("outcome").reshape(batch.batch_size).numpy()
        opp = batch.get("opponent").reshape(batch.batch_size).numpy()
        b, t_len = batch.batch_size
        for t in range(t_len):
            self.ep_sum += rew[:, t]
            self.ep_steps += 1
            for w in np.flatnonzero(done[:, t]):
                self.ego_log.write(
                    [
                        self.egos,
                        self.phase_index,
                        kind,
                        self.total - (t_len - 1 - t) * b * self.k,
                        int(w),
                        int(opp[w, t]),
                        OUTCOME_NAMES[int(outcome[w, t])],
                        round(float(self.ep_steps[w] * self.k * self.scen.sim.dt_s), 3),
                        float(self.ep_sum[w]),
                    ]
                )
                self.egos += 1
                self.ep_sum[w] = 0.0
                self.ep_steps[w] = 0

    def end_phase(self) -> None:
        """Snapshots of the finished phase, then a checkpoint at the start of the next one."""
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
        self.checkpoint()
        self.next_ckpt = self._next_checkpoint()

    def snapshot(self, weights: dict[str, Tensor]) -> HighwayPolicy:
        """The greedy highway policy of pool weights of this run's highway learner."""
        return highway_snapshot(self.cfg, self.scen, weights)

    def close(self) -> None:
        for log in (self.ego_log, self.hw_log, self.loss_log):
            log.close()
        if self.bar is not None:
            self.bar.close()

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
            args = (net.greedy, scen, cfg.eval_episodes, cfg.eval_seed, cfg.eval_worlds)
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


__all__ = [
    "INTERACTION_TERMS",
    "CoTrainConfig",
    "CoTrainResult",
    "JointPolicy",
    "cotrain",
    "load_cotrain_config",
    "load_highway_policy",
    "save_highway_policy",
]
