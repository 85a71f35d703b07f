"""Training the ego against scripted traffic (`marlmerge train`): `train()`.

The run is built from small factories and driven by the one loop of `marlmerge.training.loop`: a
torchrl `Collector` steps `BatchedMergeEnv` (B worlds, one ego each) with the learner's exploring
policy; transitions go into a torchrl `ReplayBuffer` (packed rows in a `LazyTensorStorage`); the
learner (`make_learner`: quadq, DQN or TD3, all behind the `Learner` protocol) runs the updates
owed to the new experience. The paper's schedule (Table 1): one gradient update per simulator
step, so `action_repeat` (k) updates per stored transition; with B worlds each env step stores B
transitions and owes B * k updates.

quadq's update is `FastQuadQUpdater` (hand-written gradients of `QuadraticQLoss`, Adam, compiled
with `update_path = "compiled"`) or, with `update_path = "torchrl"`, the `QuadraticQLoss`
LossModule with `torch.optim.Adam` and a hard target update: the same loss, slower. The peers
(`marlmerge.learners.dqn`) are torchrl losses with torch optimisers.
"""

from __future__ import annotations

import functools
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from marlmerge.config import ScenarioConfig, to_dict
from marlmerge.config.presets import load_train_config, resolve_config, run_scenario
from marlmerge.config.training import (
    TrainConfig,
)
from marlmerge.io import files
from marlmerge.io.policy_file import write_policy
from marlmerge.learners.base import Learner, host_greedy
from marlmerge.learners.common import resolve_device
from marlmerge.learners.loading import make_learner as make_peer_learner
from marlmerge.learners.quadq import GaussianExploration
from marlmerge.learners.quadq_learner import QuadQLearner
from marlmerge.sim import OUTCOME_SUCCESS
from marlmerge.sim.action import component_bounds
from marlmerge.training.checkpoint import open_checkpoint
from marlmerge.training.levels import LevelReplay
from marlmerge.training.logs import (
    EGO_FIELDS,
    LOSS_FIELDS,
    CsvLog,
    EgoTracker,
    RampTracker,
    progress_bar,
    tb_ego,
    tb_loss,
    tensorboard,
)
from marlmerge.training.loop import (
    GroupPolicy,
    LearningGroup,
    LoopTimes,
    make_collector,
    make_replay,
    run_loop,
    save_checkpoint,
    set_torch_threads,
    transition_rows,
)
from marlmerge.training.ramp import (
    RAMP_AGENTS,
    RampGroupPolicy,
    check_ramp_training,
    make_ramp_env,
    ramp_rows,
)
from marlmerge.training.select import Selection
from marlmerge.training.shield import (
    TrainShield,
    behind_shield,
    deployed_shield,
    make_train_shield,
    teach,
)
from marlmerge.views.torchrl_env import BatchedMergeEnv

CHECKPOINT_VERSION = 3
"""Layout of `checkpoint.pt` (2: the learner, replay and generators under `group`; 3: eight
reward terms, `jerk` added)."""


# ----------------------------------------------------------------------------------------------
# Factories: the parts of a run
# ----------------------------------------------------------------------------------------------


def make_env(cfg: TrainConfig) -> BatchedMergeEnv:
    """B worlds of the run's scenario, one ego each, seeded from `cfg.seed`; with `[levels]`
    each new road's traffic comes from the run's `LevelReplay` (`env.core.scenario_source`)."""
    return BatchedMergeEnv(
        cfg.scenario, num_worlds=cfg.num_worlds, seed=cfg.seed, scenario_source=make_levels(cfg)
    )


def make_levels(cfg: TrainConfig) -> LevelReplay | None:
    """The run's level replay (`[levels]`), its buffer seeded from `cfg.seed`; None when off."""
    if cfg.levels.replay_fraction == 0.0:
        return None
    levels = LevelReplay(cfg.levels)
    levels.seed_levels(check_levels(cfg), cfg.seed)
    return levels


def check_levels(cfg: TrainConfig) -> ScenarioConfig:
    """The run's scenario, refused if `[levels]` is on and it has no `[sample]` ranges."""
    scen = run_scenario(cfg)
    if cfg.levels.replay_fraction > 0.0 and not scen.sample.active:
        raise ValueError(
            f"levels.replay_fraction = {cfg.levels.replay_fraction} needs a scenario with "
            f"[sample] ranges; {cfg.scenario!r} has none"
        )
    return scen


def make_learner(
    cfg: TrainConfig, scen: ScenarioConfig, sample_gen: torch.Generator, obs_dim: int
) -> Learner:
    """The learner of `cfg.algorithm` (`marlmerge.learners.base.Learner`), seeded from
    `cfg.seed`; its exploration decays over `sigma_decay_fraction` of the run."""
    lo, hi = scen.ego.accel_bounds_mps2
    if cfg.algorithm != "quadq":  # networks from cfg.seed, target smoothing (td3) cfg.seed + 3
        return make_peer_learner(cfg, lo, hi, obs_dim)
    decay = max(int(cfg.sigma_decay_fraction * cfg.total_sim_steps), 1)
    bounds = component_bounds(scen)  # the acceleration's, then the join's if chosen
    noise_lo, noise_hi = (lo, hi) if len(bounds) == 1 else tuple(zip(*bounds, strict=True))
    return QuadQLearner(
        obs_dim,
        cfg.hidden,
        lo,
        hi,
        gamma=cfg.gamma,
        lr=cfg.lr,
        target_update_period=cfg.target_update_period,
        exploration=GaussianExploration(cfg.sigma_start, cfg.sigma_end, decay, noise_lo, noise_hi),
        extra_bounds=bounds[1:],
        update_path=cfg.update_path,
        updates_per_call=cfg.updates_per_call,
        seed=cfg.seed,
        sample_generator=sample_gen,
        device=cfg.device,
        expectile=cfg.td_expectile,
        lr_schedule=lr_schedule(cfg),
        flush_denormals=cfg.flush_denormals,
        peaks=cfg.peaks,
        peak_share=cfg.peak_share,
        peak_bands=cfg.peak_bands,
        peak_share_heads=cfg.peak_share_heads,
    )


def lr_schedule(cfg: TrainConfig) -> tuple[float, int]:
    """(`lr_end_fraction`, the run's updates it is reached at): the quadratic Q's decay."""
    return cfg.lr_end_fraction, max(int(cfg.total_sim_steps * cfg.updates_per_sim_step), 1)


def make_ego_group(cfg: TrainConfig, scen: ScenarioConfig, obs_dim: int) -> LearningGroup:
    """The ego's learning group: learner and replay on `cfg.device`, exploration noise
    (`seed + 1`) and minibatch sampling (`seed + 2`) from CPU generators."""
    sample_gen = torch.Generator().manual_seed(cfg.seed + 2)
    return LearningGroup(
        "ego",
        make_learner(cfg, scen, sample_gen, obs_dim),
        make_replay(cfg.replay_capacity, sample_gen, cfg.device),
        noise_gen=torch.Generator().manual_seed(cfg.seed + 1),
        sample_gen=sample_gen,
        updates_per_sim_step=cfg.updates_per_sim_step,
        batch_size=cfg.batch_size,
        learning_starts=cfg.learning_starts,
        loss_log_every=cfg.loss_log_every,
    )


@dataclass
class RunLogs:
    """The run's logs: `loss.csv`, `egos.csv` (one row per finished ego), TensorBoard."""

    loss: CsvLog
    egos: CsvLog
    tracker: EgoTracker
    tb: Any

    @classmethod
    def open(
        cls,
        out: Path,
        cfg: TrainConfig,
        step_time_s: float,
        ckpt: dict | None,
        ramp_agents: int | None = None,
    ) -> RunLogs:
        """New logs, or (resuming) the logs cut back to the checkpoint, so that the curves
        continue without overlap; with `ramp_agents` (ramp flow) a row per merging vehicle."""
        tb = tensorboard(out)
        kept_loss, kept_egos = (ckpt["loss_rows"], ckpt["ego_rows"]) if ckpt else (None, None)
        loss = CsvLog(out / "loss.csv", LOSS_FIELDS, kept_loss, tb_loss(tb))
        egos = CsvLog(out / "egos.csv", EGO_FIELDS, kept_egos, tb_ego(tb))
        tracker: EgoTracker | RampTracker = (
            EgoTracker(cfg.num_worlds, step_time_s)
            if ramp_agents is None
            else RampTracker(cfg.num_worlds, ramp_agents, step_time_s)
        )
        if ckpt is not None:
            tracker.sums[:] = ckpt["tracker_sums"]
            tracker.steps[:] = ckpt["tracker_steps"]
            tracker.egos = ckpt["egos"]
        return cls(loss, egos, tracker, tb)

    def flush(self) -> None:
        self.loss.flush()
        self.egos.flush()

    def close(self) -> None:
        self.loss.close()
        self.egos.close()
        if self.tb is not None:
            self.tb.close()


# ----------------------------------------------------------------------------------------------
# The run
# ----------------------------------------------------------------------------------------------


@dataclass
class TrainResult:
    out_dir: Path
    sim_steps: int
    updates: int
    egos: int
    wall_s: float
    update_s: float
    collect_s: float
    compile_s: float | None
    evaluation: dict[str, float] | None
    already_finished: bool = False
    """`--resume` found the run finished, with its policy and evaluation: nothing was changed."""


def check_run(cfg: TrainConfig) -> tuple[ScenarioConfig, TrainShield | None]:
    """The run's scenario and training shield; whatever the run cannot do (an unknown scenario
    or device, ramp flow it cannot train, a shape its scenario refuses) is refused here,
    before anything is written."""
    scen = run_scenario(cfg)
    resolve_device(cfg.device)
    if scen.ramp.flowing:
        check_ramp_training(cfg, scen)
    shield = make_train_shield(cfg, scen)
    if cfg.peaks > 1 and scen.ego.chooses_join:
        raise ValueError(
            f"peaks = {cfg.peaks} shapes a Q of one action component; scenario "
            f"{cfg.scenario!r} sets ego.join = {scen.ego.join!r}, a second one: use peaks = 1"
        )
    return scen, shield


def restore(
    ckpt: dict,
    ego: LearningGroup,
    env: Any,  # the ego's or the ramp flow's torchrl env
    levels: LevelReplay | None,
    selection: Selection | None,
) -> int:
    """Load a checkpoint's state into the run's parts; returns its simulator steps."""
    ego.load_state_dict(ckpt["group"])
    env.load_sim_state(ckpt["env"])
    if levels is not None:
        levels.load_state_dict(ckpt["levels"])
    if selection is not None:
        selection.load_state_dict(ckpt["select"])
    return ckpt["sim_steps"]


def train(
    cfg: TrainConfig,
    out_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
    stop_after_sim_steps: int | None = None,
) -> TrainResult:
    """Run (or resume) training; writes logs, checkpoints, the policy, the evaluation and the
    plots. `stop_after_sim_steps` ends the run abruptly at that step without checkpointing, as a
    kill would (used by the resume tests)."""
    scen, shield = check_run(cfg)
    flowing = scen.ramp.flowing  # ramp flow: one shared policy for every merging vehicle
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    done = ("sim_steps", cfg.total_sim_steps)
    ckpt = open_checkpoint(cfg, ckpt_path, CHECKPOINT_VERSION, done) if resume else None
    files.write_text(out / "config.json", json.dumps(to_dict(cfg), indent=1))
    set_torch_threads(cfg.threads)
    if ckpt is not None and ckpt["sim_steps"] >= cfg.total_sim_steps:
        return finish_resumed(cfg, out, ckpt)

    env = make_ramp_env(cfg, scen) if flowing else make_env(cfg)
    scen, k = env.cfg, env.cfg.sim.action_repeat
    ego = make_ego_group(cfg, scen, len(env.core.agent_features) if flowing else env.core.obs_size)
    teach(ego.learner, shield)
    levels = None if flowing else env.core.scenario_source
    selection = make_selection(cfg, scen)
    sim_steps = 0 if ckpt is None else restore(ckpt, ego, env, levels, selection)
    ego.explore_step = sim_steps
    logs = RunLogs.open(out, cfg, k * scen.sim.dt_s, ckpt, RAMP_AGENTS if flowing else None)
    ego.on_loss = lambda update, loss: logs.loss.write([update, sim_steps, loss])
    collector = make_collector(
        env,
        (RampGroupPolicy if flowing else GroupPolicy)(ego, shield),
        cfg.num_worlds * cfg.env_steps_per_batch,
        cfg.total_sim_steps - sim_steps,
        k,
        resumed_groups=[ego] if ckpt else [],
    )
    bar = progress_bar(cfg.total_sim_steps, sim_steps, progress)
    every = cfg.checkpoint_every_sim_steps
    next_ckpt = (sim_steps // every + 1) * every
    recent: list[dict] = []

    def checkpoint() -> None:
        logs.flush()
        state = run_state(cfg, ego, sim_steps, logs, levels, selection)
        save_checkpoint(ckpt_path, {**state, "env": env.sim_state()})

    def on_batch(batch, n_sim: int) -> None:
        nonlocal sim_steps, recent
        sim_steps += n_sim
        ego.explore_step = sim_steps
        recent = (recent + logs.tracker.update(batch, sim_steps, k, logs.egos))[-200:]
        if levels is not None:
            score_levels(levels, batch)
        show_progress(bar, n_sim, logs.tracker.egos, recent)

    def after_updates() -> bool:
        nonlocal next_ckpt
        if selection is not None and selection.due(sim_steps):
            selection.consider(sim_steps, ego.learner)
        if sim_steps >= cfg.total_sim_steps:  # the policy first: a finished checkpoint has one
            save_policies(out, cfg, scen, ego.learner, selection)
        if sim_steps >= next_ckpt or sim_steps >= cfg.total_sim_steps:
            checkpoint()
            next_ckpt += every
        if stop_after_sim_steps is not None and sim_steps >= stop_after_sim_steps:
            logs.flush()  # a kill: logs written past the last checkpoint, no new checkpoint
            return True
        return False

    t_start = time.perf_counter()
    feeds = [(ego, functools.partial(ramp_rows if flowing else ego_rows, ego))]
    times = run_loop(collector, feeds, k, on_batch, after_updates)
    wall = time.perf_counter() - t_start
    if bar is not None:
        bar.close()
    run = RunEnd(cfg, out, ego, logs, selection, sim_steps)
    return finish_run(run, wall, times, ego.learner.compile_time_s, k)


@dataclass
class RunEnd:
    """What a run's end needs of it (`finish_run`)."""

    cfg: TrainConfig
    out: Path
    ego: LearningGroup
    logs: RunLogs
    selection: Selection | None
    sim_steps: int


def finish_run(
    run: RunEnd, wall: float, times: LoopTimes, compile_s: float | None, k: int
) -> TrainResult:
    """Close the logs; if the training is complete, evaluate the greedy policy (the selected
    one with `[select]`) and draw the figures; write `timing.json`."""
    run.logs.close()
    finished = run.sim_steps >= run.cfg.total_sim_steps
    greedy = host_greedy(run.ego.learner)
    if finished and run.selection is not None:
        from marlmerge.learners.loading import load_policy

        greedy = load_policy(run.out / "policy.pt")
    evaluation = evaluate_and_plot(run.cfg, run.out, greedy) if finished else None
    result = TrainResult(
        run.out, run.sim_steps, run.ego.updates, run.logs.tracker.egos, wall, times.update_s,
        times.collect_s, compile_s, evaluation,
    )  # fmt: skip
    write_timing(run.out, result, k)
    return result


def run_state(
    cfg: TrainConfig,
    ego: LearningGroup,
    sim_steps: int,
    logs: RunLogs,
    levels: LevelReplay | None,
    selection: Selection | None,
) -> dict[str, Any]:
    """What `checkpoint.pt` holds of a run besides its env (`"env"`): the config, the learning
    group, the step count, the logs so far and the level and selection states."""
    return {
        "version": CHECKPOINT_VERSION,
        "config": to_dict(cfg),
        "algorithm": cfg.algorithm,
        "group": ego.state_dict(),
        "sim_steps": sim_steps,
        "updates": ego.updates,
        "egos": logs.tracker.egos,
        "tracker_sums": logs.tracker.sums.copy(),
        "tracker_steps": logs.tracker.steps.copy(),
        "loss_rows": logs.loss.rows,
        "ego_rows": logs.egos.rows,
        "levels": None if levels is None else levels.state_dict(),
        "select": None if selection is None else selection.state_dict(),
    }


def score_levels(levels: LevelReplay, batch) -> None:
    """The egos that finished in a batch [B, T] score the levels they drove (failure: a
    collision or a truncation)."""
    nxt = batch.get("next")
    done = nxt.get("done").reshape(-1).numpy()
    tags = nxt.get("scenario_tag").reshape(-1).numpy()[done]
    outcome = nxt.get("outcome").reshape(-1).numpy()[done]
    levels.update(tags, outcome != OUTCOME_SUCCESS)


def ego_rows(ego: LearningGroup, batch) -> torch.Tensor:
    """The ego transitions of a batch [B, T], with the action the learner replays."""
    return transition_rows(batch, ego.learner.replay_action(batch.reshape(-1)))


def make_selection(cfg: TrainConfig, scen: ScenarioConfig) -> Selection | None:
    """The run's checkpoint selection (`[select]`) on its own scenario (or `select.scenario`);
    None when off."""
    if cfg.select.every_sim_steps == 0:
        return None
    if cfg.select.scenario:
        scen = resolve_config(cfg.select.scenario)
    return Selection(cfg.select, scen, cfg.total_sim_steps, cfg.eval_worlds)


def save_policies(
    out: Path, cfg: TrainConfig, scen: ScenarioConfig, learner: Learner, selection: Selection | None
) -> None:
    """policy.pt: the last policy, or with `[select]` the selected one (then the last is
    policy_last.pt and the candidates are in selection.json)."""
    if selection is None:
        save_policy(out / "policy.pt", cfg, scen, learner)
        return
    save_policy(out / "policy.pt", cfg, scen, learner, selection.best_state)
    save_policy(out / "policy_last.pt", cfg, scen, learner)
    files.write_text(out / "selection.json", json.dumps(selection.summary(), indent=1))


def save_policy(
    path: Path,
    cfg: TrainConfig,
    scen: ScenarioConfig,
    learner: Learner,
    state: dict[str, Any] | None = None,
) -> None:
    """policy.pt (`marlmerge.io.policy_file`): what `load_policy` rebuilds the greedy policy
    from; `state` (a `policy_state`) instead of the learner's current one."""
    write_policy(
        path,
        "ego",
        cfg.algorithm,
        scen.ego.accel_bounds_mps2,
        learner.policy_state() if state is None else state,
        to_dict(cfg),
        to_dict(scen),
    )


def show_progress(bar, n_sim: int, egos: int, recent: list[dict]) -> None:
    """Advance the progress bar; success and reward of the last 200 egos."""
    if bar is None:
        return
    bar.update(n_sim)
    if recent:
        bar.set_postfix(
            egos=egos,
            success=f"{np.mean([r['outcome'] == 'success' for r in recent]):.2f}",
            reward=f"{np.mean([r['total_reward'] for r in recent]):.1f}",
        )


def write_timing(out: Path, result: TrainResult, k: int) -> None:
    """timing.json: where the run's time went (read by `benchmarks/bench_train.py`)."""
    timing = {
        "wall_s": result.wall_s,
        "update_s": result.update_s,
        "collect_s": result.collect_s,
        "compile_s": result.compile_s,
        "sim_steps": result.sim_steps,
        "updates": result.updates,
        "egos": result.egos,
        "updates_per_s": result.updates / max(result.update_s, 1e-9),
        "env_steps_per_s": result.sim_steps / k / max(result.collect_s, 1e-9),
    }
    files.write_text(out / "timing.json", json.dumps(timing, indent=1))


def evaluate_and_plot(cfg: TrainConfig, out: Path, greedy) -> dict[str, float] | None:
    """The greedy policy (behind the run's driving shield, if it has one) on the held-out roads
    (`evaluation.json`), and the run's figures. Ramp flow: the saved policy drives every ramp
    vehicle (`run_ramp_flow`) until about `eval_episodes` have merged."""
    evaluation = None
    scen = resolve_config(cfg.scenario)
    if cfg.eval_episodes > 0 and scen.ramp.flowing:
        from marlmerge.evaluation.ramp_flow import evaluate_ramp_flow

        driver = str(out) if cfg.shield == "none" else f"{cfg.algorithm}@{cfg.shield}:{out}"
        evaluation = evaluate_ramp_flow(
            scen, driver, cfg.eval_episodes, cfg.eval_seed, cfg.eval_worlds
        )
        files.write_text(out / "evaluation.json", json.dumps(evaluation, indent=1))
    elif cfg.eval_episodes > 0:
        from marlmerge.evaluation.rollout import evaluate_policy

        evaluation = evaluate_policy(
            behind_shield(greedy, deployed_shield(cfg, scen)),
            scen,
            cfg.eval_episodes,
            cfg.eval_seed,
            cfg.eval_worlds,
        )
        files.write_text(out / "evaluation.json", json.dumps(evaluation, indent=1))
    from marlmerge.training.plots import plot_run

    plot_run(out)
    return evaluation


def finish_resumed(cfg: TrainConfig, out: Path, ckpt: dict[str, Any]) -> TrainResult:
    """`--resume` of a run whose training is complete: nothing changes if its evaluation is
    there; a run killed during the final evaluation is evaluated from its saved policy."""
    from marlmerge.learners.loading import load_policy

    done = cfg.eval_episodes == 0 or (out / "evaluation.json").is_file()
    evaluation = None
    if done and cfg.eval_episodes > 0:
        evaluation = json.loads((out / "evaluation.json").read_text())
    elif not done:
        evaluation = evaluate_and_plot(cfg, out, load_policy(out / "policy.pt"))
    return TrainResult(
        out, ckpt["sim_steps"], ckpt["updates"], ckpt["egos"], 0.0, 0.0, 0.0, None, evaluation,
        already_finished=done,
    )  # fmt: skip


__all__ = [
    "TrainConfig",
    "TrainResult",
    "load_train_config",
    "make_learner",
    "save_policy",
    "train",
]
