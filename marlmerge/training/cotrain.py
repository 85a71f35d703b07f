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

Several seeds in one process (`cotrain_seeds`, `marlmerge cotrain PRESET --seeds 0-2`): one env
of S x B worlds (`MultiAgentMergeEnv`'s `group_seeds`), one collector, and per seed a
`CoTrainSeed` (both groups, the pool, the kept egos, the logs) acting and learning on its slice of
the worlds; each group's seeds learn as one feed (`SeedGroups`: one fused update for the
quadratic-Q fast path, PPO seed after seed). Seed s is bit for bit the single run with
`seed = s`, written to `OUT/seed_S`; one checkpoint, `OUT/seeds_checkpoint.pt`, holds them all.

Outputs in the run folder: `policy.pt` (the selected ego, loadable by `load_policy` and the grid),
`policy_last.pt` (the ego at the end of the schedule), `policy_pretrained.pt` (the ego before any
co-training, when pretrained here), `highway_policy.pt` (the latest highway policy;
`load_highway_policy`), `pool/adversary_<i>.pt`, `pool/ego_start.pt` and `pool/ego_<i>.pt`
(the ego at the start and after each ego phase), `egos.csv`, `highway.csv`, `loss.csv`,
`checkpoint.pt`, `evaluation.json` (the selection's scores, then the selected ego against
scripted traffic and the latest highway policy).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torch import Tensor

from marlmerge.config import to_dict
from marlmerge.config.cotraining import PROFILES, CoTrainConfig
from marlmerge.config.presets import load_cotrain_config, run_scenario
from marlmerge.learners.common import resolve_device
from marlmerge.learners.highway import load_highway_policy, save_highway_policy
from marlmerge.sim.reward import INTERACTION_TERMS
from marlmerge.training.checkpoint import open_checkpoint, refuse_to_overwrite
from marlmerge.training.cotrain_groups import JointPolicy, shape_with_ego_value
from marlmerge.training.cotrain_seed import CoTrainSeed
from marlmerge.training.logs import progress_bar
from marlmerge.training.loop import (
    LearningGroup,
    RowsFn,
    make_collector,
    run_loop,
    save_checkpoint,
    set_torch_threads,
)
from marlmerge.training.seeds import CHECKPOINT_NAME, SeedGroups, check_seed_list, seed_dir
from marlmerge.views.torchrl_groups import MultiAgentMergeEnv

CHECKPOINT_VERSION = 3
"""Layout of `checkpoint.pt` (2: each group's learner, replay and generators under its name; 3:
eight reward terms, `jerk` added)."""
SEEDS_CHECKPOINT = CHECKPOINT_NAME
"""The one checkpoint of `cotrain_seeds` in `OUT` (as `train --seeds` names its own): the env
and every seed's part (`"runs"`)."""


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


class SeedsJointPolicy:
    """Collector policy of S seeds co-trained in one env: each seed's `JointPolicy` acts on its
    slice of the S x B worlds, as in its own run."""

    def __init__(self, policies: list[JointPolicy], worlds_per_seed: int) -> None:
        self.policies, self.b = policies, worlds_per_seed

    @torch.no_grad()
    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        b = self.b
        acted = [p.actions(td[j * b : (j + 1) * b]) for j, p in enumerate(self.policies)]
        for key in dict.fromkeys(k for a in acted for k in a):
            like = next(a[key] for a in acted if key in a)  # a seed without it sends zeros
            td.set(key, torch.cat([a.get(key, torch.zeros_like(like)) for a in acted]))
        return td


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
    out = Path(out_dir)
    return _run(cfg, None, out / "checkpoint.pt", resume, progress, stop_after_sim_steps)[0]


def cotrain_seeds(
    cfg: CoTrainConfig,
    seeds: list[int],
    out_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
    stop_after_sim_steps: int | None = None,
    checkpoint_name: str = SEEDS_CHECKPOINT,
) -> list[CoTrainResult]:
    """Co-train `seeds` of `cfg` in one process (`marlmerge cotrain PRESET --seeds 0-3`): one
    env of S x B worlds, each seed's worlds, groups, pool, logs and selection its own, so seed
    s is bit for bit `cotrain` with `seed = s`, written to `OUT/seed_S` as that run writes its
    folder. One checkpoint, `OUT/<checkpoint_name>`, holds them all; `resume` with the same
    seeds continues every one exactly."""
    check_seed_list(seeds)
    out = Path(out_dir)
    return _run(cfg, list(seeds), out / checkpoint_name, resume, progress, stop_after_sim_steps)


def _run(
    cfg: CoTrainConfig,
    seeds: list[int] | None,
    ckpt_path: Path,
    resume: bool,
    progress: bool,
    stop_after_sim_steps: int | None,
) -> list[CoTrainResult]:
    """One run (`seeds` None: `cfg.seed`) or several in one process, checkpointed to
    `ckpt_path` in the run's folder."""
    run_scenario(cfg)  # an unknown scenario fails before anything is written
    resolve_device(cfg.device)  # and a device this machine lacks
    out = ckpt_path.parent
    if seeds is not None:
        refuse_to_overwrite(ckpt_path, resume)
    done = ("phase_index", len(cfg.phases()))
    ckpt = open_checkpoint(cfg, ckpt_path, CHECKPOINT_VERSION, done, seeds) if resume else None
    if ckpt is not None and ckpt["phase_index"] >= len(cfg.phases()):
        finished = _finished(ckpt, seeds, out)
        if finished is not None:
            return finished
    set_torch_threads(cfg.threads)
    run = CoTrainRun(cfg, seeds, ckpt_path, ckpt, progress)
    t0 = time.perf_counter()
    killed = False
    while run.phase_index < len(run.phases) and not killed:
        killed = run.run_phase(stop_after_sim_steps)
        if not killed:
            run.end_phase()
    run.close()
    wall = time.perf_counter() - t0
    ended = run.phase_index >= len(run.phases)  # not stopped by stop_after_sim_steps
    return [
        CoTrainResult(s.out, s.total, s.egos, wall, len(s.pool), s.finish() if ended else None)
        for s in run.seeds
    ]


def _finished(
    ckpt: dict[str, Any], seeds: list[int] | None, out: Path
) -> list[CoTrainResult] | None:
    """The results of a finished and evaluated run as they are, or None (killed while it was
    evaluated: the evaluation runs again)."""
    states = [ckpt] if seeds is None else ckpt["runs"]
    folders = [out] if seeds is None else [seed_dir(out, s) for s in seeds]
    if not all((f / "evaluation.json").is_file() for f in folders):
        return None
    return [
        CoTrainResult(
            f,
            st["total"],
            st["egos"],
            0.0,
            len(st["pool"]),
            json.loads((f / "evaluation.json").read_text()),
            True,
        )  # fmt: skip
        for f, st in zip(folders, states, strict=True)
    ]


class CoTrainRun:
    """A co-training process: the worlds (one env for all its seeds), the schedule's phases
    and the checkpoints; each seed's state is a `CoTrainSeed`, which the phases step in
    lockstep."""

    def __init__(
        self,
        cfg: CoTrainConfig,
        seeds: list[int] | None,
        ckpt_path: Path,
        ckpt: dict[str, Any] | None,
        progress: bool,
    ) -> None:
        self.cfg, self.many, self.ckpt_path = cfg, seeds is not None, ckpt_path
        out = ckpt_path.parent
        overrides = {"interaction.sign": PROFILES[cfg.profile]}
        self.env = MultiAgentMergeEnv(
            cfg.scenario, num_worlds=cfg.num_worlds, seed=cfg.seed, overrides=overrides,
            group_seeds=seeds,
        )  # fmt: skip
        self.seed_list = seeds if seeds is not None else [cfg.seed]
        saved = (
            [None] * len(self.seed_list) if ckpt is None else ckpt["runs"] if self.many else [ckpt]
        )
        self.seeds = [
            CoTrainSeed(
                dataclasses.replace(cfg, seed=s),
                seed_dir(out, s) if self.many else out,
                self.env.cfg,
                st,
            )
            for s, st in zip(self.seed_list, saved, strict=True)
        ]
        self.phases = cfg.phases()
        self.resuming_mid_phase = ckpt is not None and ckpt["phase_done"] > 0
        if ckpt is not None:
            self.env.load_sim_state(ckpt["env"])
        self.parts: list[TensorDictBase] = []  # the batch's slice of each seed
        self.seed_groups: dict[str, SeedGroups] = {}  # each group's seeds, as one feed
        total_steps = sum(n for _, n in self.phases)
        self.bar = progress_bar(total_steps, self.seeds[0].total, progress, desc="cotrain")
        self.next_ckpt = self._next_checkpoint()

    @property
    def phase_index(self) -> int:
        return self.seeds[0].phase_index

    def _next_checkpoint(self) -> int:
        every = self.cfg.checkpoint_every_sim_steps
        return (self.seeds[0].total // every + 1) * every

    def checkpoint(self) -> None:
        states = [s.state_dict() for s in self.seeds]
        head = {"version": CHECKPOINT_VERSION, "config": to_dict(self.seeds[0].cfg)}
        if self.many:  # the schedule's position at the top, as a single run's
            where = {k: states[0][k] for k in ("phase_index", "phase_done", "total")}
            payload = {**head, **where, "seeds": self.seed_list, "runs": states}
        else:
            payload = {**head, **states[0]}
        save_checkpoint(self.ckpt_path, {**payload, "env": self.env.sim_state()})

    def run_phase(self, stop_after_sim_steps: int | None) -> bool:
        """Run the current phase to its end (True: stopped by `stop_after_sim_steps`)."""
        kind, length = self.phases[self.phase_index]
        n, b = len(self.seeds), self.cfg.num_worlds
        setups = [s.setup_phase(kind, length, self.env) for s in self.seeds]
        policy = setups[0][0] if n == 1 else SeedsJointPolicy([p for p, _ in setups], b)
        feeds = setups[0][1] if n == 1 else self._seed_feeds([f for _, f in setups])
        if self.resuming_mid_phase:
            self.env.resume_without_reset()
        groups = [g for s in self.seeds for g in (s.ego, s.hw)]
        collector = make_collector(
            self.env,
            policy,
            n * b * self.cfg.env_steps_per_batch,
            n * (length - self.seeds[0].phase_done),
            self.seeds[0].k,
            resumed_groups=groups if self.resuming_mid_phase else [],
        )
        self.resuming_mid_phase = False
        self._bg_before = self._background_collisions()
        killed = False

        def after_updates() -> bool:
            nonlocal killed
            first = self.seeds[0]
            if self.bar is not None:
                self.bar.update(self._last_sim_steps)
                self.bar.set_postfix(
                    phase=f"{self.phase_index + 1}/{len(self.phases)} {kind}",
                    egos=sum(s.egos for s in self.seeds),
                )
            if first.phase_done >= length:
                return True
            if first.total >= self.next_ckpt:
                self.checkpoint()
                self.next_ckpt += self.cfg.checkpoint_every_sim_steps
            killed = stop_after_sim_steps is not None and first.total >= stop_after_sim_steps
            return killed

        on_batch = functools.partial(self.on_batch, kind)
        run_loop(collector, feeds, self.seeds[0].k, on_batch, after_updates)  # type: ignore[arg-type]
        return killed

    def _seed_feeds(self, feeds: list[list[tuple[LearningGroup, RowsFn]]]) -> list:
        """The loop's feeds from each seed's (group, rows) pairs: the seeds' groups of each
        kind as one feed (`SeedGroups`: one fused update for the quadratic-Q fast path), each
        seed's rows from its slice of the batch (`on_batch` cut it)."""
        out: list = []
        for i, (group, _) in enumerate(feeds[0]):
            if group.name not in self.seed_groups:  # once per run: the groups stay the same
                same = [s.ego if group is self.seeds[0].ego else s.hw for s in self.seeds]
                self.seed_groups[group.name] = SeedGroups(same)
            rows = [f[i][1] for f in feeds]
            out.append((self.seed_groups[group.name], functools.partial(self._parts_rows, rows)))
        return out

    def _parts_rows(self, rows: list[RowsFn], batch: TensorDictBase) -> list[Tensor]:
        """Every seed's transitions, each from its slice of the batch."""
        return [r(part) for r, part in zip(rows, self.parts, strict=True)]

    def _background_collisions(self) -> np.ndarray:
        """[S] the collisions without the ego so far in each seed's worlds."""
        bg = self.env.core.state.background_collisions
        return np.asarray(bg).reshape(len(self.seeds), -1).sum(1)

    def on_batch(self, kind: str, batch: TensorDictBase, sim_steps: int) -> None:
        """Cut the batch [S x B, T] into each seed's [B, T]; each counts and logs its part."""
        n, b = len(self.seeds), self.cfg.num_worlds
        self.parts = [batch] if n == 1 else [batch[j * b : (j + 1) * b] for j in range(n)]
        self._last_sim_steps = sim_steps // n
        bg_now = self._background_collisions()
        for seed, part, bg in zip(self.seeds, self.parts, bg_now - self._bg_before, strict=True):
            seed.on_batch(kind, part, sim_steps // n, int(bg))
        self._bg_before = bg_now

    def end_phase(self) -> None:
        """Every seed's snapshots of the finished phase, then a checkpoint at the start of the
        next one."""
        for seed in self.seeds:
            seed.end_phase()
        self.checkpoint()
        self.next_ckpt = self._next_checkpoint()

    def close(self) -> None:
        for seed in self.seeds:
            seed.close()
        if self.bar is not None:
            self.bar.close()


__all__ = [
    "INTERACTION_TERMS",
    "CoTrainConfig",
    "CoTrainResult",
    "JointPolicy",
    "cotrain",
    "cotrain_seeds",
    "load_cotrain_config",
    "load_highway_policy",
    "save_highway_policy",
    "shape_with_ego_value",
]
