"""Many seeds in one process (`marlmerge train PRESET --seeds 0-7`): `train_seeds()`.

S independent seeds of one recipe share a process, an env and a collector:

- the env holds S x B worlds; world i of seed s is seeded as world i of a run with `seed = s`
  (`SeedSequence(s, spawn_key=(i,))`), so each seed's B worlds drive exactly the traffic its
  own run would;
- each seed keeps everything else of its own: learner, replay, exploration and sampling
  generators, logs, checkpoint selection; the policy acts on each seed's slice of the batch;
- the quadratic-Q fast path updates all seeds in one fused call
  (`marlmerge.learners.quadq_fused`); other learners update seed after seed.

Seeds are independent: seed s of a `--seeds 0-7` run is bit for bit seed s of a `--seeds s` run,
and that is bit for bit `marlmerge train --set seed=s` (`tests/test_vectorized_seeds.py`).
Each seed writes `OUT/seed_S` as a single run writes its folder (config, logs, `policy.pt`,
evaluation, figures, `timing.json` with the times of the whole process); the one checkpoint,
`OUT/seeds_checkpoint.pt`, holds the shared env and every seed's state, and `--resume` with the
same seeds continues all of them exactly. With `[levels]` each seed keeps its own level replay,
and its worlds draw their roads from it (`marlmerge.training.levels.SeedLevels`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

from marlmerge.config import to_dict
from marlmerge.config.presets import run_scenario
from marlmerge.config.training import TrainConfig
from marlmerge.io import files
from marlmerge.learners.common import resolve_device, sample_uniform
from marlmerge.learners.quadq_fused import FusedQuadQUpdates
from marlmerge.learners.quadq_learner import QuadQLearner
from marlmerge.training.checkpoint import open_checkpoint, refuse_to_overwrite, saved_config
from marlmerge.training.levels import LevelReplay, SeedLevels
from marlmerge.training.logs import progress_bar
from marlmerge.training.loop import (
    LearningGroup,
    make_collector,
    run_loop,
    save_checkpoint,
    set_torch_threads,
)
from marlmerge.training.shield import TrainShield, make_train_shield, shielded, teach
from marlmerge.training.train import (
    CHECKPOINT_VERSION,
    RunEnd,
    RunLogs,
    TrainResult,
    check_levels,
    ego_rows,
    finish_resumed,
    finish_run,
    make_ego_group,
    make_levels,
    make_selection,
    run_state,
    save_policies,
    score_levels,
    show_progress,
)
from marlmerge.views.torchrl_env import BatchedMergeEnv, seed_worlds

CHECKPOINT_NAME = "seeds_checkpoint.pt"


def seed_dir(out: Path, seed: int) -> Path:
    """The run folder of one seed (as `marlmerge sweep` names it)."""
    return out / f"seed_{seed}"


def check_seed_list(seeds: list[int]) -> None:
    """The seeds of one process (`train --seeds`, `cotrain --seeds`): distinct, none negative."""
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ValueError(f"--seeds: need distinct seeds >= 0, got {seeds}")


def check_seeds(cfg: TrainConfig, seeds: list[int]) -> None:
    """Refuse what a vectorised run cannot do (and a device this machine lacks), before any
    work."""
    resolve_device(cfg.device)
    check_seed_list(seeds)
    scen = check_levels(cfg)
    make_train_shield(cfg, scen)
    if scen.ramp.flowing:
        raise ValueError(
            f"--seeds: scenario {cfg.scenario!r} runs ramp flow (ramp.flow_vph = "
            f"{scen.ramp.flow_vph}); train its seeds one by one (marlmerge train --set seed=S) "
            "or with marlmerge sweep"
        )
    if scen.ego.chooses_join:
        raise ValueError(
            f"--seeds: scenario {cfg.scenario!r} sets ego.join = {scen.ego.join!r} (two action "
            "components), which the seeds' fused update does not take; train its seeds one by "
            "one (marlmerge train --set seed=S) or with marlmerge sweep"
        )


@dataclass
class SeedRun(RunEnd):
    """One seed of the process: its config, folder, learning group, logs, selection, step
    count, its last 200 finished egos (for the progress bar) and its level replay
    (`[levels]`)."""

    recent: list[dict] = dataclasses.field(default_factory=list)
    levels: LevelReplay | None = None


def make_seed_env(
    cfg: TrainConfig, seeds: list[int], levels: list[LevelReplay] | None = None
) -> BatchedMergeEnv:
    """S x B worlds; world i of seed s seeded as world i of a single run with `seed = s`;
    with `[levels]`, world i of seed s draws its roads from seed s's replay (`levels`). Each
    seed's worlds are one draw group (`marlmerge.sim.core.draw_groups`): they run bit for bit
    as the single run's env, whatever the other seeds' worlds do."""
    b = cfg.num_worlds
    world_seeds, groups = seed_worlds(seeds, b)
    source = None if levels is None else SeedLevels(levels, b)
    return BatchedMergeEnv(
        cfg.scenario,
        num_worlds=len(seeds) * b,
        seed=world_seeds,  # type: ignore[arg-type]
        scenario_source=source,  # type: ignore[arg-type]
        world_groups=groups,
    )


class SeedsPolicy:
    """Collector policy of S seeds: each seed's learner acts on its slice of the worlds (through
    the run's `shield`, row by row, as a single run's)."""

    def __init__(
        self, groups: list[LearningGroup], worlds_per_seed: int, shield: TrainShield | None = None
    ) -> None:
        self.groups, self.b, self.shield = groups, worlds_per_seed, shield

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        obs = td.get("observation")  # [S * B, d]
        acts = [g.act(obs[j * self.b : (j + 1) * self.b]) for j, g in enumerate(self.groups)]
        joined = {key: torch.cat([a[key] for a in acts]) for key in acts[0]}
        for key, value in shielded(self.shield, obs, joined).items():
            td.set(key, value)
        return td


class SeedGroups:
    """The learning groups of S seeds as one feed of the loop: each stores its own slice of
    the batch; the quadratic-Q fast path learns in one fused call, other learners one by one.
    Seeds that owe different updates or have made different numbers (a replay short of
    `learning_starts` in one seed but not another, as highway agents' transitions fill it at
    their own rate: the skipped updates are never made) learn one by one."""

    def __init__(self, groups: list[LearningGroup]) -> None:
        self.groups = groups
        learners = [g.learner for g in groups]
        self.fused: FusedQuadQUpdates | None = None
        if all(isinstance(le, QuadQLearner) and le.fast is not None for le in learners):
            fast = [le.fast for le in learners]  # type: ignore[union-attr]
            self.fused = FusedQuadQUpdates(fast, compile=learners[0].update_path == "compiled")

    @property
    def compile_time_s(self) -> float | None:
        if self.fused is not None:
            return self.fused.compile_time_s
        return self.groups[0].learner.compile_time_s

    def _sample(self) -> Tensor:
        """Every seed's minibatches of one fused call, each drawn from its own replay with its
        own generator (as `QuadQLearner.sample_chunk`), into one tensor [S, k, batch, row]."""
        k, bsz = self.fused.k, self.groups[0].batch_size  # type: ignore[union-attr]
        rows = None
        for j, g in enumerate(self.groups):
            drawn = sample_uniform(g.replay, k * bsz, None if rows is None else rows[j])
            if rows is None:  # the first seed's rows give the row size and the device
                rows = drawn.new_empty((len(self.groups), k * bsz, drawn.shape[-1]))
                rows[0] = drawn
        assert rows is not None
        return rows.view(len(self.groups), k, bsz, -1)

    def store(self, rows: list[Tensor], sim_steps: int) -> None:
        for group, r in zip(self.groups, rows, strict=True):
            group.store(r, sim_steps // len(self.groups))

    def learn(self) -> None:
        if self.fused is None:
            for group in self.groups:
                group.learn()
            return
        owed = [g.take_owed() for g in self.groups]
        counts = {u.num_updates for u in self.fused.updaters}  # made, not skipped
        if len(set(owed)) != 1 or len(counts) != 1:  # replays that filled at other rates
            for group, n in zip(self.groups, owed, strict=True):
                if n is not None:  # each seed's own update: the fused one's, bit for bit
                    group.record(group.learner.learn(group.replay, n, group.batch_size))
            return
        if owed[0] is None:
            return
        losses = []
        for _ in range(owed[0] // self.fused.k):
            losses.append(self.fused.step(self._sample()))
        per_seed = torch.cat(losses, 1) if losses else torch.empty(len(self.groups), 0)
        for group, seed_losses in zip(self.groups, per_seed, strict=True):
            group.record(seed_losses)


def seed_rows(runs: list[SeedRun], worlds_per_seed: int, batch: TensorDictBase) -> list[Tensor]:
    """Each seed's transitions of a batch [S * B, T]."""
    b = worlds_per_seed
    return [ego_rows(r.ego, batch[j * b : (j + 1) * b]) for j, r in enumerate(runs)]


def open_run(
    cfg: TrainConfig,
    seed: int,
    out: Path,
    obs_dim: int,
    saved: dict | None,
    levels: LevelReplay | None = None,
) -> SeedRun:
    """One seed's run (with its level replay `levels`): a fresh one, or the one `saved` (its
    part of the checkpoint) left."""
    cfg_s = dataclasses.replace(cfg, seed=seed)
    folder = seed_dir(out, seed)
    folder.mkdir(parents=True, exist_ok=True)
    files.write_text(folder / "config.json", json.dumps(to_dict(cfg_s), indent=1))
    scen = run_scenario(cfg_s)
    ego = make_ego_group(cfg_s, scen, obs_dim)
    teach(ego.learner, make_train_shield(cfg_s, scen))
    selection = make_selection(cfg_s, scen)
    logs = RunLogs.open(folder, cfg_s, scen.sim.action_repeat * scen.sim.dt_s, saved)
    run = SeedRun(cfg_s, folder, ego, logs, selection, 0, levels=levels)
    if saved is not None:
        ego.load_state_dict(saved["group"])
        run.sim_steps = saved["sim_steps"]
        if levels is not None:
            levels.load_state_dict(saved["levels"])
        if selection is not None:
            selection.load_state_dict(saved["select"])
    ego.explore_step = run.sim_steps
    ego.on_loss = lambda update, loss: logs.loss.write([update, run.sim_steps, loss])
    return run


def train_seeds(
    cfg: TrainConfig,
    seeds: list[int],
    out_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
    stop_after_sim_steps: int | None = None,
    checkpoint_name: str = CHECKPOINT_NAME,
) -> list[TrainResult]:
    """Train (or resume) `seeds` of `cfg` in one process into `OUT/seed_S`; returns one result
    per seed. `stop_after_sim_steps` ends the run abruptly there, as a kill would (tests);
    `checkpoint_name`: the checkpoint file in `OUT` (a vectorised sweep names one per group)."""
    check_seeds(cfg, seeds)  # the scenario loads, too
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / checkpoint_name
    refuse_to_overwrite(ckpt_path, resume)
    done = ("sim_steps", cfg.total_sim_steps)
    ckpt = open_checkpoint(cfg, ckpt_path, CHECKPOINT_VERSION, done, seeds) if resume else None
    set_torch_threads(cfg.threads)
    if ckpt is not None and ckpt["sim_steps"] >= cfg.total_sim_steps:
        return [
            _finished_result(seed_dir(out, s), st)
            for s, st in zip(seeds, ckpt["runs"], strict=True)
        ]
    run = SeedsRun(cfg, seeds, ckpt_path, ckpt, progress, stop_after_sim_steps)
    collector = run.collector(resumed=ckpt is not None)
    t_start = time.perf_counter()
    feeds = [(run.groups, functools.partial(seed_rows, run.runs, cfg.num_worlds))]
    times = run_loop(collector, feeds, run.k, run.on_batch, run.after_updates)  # type: ignore[arg-type]
    wall = time.perf_counter() - t_start
    if run.bar is not None:
        run.bar.close()
    return [finish_run(r, wall, times, run.groups.compile_time_s, run.k) for r in run.runs]


class SeedsRun:
    """The process of `train_seeds`: one env of every seed's worlds, each seed's `SeedRun`,
    their learning groups as one feed, the progress bar and the checkpoints."""

    def __init__(
        self,
        cfg: TrainConfig,
        seeds: list[int],
        ckpt_path: Path,
        ckpt: dict[str, Any] | None,
        progress: bool,
        stop_after_sim_steps: int | None,
    ) -> None:
        self.cfg, self.seeds, self.ckpt_path = cfg, seeds, ckpt_path
        self.stop_after_sim_steps = stop_after_sim_steps
        replays = [make_levels(dataclasses.replace(cfg, seed=s)) for s in seeds]
        self.env = make_seed_env(cfg, seeds, replays if replays[0] is not None else None)  # type: ignore[arg-type]
        obs_dim = self.env.observation_spec["observation"].shape[-1]
        saved = ckpt["runs"] if ckpt is not None else [None] * len(seeds)
        self.runs = [
            open_run(cfg, s, ckpt_path.parent, obs_dim, st, lv)
            for s, st, lv in zip(seeds, saved, replays, strict=True)
        ]
        if ckpt is not None:
            self.env.load_sim_state(ckpt["env"])
        self.k = self.env.cfg.sim.action_repeat
        self.groups = SeedGroups([r.ego for r in self.runs])
        done_steps = self.runs[0].sim_steps
        self.bar = progress_bar(cfg.total_sim_steps, done_steps, progress)
        every = cfg.checkpoint_every_sim_steps
        self.next_ckpt = (done_steps // every + 1) * every

    def collector(self, resumed: bool) -> Any:
        """The collector of the remaining steps: every seed's policy on its slice of the
        worlds (through the run's shield)."""
        cfg, n, b = self.cfg, len(self.seeds), self.cfg.num_worlds
        return make_collector(
            self.env,
            SeedsPolicy(self.groups.groups, b, make_train_shield(cfg, self.env.cfg)),
            n * b * cfg.env_steps_per_batch,
            n * (cfg.total_sim_steps - self.runs[0].sim_steps),
            self.k,
            resumed_groups=self.groups.groups if resumed else [],
        )

    def checkpoint(self) -> None:
        states = []
        for r in self.runs:
            r.logs.flush()
            states.append(run_state(r.cfg, r.ego, r.sim_steps, r.logs, r.levels, r.selection))
        payload = {**states[0], "seeds": self.seeds, "runs": states, "env": self.env.sim_state()}
        save_checkpoint(self.ckpt_path, payload)

    def on_batch(self, batch: TensorDictBase, n_sim: int) -> None:
        """Each seed counts its slice of the batch [S x B, T], logs its egos and scores its
        levels."""
        b, n_seed = self.cfg.num_worlds, n_sim // len(self.seeds)
        for j, r in enumerate(self.runs):
            r.sim_steps += n_seed
            r.ego.explore_step = r.sim_steps
            part = batch[j * b : (j + 1) * b]
            rows = r.logs.tracker.update(part, r.sim_steps, self.k, r.logs.egos)
            r.recent = (r.recent + rows)[-200:]
            if r.levels is not None:
                score_levels(r.levels, part)
        recent = [row for r in self.runs for row in r.recent]
        show_progress(self.bar, n_seed, sum(r.logs.tracker.egos for r in self.runs), recent)

    def after_updates(self) -> bool:
        """Checkpoint selection, the policies at the end, the checkpoints; True: stop."""
        cfg, steps = self.cfg, self.runs[0].sim_steps
        for r in self.runs:
            if r.selection is not None and r.selection.due(steps):
                r.selection.consider(steps, r.ego.learner)
            if steps >= cfg.total_sim_steps:
                save_policies(r.out, r.cfg, self.env.cfg, r.ego.learner, r.selection)
        if steps >= self.next_ckpt or steps >= cfg.total_sim_steps:
            self.checkpoint()
            self.next_ckpt += cfg.checkpoint_every_sim_steps
        stop = self.stop_after_sim_steps
        if stop is not None and steps >= stop:
            for r in self.runs:
                r.logs.flush()
            return True
        return False


def _finished_result(folder: Path, state: dict[str, Any]) -> TrainResult:
    """`--resume` of a finished seed: its results as they are (evaluated now if the run was
    killed during its evaluation)."""
    return finish_resumed(saved_config(TrainConfig, state["config"]), folder, state)
