"""The one training loop and the parts it is built from.

A run is a collector stepping an env with a policy, and one or more learning groups (a
`Learner` with its replay and the updates it owes). `run_loop` is the loop every run uses:
`marlmerge.training.train` for the ego against scripted traffic, `marlmerge.training.cotrain`
once per phase:

    for batch in collector:                        # [B, T] env steps of B worlds
        on_batch(batch, sim_steps)                 # count the steps, log finished episodes
        for group, rows in feeds:                  # the groups learning in this run or phase
            group.store(rows(batch), sim_steps)    # packed transitions into its replay
            group.learn()                          # the updates owed: updates_per_sim_step each
        if after_updates(): break                  # progress, checkpoints, the end

It has no branch per algorithm or per group: a learner only meets it through the `Learner`
protocol (`marlmerge.learners.base`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numba
import torch
from tensordict import TensorDictBase
from torch import Tensor
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer

from marlmerge.io import files
from marlmerge.learners.base import Learner
from marlmerge.training.shield import SHIELD_COST, TrainShield, shielded

RowsFn = Callable[[TensorDictBase], Tensor]
"""Collector batch [B, T] -> packed transitions [n, obs | action | reward | terminated | next]."""


def set_torch_threads(n: int) -> None:
    """Run torch on `n` threads for the rest of the process.

    Numba's OpenMP thread pool, started by the first core of `PARALLEL_MIN_WORLDS` worlds or
    more (`marlmerge.sim.core`), sets the OpenMP runtime's thread count that torch reads too: a
    `torch.set_num_threads(1)` made before it would be undone, and the updates would run on
    every core, slower (`docs/scale-out.md`). So the pool is started first (once per process).
    """
    numba.get_num_threads()  # starts Numba's threading layer
    torch.set_num_threads(n)


def make_replay(
    capacity: int, sample_gen: torch.Generator, device: torch.device | str = "cpu"
) -> ReplayBuffer:
    """torchrl buffer of packed transitions [obs | action | reward | terminated | next_obs],
    stored on `device`; minibatch indices come from `sample_gen` (a CPU generator)."""
    return ReplayBuffer(storage=LazyTensorStorage(capacity, device=device), generator=sample_gen)


def replay_to(replay: ReplayBuffer, device: torch.device) -> None:
    """Put a loaded replay's storage on `device` (torchrl loads a checkpoint's storage where the
    checkpoint held it: on the CPU)."""
    storage = replay._storage
    rows = getattr(storage, "_storage", None)
    if isinstance(rows, Tensor) and rows.device != device:
        storage._storage = rows.to(device)


@dataclass
class LearningGroup:
    """One learning group of a run: a learner, its replay, its generators and the bookkeeping
    of the updates it owes (`updates_per_sim_step` per simulator step of its experience).

    `exploring` and `explore_step` (the step of the exploration schedule) are set by the run;
    `on_loss(update, loss)` sees every `loss_log_every`-th update's loss. The group is the
    boundary between the simulator's CPU tensors and the learner's device: observations go
    there, actions come back, transitions are stored there.
    """

    name: str
    learner: Learner
    replay: ReplayBuffer
    noise_gen: torch.Generator
    sample_gen: torch.Generator
    updates_per_sim_step: float
    batch_size: int
    learning_starts: int
    loss_log_every: int
    on_loss: Callable[[int, float], None] | None = None
    exploring: bool = True
    explore_step: int = 0
    experience_sim_steps: int = 0
    updates: int = 0

    @torch.no_grad()
    def act(self, obs: Tensor) -> dict[str, Tensor]:
        """The learner's action for `obs` [..., d] (with exploration noise while exploring),
        on the device of `obs`."""
        gen = self.noise_gen if self.exploring else None
        dev = self.learner.device
        if obs.device == dev:
            return self.learner.act(obs, self.explore_step, gen)
        acted = self.learner.act(obs.to(dev), self.explore_step, gen)
        return {key: value.to(obs.device) for key, value in acted.items()}

    def store(self, rows: Tensor, sim_steps: int) -> None:
        """Add transitions [n, row] that stand for `sim_steps` simulator steps of experience."""
        if rows.shape[0]:
            self.replay.extend(rows.to(self.learner.device))
        self.experience_sim_steps += sim_steps

    def learn(self) -> None:
        """Run the updates owed to the experience so far (`take_owed`)."""
        owed = self.take_owed()
        if owed is not None:
            self.record(self.learner.learn(self.replay, owed, self.batch_size))

    def take_owed(self) -> int | None:
        """The updates owed to the experience so far: `updates_per_sim_step` per simulator
        step, less those made. While the replay holds fewer than `learning_starts`
        transitions they are skipped, not postponed (counted as made; None returned). An
        on-policy learner (PPO) learns from the rollout just stored, as many updates as it
        makes of one."""
        owed = max(int(self.experience_sim_steps * self.updates_per_sim_step) - self.updates, 0)
        if self.learner.on_policy:
            return len(self.replay)
        if len(self.replay) < self.learning_starts:
            self.updates += owed
            return None
        return owed

    def record(self, losses: Tensor) -> None:
        """Count the updates just made (their losses [n]); `on_loss` sees every
        `loss_log_every`-th."""
        if self.on_loss is not None:
            first = (-(self.updates + 1)) % self.loss_log_every  # update n = updates + j + 1
            for j in range(first, len(losses), self.loss_log_every):
                self.on_loss(self.updates + j + 1, float(losses[j]))
        self.updates += len(losses)

    def state_dict(self) -> dict[str, Any]:
        return {
            "learner": self.learner.state_dict(),
            "replay": self.replay.state_dict(),
            "noise_gen": self.noise_gen.get_state(),
            "sample_gen": self.sample_gen.get_state(),
            "experience_sim_steps": self.experience_sim_steps,
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.learner.load_state_dict(state["learner"])
        self.replay.load_state_dict(state["replay"])
        replay_to(self.replay, self.learner.device)
        self.noise_gen.set_state(state["noise_gen"])
        self.sample_gen.set_state(state["sample_gen"])
        self.experience_sim_steps = state["experience_sim_steps"]
        self.updates = state["updates"]


class GroupPolicy:
    """Collector policy of one learning group: writes the learner's `action` [B, 1] m/s^2 (and
    what else it acts with, e.g. DQN's `action_index`), through `shield` if the run has one
    (`marlmerge.training.shield`)."""

    def __init__(self, group: LearningGroup, shield: TrainShield | None = None) -> None:
        self.group, self.shield = group, shield

    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        obs = td.get("observation")
        for key, value in shielded(self.shield, obs, self.group.act(obs)).items():
            td.set(key, value)
        return td


def make_collector(
    env: Any,
    policy: Callable[[TensorDictBase], TensorDictBase],
    frames_per_batch: int,
    sim_steps_left: int,
    action_repeat: int,
    resumed_groups: Sequence[LearningGroup] = (),
) -> Collector:
    """A torchrl collector for at least `sim_steps_left` simulator steps, in whole batches.
    Setting up, the collector runs the policy once: the noise generators of `resumed_groups`
    (a run continuing from a checkpoint) are put back where the checkpoint left them."""
    frames = math.ceil(sim_steps_left / action_repeat)
    frames = max(frames_per_batch, math.ceil(frames / frames_per_batch) * frames_per_batch)
    states = [g.noise_gen.get_state() for g in resumed_groups]
    collector = Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=frames,
        auto_register_policy_transforms=False,
    )
    for group, state in zip(resumed_groups, states, strict=True):
        group.noise_gen.set_state(state)
    return collector


@dataclass
class LoopTimes:
    collect_s: float = 0.0
    """Seconds spent stepping the envs (the collector)."""
    update_s: float = 0.0
    """Seconds spent storing transitions and updating."""


def run_loop(
    collector: Collector,
    feeds: Sequence[tuple[LearningGroup, RowsFn]],
    action_repeat: int,
    on_batch: Callable[[TensorDictBase, int], None],
    after_updates: Callable[[], bool],
) -> LoopTimes:
    """Collect a batch; `on_batch(batch, sim_steps)` counts it and logs its episodes; each group
    in `feeds` stores its transitions and learns; `after_updates()` (progress, checkpoints) says
    whether to stop."""
    times = LoopTimes()
    t_collect = time.perf_counter()
    for batch in collector:
        times.collect_s += time.perf_counter() - t_collect
        sim_steps = batch.numel() * action_repeat
        on_batch(batch, sim_steps)
        t_update = time.perf_counter()
        for group, rows in feeds:
            group.store(rows(batch), sim_steps)
            group.learn()
        times.update_s += time.perf_counter() - t_update
        if after_updates():
            break
        t_collect = time.perf_counter()
    collector.shutdown()
    return times


def transition_rows(batch: TensorDictBase, action: Tensor | None = None) -> Tensor:
    """The packed transitions [B * T, obs | action | reward | terminated | next_obs] of a
    single-agent batch [B, T]; `action` [B * T, 1] replaces the stored action (e.g. the
    learner's `replay_action`). A judging shield's `shield_cost` is taken off the reward
    (`marlmerge.training.shield`)."""
    flat = batch.reshape(-1)
    nxt = flat.get("next")
    reward = nxt.get("reward")
    if SHIELD_COST in flat.keys():
        reward = reward - flat.get(SHIELD_COST)
    return torch.cat(
        [
            flat.get("observation"),
            flat.get("action") if action is None else action,
            reward,
            nxt.get("terminated").float(),
            nxt.get("observation"),
        ],
        -1,
    )


def save_checkpoint(path: Any, payload: dict[str, Any]) -> None:
    """Write atomically (a run killed while saving keeps its previous checkpoint), as tensors
    and plain data only (`marlmerge.io.files`)."""
    files.save(payload, path)
