"""Training the ego with the paper's quadratic-Q learner on torchrl: the whole loop in `train()`.

Data flows through torchrl: a `Collector` steps `BatchedMergeEnv` (B worlds, one ego each,
scripted mainline traffic) with the noisy greedy policy; transitions go into a torchrl
`ReplayBuffer` (packed rows in a `LazyTensorStorage`); minibatches go to the update. The update is
`FastQuadQUpdater` (hand-written gradients of `QuadraticQLoss`, Adam, optionally compiled) or, with
`update_path = "torchrl"`, the `QuadraticQLoss` LossModule with `torch.optim.Adam` and a hard
target update: the same loss, slower.

The paper's schedule (Table 1): one gradient update per simulator step, so `action_repeat` (k)
updates per stored transition; target copied every p updates. With B worlds, each env step stores B
transitions and owes B * k updates.

`algorithm` picks the learner: "quadq" (the paper's, above) or one of the peers in
`marlmerge.learners.baselines_rl` ("dqn" over discrete acceleration levels, "td3"), trained by the
same loop, replay, schedule, logs, checkpoints and evaluation; their gradient steps are torchrl
losses with torch optimisers, compiled when `update_path = "compiled"`.
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer

from marlmerge import files
from marlmerge.batched_env import BatchedMergeEnv
from marlmerge.config import ScenarioConfig, check_values, from_dict, read_toml, to_dict
from marlmerge.learners.base import Learner
from marlmerge.learners.baselines_rl import ALGORITHMS, LearnerPolicy
from marlmerge.learners.baselines_rl import make_learner as make_peer_learner
from marlmerge.learners.quadq import PAPER_GAMMA, GaussianExploration
from marlmerge.learners.quadq_learner import QuadQLearner
from marlmerge.pettingzoo_env import resolve_config
from marlmerge.policy_file import write_policy
from marlmerge.presets import preset_dir
from marlmerge.sim import OUTCOME_NAMES
from marlmerge.spec.observation import EGO_FEATURES
from marlmerge.spec.reward import EGO_TERMS

UPDATE_PATHS = ("compiled", "fast", "torchrl")


TRAIN_RULES = {
    **dict.fromkeys(
        [
            "total_sim_steps", "num_worlds", "env_steps_per_batch", "batch_size",
            "target_update_period", "hidden", "replay_capacity", "updates_per_call", "threads",
            "loss_log_every", "checkpoint_every_sim_steps", "eval_worlds",
            "mlp_hidden_layers", "td3_policy_delay",
        ],
        ">=1",
    ),
    **dict.fromkeys(
        [
            "seed", "updates_per_sim_step", "learning_starts", "sigma_start", "sigma_end",
            "eval_episodes", "eval_seed", "td3_target_noise", "td3_target_noise_clip",
        ],
        ">=0",
    ),
    "lr": ">0",
    "sigma_decay_fraction": "[0,1]",
    "epsilon_start": "[0,1]",
    "epsilon_end": "[0,1]",
}  # fmt: skip
"""Signs and ranges of the training numbers (`marlmerge.config.check_values`)."""


PRESET_KINDS = ("train", "cotrain")
"""What a training preset's `kind` key may say: the schema (and command) it belongs to."""


@dataclass(frozen=True)
class TrainConfig:
    """One training run. Defaults are the paper's recipe (Sec. IV.B, Table 1)."""

    KIND: ClassVar[str] = "train"
    """The `kind` a preset of this schema names."""

    name: str = "paper"
    """Run name; outputs go to `runs/<name>` unless `--out` says otherwise."""
    scenario: str = "default"
    """Scenario preset in `envs/` (or a path) the ego trains in."""
    seed: int = 0
    """Seeds the traffic, the network initialisation, exploration noise and replay sampling."""
    total_sim_steps: int = 1_600_000
    """N: simulator steps of ego experience, summed over all worlds (paper: 1.6 M)."""
    num_worlds: int = 32
    """B: independent worlds stepped together, each with its own ego, feeding one buffer."""
    env_steps_per_batch: int = 4
    """Env steps per world in each collector batch; updates follow each batch."""
    updates_per_sim_step: float = 1.0
    """Gradient updates per simulator step of experience (paper: 1, i.e. k per transition)."""
    batch_size: int = 32
    """M: minibatch size."""
    gamma: float = PAPER_GAMMA
    lr: float = 1.0e-3
    target_update_period: int = 500
    """p: the target network is a copy of the online one, refreshed every p updates."""
    hidden: int = 64
    """Hidden width of each of the A, B, C networks (two layers each)."""
    replay_capacity: int = 200_000
    """Transitions kept in the replay buffer (oldest dropped first)."""
    learning_starts: int = 1_000
    """No updates until the buffer holds this many transitions (those updates are skipped)."""
    sigma_start: float = 1.0
    """Exploration: std of the Gaussian noise on the greedy action at the start, m/s^2."""
    sigma_end: float = 0.1
    """... decaying linearly to this ..."""
    sigma_decay_fraction: float = 0.5
    """... over this fraction of `total_sim_steps`, then constant."""
    update_path: str = "compiled"
    """"compiled" (torch.compile of the fast path), "fast" (same, eager) or "torchrl"."""
    updates_per_call: int = 10
    """Updates fused into one call of the fast path; must divide `target_update_period`."""
    threads: int = 1
    """torch threads (tiny networks run fastest on one)."""
    loss_log_every: int = 5
    """Log the loss every this many updates (the paper stores it every 5 steps)."""
    checkpoint_every_sim_steps: int = 200_000
    """Checkpoint interval; a killed run resumes from its last checkpoint."""
    eval_episodes: int = 200
    """Greedy evaluation after training: this many held-out episodes ..."""
    eval_seed: int = 1_000_000
    """... on roads seeded from here on (training seeds are small numbers)."""
    eval_worlds: int = 50
    """Episodes evaluated in parallel (one seed per group of this many)."""
    algorithm: str = "quadq"
    """Learner: "quadq" (the paper's quadratic Q), "dqn" (discrete levels) or "td3". The peers
    use `hidden`, `gamma`, `lr`, `batch_size`, the schedule and the exploration decay above;
    "compiled" `update_path` compiles their gradient steps, any other runs them eagerly."""
    mlp_hidden_layers: int = 2
    """dqn/td3: hidden ReLU layers of width `hidden` in each MLP (Q-network, actor, critics)."""
    dqn_levels: int = 7
    """dqn: acceleration levels evenly spaced over the ego bounds, both ends included."""
    dqn_double: bool = False
    """dqn: double DQN target (online argmax, target value). The target is a hard copy every
    `target_update_period` updates."""
    epsilon_start: float = 1.0
    """dqn: epsilon-greedy exploration, epsilon falling linearly from this ..."""
    epsilon_end: float = 0.05
    """... to this over `sigma_decay_fraction` of `total_sim_steps`, then constant."""
    td3_tau: float = 0.005
    """td3: Polyak factor of the target networks (updated with each actor step). TD3's
    exploration is the Gaussian noise of `sigma_start`/`sigma_end`, m/s^2."""
    td3_policy_delay: int = 2
    """td3: critic updates per actor update."""
    td3_target_noise: float = 0.7
    """td3: std of the target-policy smoothing noise, m/s^2 (TD3's 0.2 x half-range 3.5) ..."""
    td3_target_noise_clip: float = 1.75
    """... clipped to +- this, m/s^2 (TD3's 0.5 x 3.5)."""

    def __post_init__(self) -> None:
        check_values(self, TRAIN_RULES)
        checks = [
            (
                self.replay_capacity >= self.batch_size,
                f"replay_capacity ({self.replay_capacity}) must be >= batch_size "
                f"({self.batch_size})",
            ),
            (
                self.algorithm in ALGORITHMS,
                f"algorithm must be one of {ALGORITHMS}, got {self.algorithm!r}",
            ),
            (
                self.update_path in UPDATE_PATHS,
                f"update_path must be one of {UPDATE_PATHS}, got {self.update_path!r}",
            ),
            (
                self.target_update_period % self.updates_per_call == 0,
                f"updates_per_call ({self.updates_per_call}) must divide target_update_period "
                f"({self.target_update_period})",
            ),
            (0.0 < self.gamma < 1.0, f"gamma must lie in (0, 1), got {self.gamma}"),
            (self.dqn_levels >= 2, f"dqn_levels must be >= 2, got {self.dqn_levels}"),
            (0.0 < self.td3_tau <= 1.0, f"td3_tau must lie in (0, 1], got {self.td3_tau}"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(msg)


def load_train_config(path: str | Path, **overrides: Any) -> TrainConfig:
    """A training preset (TOML), loaded strictly, with optional field overrides."""
    return load_preset(TrainConfig, path, **overrides)


C = TypeVar("C")


def preset_path(path: str | Path) -> Path:
    """A training preset's file: a TOML path, or a name in `trainers/`."""
    path = Path(path)
    if not path.exists():
        known = sorted(p.stem for p in preset_dir("trainers").glob("*.toml"))
        candidate = preset_dir("trainers") / f"{path.stem}.toml"
        if not candidate.exists():
            raise ValueError(f"unknown training preset {str(path)!r} (known: {', '.join(known)})")
        path = candidate
    return path


def preset_kind(path: str | Path) -> str:
    """The schema a training preset names with its `kind` key: "train" or "cotrain"."""
    path = preset_path(path)
    return _kind_of(path, read_toml(path))


def _kind_of(path: Path, data: dict[str, Any]) -> str:
    kind = data.get("kind")
    if kind not in PRESET_KINDS:
        raise ValueError(
            f"{path}: kind must name the preset's schema, one of {', '.join(PRESET_KINDS)} "
            f'(`kind = "train"` for `marlmerge train`), got {kind!r}'
        )
    return kind


def load_preset(cls: type[C], path: str | Path, **overrides: Any) -> C:
    """A preset of the dataclass `cls` (its `KIND` must be the preset's `kind`): a TOML path, or
    a name in `trainers/`; loaded strictly (unknown keys raise), `name` defaulting to the file's
    stem, with field overrides."""
    path = preset_path(path)
    data = read_toml(path)
    kind = _kind_of(path, data)
    if kind != cls.KIND:  # type: ignore[attr-defined]
        raise ValueError(f"{path} is a {kind!r} preset: run it with `marlmerge {kind} {path.stem}`")
    del data["kind"]
    data.setdefault("name", path.stem)
    data.update(overrides)
    try:
        return from_dict(cls, data)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


# ----------------------------------------------------------------------------------------------
# Policy used by the collector
# ----------------------------------------------------------------------------------------------


# ----------------------------------------------------------------------------------------------
# Logging
# ----------------------------------------------------------------------------------------------

LOSS_FIELDS = ("update", "sim_step", "loss")
EGO_FIELDS = ("ego", "sim_step", "world", "outcome", "time_s", "total_reward", *EGO_TERMS)


class CsvLog:
    """Append-only CSV that can be cut back to a checkpoint's row count on resume."""

    def __init__(
        self,
        path: Path,
        fields: tuple[str, ...],
        keep_rows: int | None,
        on_row: Callable[[list[Any]], None] | None = None,
    ):
        """A new log, or (`keep_rows` given: a resumed run) the log cut back to its first
        `keep_rows` rows, rewritten atomically. A resumed run's log must hold those rows.
        `on_row` sees every row written from now on (TensorBoard)."""
        self.path = path
        self.fields = fields
        self.on_row = on_row
        rows: list[list[str]] = []
        if keep_rows is not None:
            rows = _read_rows(path, fields)
            if len(rows) < keep_rows:
                raise ValueError(
                    f"{path}: holds {len(rows)} rows, the checkpoint needs its first {keep_rows} "
                    "(the log was deleted or cut): the run cannot be resumed exactly"
                )
            rows = rows[:keep_rows]
        text = io.StringIO()
        writer = csv.writer(text)
        writer.writerow(fields)
        writer.writerows(rows)
        files.write_text(path, text.getvalue())
        self.rows = len(rows)
        self.fh = path.open("a", newline="")
        self.writer = csv.writer(self.fh)

    def write(self, row: list[Any]) -> None:
        self.writer.writerow(row)
        self.rows += 1
        if self.on_row is not None:
            self.on_row(row)

    def flush(self) -> None:
        self.fh.flush()

    def close(self) -> None:
        self.fh.close()


class EgoTracker:
    """Sums each world's reward terms over its current ego's episode; emits a row when it ends."""

    def __init__(self, num_worlds: int, step_time_s: float):
        self.sums = np.zeros((num_worlds, len(EGO_TERMS)))  # [B, terms]
        self.steps = np.zeros(num_worlds, dtype=np.int64)  # env steps of the current ego
        self.egos = 0
        self.step_time_s = step_time_s

    def update(self, batch: TensorDictBase, sim_step_end: int, k: int, log: CsvLog) -> list[dict]:
        """batch: collector output [B, T]. Returns the finished egos' rows, in time order."""
        nxt = batch.get("next")
        terms = torch.stack([nxt.get(("reward_terms", t)) for t in EGO_TERMS], -1)
        terms = terms.reshape(*batch.batch_size, len(EGO_TERMS)).numpy()  # [B, T, terms]
        done = nxt.get("done").reshape(batch.batch_size).numpy()  # [B, T]
        outcome = nxt.get("outcome").reshape(batch.batch_size).numpy()
        b, t_len = batch.batch_size
        finished = []
        for t in range(t_len):
            self.sums += terms[:, t]
            self.steps += 1
            sim_step = sim_step_end - (t_len - 1 - t) * b * k
            for w in np.flatnonzero(done[:, t]):
                row = {
                    "ego": self.egos,
                    "sim_step": sim_step,
                    "world": int(w),
                    "outcome": OUTCOME_NAMES[int(outcome[w, t])],
                    "time_s": round(float(self.steps[w] * self.step_time_s), 3),
                    "total_reward": float(self.sums[w].sum()),
                    **{name: float(self.sums[w, i]) for i, name in enumerate(EGO_TERMS)},
                }
                log.write([row[f] for f in EGO_FIELDS])
                finished.append(row)
                self.egos += 1
                self.sums[w] = 0.0
                self.steps[w] = 0
        return finished


def _read_rows(path: Path, fields: tuple[str, ...]) -> list[list[str]]:
    """The data rows of a log written by `CsvLog` (a missing or foreign file is an error)."""
    if not path.is_file():
        raise ValueError(f"{path}: missing: the run's logs are needed to resume it exactly")
    with path.open(newline="") as fh:
        table = list(csv.reader(fh))
    if not table or tuple(table[0]) != fields:
        raise ValueError(f"{path}: not this run's log (header {table[:1]}, expected {fields})")
    return table[1:]


# ----------------------------------------------------------------------------------------------
# Factories: the parts of a run
# ----------------------------------------------------------------------------------------------


def make_learner(cfg: TrainConfig, scen: ScenarioConfig, sample_gen: torch.Generator) -> Learner:
    """The learner of `cfg.algorithm` (`marlmerge.learners.base.Learner`), seeded from
    `cfg.seed`; its exploration decays over `sigma_decay_fraction` of the run."""
    lo, hi = scen.ego.accel_bounds_mps2
    if cfg.algorithm != "quadq":  # networks from cfg.seed, target smoothing (td3) cfg.seed + 3
        return make_peer_learner(cfg, lo, hi)
    decay = max(int(cfg.sigma_decay_fraction * cfg.total_sim_steps), 1)
    return QuadQLearner(
        len(EGO_FEATURES),
        cfg.hidden,
        lo,
        hi,
        gamma=cfg.gamma,
        lr=cfg.lr,
        target_update_period=cfg.target_update_period,
        exploration=GaussianExploration(cfg.sigma_start, cfg.sigma_end, decay, lo, hi),
        update_path=cfg.update_path,
        updates_per_call=cfg.updates_per_call,
        seed=cfg.seed,
        sample_generator=sample_gen,
    )


def make_replay(cfg: TrainConfig, sample_gen: torch.Generator) -> ReplayBuffer:
    """torchrl buffer of packed transitions [obs | action | reward | terminated | next_obs]."""
    return ReplayBuffer(storage=LazyTensorStorage(cfg.replay_capacity), generator=sample_gen)


# ----------------------------------------------------------------------------------------------
# Checkpoints
# ----------------------------------------------------------------------------------------------


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write atomically (a run killed while saving keeps its previous checkpoint), as tensors
    and plain data only (`marlmerge.files`)."""
    files.save(payload, path)


def resume_config(cls: type[C], out: Path, requested: C, set_keys: Iterable[str]) -> C:
    """The config of the run in `out` that `--resume` continues. A key given with `--set` must
    agree with it (a resumed run continues that run: nothing is resumable with other values)."""
    saved = from_dict(cls, files.load(out / "checkpoint.pt", "checkpoint")["config"])
    for key in set_keys:
        if getattr(saved, key) != getattr(requested, key):
            raise ValueError(
                f"--set {key}={getattr(requested, key)!r} differs from the run being resumed "
                f"({key} = {getattr(saved, key)!r} in {out / 'checkpoint.pt'}): a resumed run "
                "continues with its own config; start a new run with --out to change it"
            )
    return saved


# ----------------------------------------------------------------------------------------------
# The loop
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


def train(
    cfg: TrainConfig,
    out_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
    stop_after_sim_steps: int | None = None,
) -> TrainResult:
    """Run (or resume) training; writes logs, checkpoints, the evaluation and the plots.

    `stop_after_sim_steps` ends the run abruptly at that step without checkpointing, as a kill
    would (used by the resume test).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    ckpt = None
    if resume:
        if not ckpt_path.exists():
            raise ValueError(f"--resume: no checkpoint at {ckpt_path}")
        ckpt = files.load(ckpt_path, "checkpoint")
        saved_cfg = from_dict(TrainConfig, ckpt["config"])
        if saved_cfg != cfg:  # a resumed run continues that run, with its own config
            differ = [k for k, v in to_dict(cfg).items() if ckpt["config"].get(k) != v]
            raise ValueError(
                f"{ckpt_path}: the run was made with other values of {', '.join(differ)}; "
                "resume it with its own config (`marlmerge train --out RUN --resume`)"
            )
    (out / "config.json").write_text(json.dumps(to_dict(cfg), indent=1))
    torch.set_num_threads(cfg.threads)

    if ckpt is not None and ckpt["sim_steps"] >= cfg.total_sim_steps:
        return _finish_resumed(cfg, out, ckpt)

    # ---- environment, learner, replay (every part from a factory; no branch per algorithm)
    env = BatchedMergeEnv(cfg.scenario, num_worlds=cfg.num_worlds, seed=cfg.seed)
    scen = env.cfg
    k = scen.sim.action_repeat
    noise_gen = torch.Generator().manual_seed(cfg.seed + 1)
    sample_gen = torch.Generator().manual_seed(cfg.seed + 2)
    learner = make_learner(cfg, scen, sample_gen)
    policy = LearnerPolicy(learner, noise_gen)
    replay = make_replay(cfg, sample_gen)

    sim_steps = updates = 0
    if ckpt is not None:
        learner.load_state_dict(ckpt["learner"])
        replay.load_state_dict(ckpt["replay"])
        sample_gen.set_state(ckpt["sample_gen"])
        env.load_sim_state(ckpt["env"])
        sim_steps, updates = ckpt["sim_steps"], ckpt["updates"]
        policy.sim_step = sim_steps

    # ---- logs (cut back to the checkpoint on resume, so the curves continue without overlap)
    tb = _tensorboard(out)
    loss_log = CsvLog(
        out / "loss.csv", LOSS_FIELDS, ckpt["loss_rows"] if ckpt else None, _tb_loss(tb)
    )
    ego_log = CsvLog(out / "egos.csv", EGO_FIELDS, ckpt["ego_rows"] if ckpt else None, _tb_ego(tb))
    tracker = EgoTracker(cfg.num_worlds, k * scen.sim.dt_s)
    if ckpt is not None:
        tracker.sums[:] = ckpt["tracker_sums"]
        tracker.steps[:] = ckpt["tracker_steps"]
        tracker.egos = ckpt["egos"]

    frames_per_batch = cfg.num_worlds * cfg.env_steps_per_batch
    remaining_frames = math.ceil((cfg.total_sim_steps - sim_steps) / k)
    remaining_frames = max(
        frames_per_batch, math.ceil(remaining_frames / frames_per_batch) * frames_per_batch
    )
    collector = Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=remaining_frames,
        auto_register_policy_transforms=False,
    )
    if ckpt is not None:  # after the collector, which runs the policy once while it sets up
        noise_gen.set_state(ckpt["noise_gen"])
    bar = _progress(cfg.total_sim_steps, sim_steps, progress)
    next_ckpt = (sim_steps // cfg.checkpoint_every_sim_steps + 1) * cfg.checkpoint_every_sim_steps
    t_start = time.perf_counter()
    update_s = collect_s = 0.0
    t_collect = time.perf_counter()
    recent: list[dict] = []

    def checkpoint() -> None:
        loss_log.flush()
        ego_log.flush()
        save_checkpoint(
            ckpt_path,
            {
                "config": to_dict(cfg),
                "algorithm": cfg.algorithm,
                "learner": learner.state_dict(),
                "replay": replay.state_dict(),
                "noise_gen": noise_gen.get_state(),
                "sample_gen": sample_gen.get_state(),
                "env": env.sim_state(),
                "sim_steps": sim_steps,
                "updates": updates,
                "egos": tracker.egos,
                "tracker_sums": tracker.sums.copy(),
                "tracker_steps": tracker.steps.copy(),
                "loss_rows": loss_log.rows,
                "ego_rows": ego_log.rows,
            },
        )

    for batch in collector:
        collect_s += time.perf_counter() - t_collect
        # ---- store transitions
        flat = batch.reshape(-1)
        nxt = flat.get("next")
        rows = torch.cat(
            [
                flat.get("observation"),
                learner.replay_action(flat),
                nxt.get("reward"),
                nxt.get("terminated").float(),
                nxt.get("observation"),
            ],
            -1,
        )
        replay.extend(rows)
        sim_steps += flat.numel() * k
        policy.sim_step = sim_steps
        recent += tracker.update(batch, sim_steps, k, ego_log)

        # ---- updates owed to the new experience (paper: one per simulator step)
        t_upd = time.perf_counter()
        owed = int(sim_steps * cfg.updates_per_sim_step) - updates
        if len(replay) < cfg.learning_starts:
            updates += owed  # skipped: too little data to learn from yet
        else:
            losses = learner.learn(replay, owed, cfg.batch_size)  # [n <= owed]
            first = (-(updates + 1)) % cfg.loss_log_every  # update n = updates + j + 1
            for j in range(first, len(losses), cfg.loss_log_every):
                loss_log.write([updates + j + 1, sim_steps, float(losses[j])])
            updates += len(losses)
        update_s += time.perf_counter() - t_upd

        if bar is not None:
            bar.update(flat.numel() * k)
            if recent:
                last = recent[-200:]
                bar.set_postfix(
                    egos=tracker.egos,
                    success=f"{np.mean([r['outcome'] == 'success' for r in last]):.2f}",
                    reward=f"{np.mean([r['total_reward'] for r in last]):.1f}",
                )
        recent = recent[-200:]
        if sim_steps >= cfg.total_sim_steps:  # the policy first: a finished checkpoint has one
            save_policy(out / "policy.pt", cfg, scen, learner)
        if sim_steps >= next_ckpt or sim_steps >= cfg.total_sim_steps:
            checkpoint()
            next_ckpt += cfg.checkpoint_every_sim_steps
        if stop_after_sim_steps is not None and sim_steps >= stop_after_sim_steps:
            loss_log.flush()  # a kill: logs written past the last checkpoint, no new checkpoint
            ego_log.flush()
            break
        t_collect = time.perf_counter()
    collector.shutdown()
    if bar is not None:
        bar.close()
    loss_log.close()
    ego_log.close()
    if tb is not None:
        tb.close()
    wall = time.perf_counter() - t_start
    finished = sim_steps >= cfg.total_sim_steps

    evaluation = None
    if finished:
        evaluation = _evaluate_and_plot(cfg, out, learner.greedy)
    result = TrainResult(
        out,
        sim_steps,
        updates,
        tracker.egos,
        wall,
        update_s,
        collect_s,
        learner.compile_time_s,
        evaluation,
    )
    (out / "timing.json").write_text(
        json.dumps(
            {
                "wall_s": wall,
                "update_s": update_s,
                "collect_s": collect_s,
                "compile_s": result.compile_s,
                "sim_steps": sim_steps,
                "updates": updates,
                "egos": tracker.egos,
                "updates_per_s": updates / max(update_s, 1e-9),
                "env_steps_per_s": sim_steps / k / max(collect_s, 1e-9),
            },
            indent=1,
        )
    )
    return result


def save_policy(path: Path, cfg: TrainConfig, scen, learner: Learner) -> None:
    """policy.pt (`marlmerge.policy_file`): what `load_policy` rebuilds the greedy policy from."""
    write_policy(
        path,
        "ego",
        cfg.algorithm,
        scen.ego.accel_bounds_mps2,
        learner.policy_state(),
        to_dict(cfg),
        to_dict(scen),
    )


def _evaluate_and_plot(cfg: TrainConfig, out: Path, greedy) -> dict[str, float] | None:
    """The greedy policy on the held-out roads (`evaluation.json`), and the run's figures."""
    evaluation = None
    if cfg.eval_episodes > 0:
        from marlmerge.evaluate import evaluate_policy

        scen = resolve_config(cfg.scenario)
        evaluation = evaluate_policy(
            greedy, scen, cfg.eval_episodes, cfg.eval_seed, cfg.eval_worlds
        )
        files.write_text(out / "evaluation.json", json.dumps(evaluation, indent=1))
    from marlmerge.plots import plot_run

    plot_run(out)
    return evaluation


def _finish_resumed(cfg: TrainConfig, out: Path, ckpt: dict[str, Any]) -> TrainResult:
    """`--resume` of a run whose training is complete: nothing changes if its evaluation is
    there; a run killed during the final evaluation is evaluated from its saved policy."""
    from marlmerge.learners.baselines_rl import load_policy

    done = cfg.eval_episodes == 0 or (out / "evaluation.json").is_file()
    evaluation = None
    if done and cfg.eval_episodes > 0:
        evaluation = json.loads((out / "evaluation.json").read_text())
    elif not done:
        evaluation = _evaluate_and_plot(cfg, out, load_policy(out / "policy.pt"))
    return TrainResult(
        out, ckpt["sim_steps"], ckpt["updates"], ckpt["egos"], 0.0, 0.0, 0.0, None, evaluation,
        already_finished=done,
    )  # fmt: skip


def _progress(total: int, initial: int, enabled: bool):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(
        total=total,
        initial=initial,
        unit="step",
        unit_scale=True,
        dynamic_ncols=True,
        desc="train",
        file=sys.stderr,
    )


def _tb_loss(tb) -> Callable[[list[Any]], None] | None:
    """TensorBoard `losses/td_loss` at each logged update (each point once)."""
    if tb is None:
        return None
    return lambda row: tb.add_scalar("losses/td_loss", float(row[2]), int(row[0]))


def _tb_ego(tb) -> Callable[[list[Any]], None] | None:
    """TensorBoard `charts/total_reward`, `charts/<term>` and `charts/success` per ego, x = the
    ego's number (as in the paper's Fig. 4; each ego once)."""
    if tb is None:
        return None

    def write(row: list[Any]) -> None:
        values = dict(zip(EGO_FIELDS, row, strict=True))
        step = int(values["ego"])
        tb.add_scalar("charts/total_reward", float(values["total_reward"]), step)
        tb.add_scalar("charts/success", float(values["outcome"] == "success"), step)
        for term in EGO_TERMS:
            tb.add_scalar(f"charts/{term}", float(values[term]), step)

    return write


def _tensorboard(out: Path):
    """A TensorBoard writer if tensorboard is installed, else None."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(out / "tb"))
