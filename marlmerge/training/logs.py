"""What a training run writes while it runs: CSV logs that a resumed run cuts back to its
checkpoint, the per-ego episode rows, TensorBoard (`losses/`, `charts/`, each point once) and the
progress bar."""

from __future__ import annotations

import csv
import io
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from marlmerge.io import files
from marlmerge.sim import OUTCOME_NAMES
from marlmerge.sim.reward import EGO_TERMS, total_reward

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


class _EpisodeTracker:
    """Sums the reward terms of running episodes (`sums` [..., terms], `steps` [...] indexed by
    world, or by world and agent column) and writes an `egos.csv` row when one ends."""

    def __init__(self, shape: tuple[int, ...], step_time_s: float):
        self.sums = np.zeros((*shape, len(EGO_TERMS)))
        self.steps = np.zeros(shape, dtype=np.int64)  # env steps of each running episode
        self.egos = 0
        self.step_time_s = step_time_s

    def _end(self, at: tuple[int, ...], sim_step: int, outcome: int, log: CsvLog) -> dict:
        """The row of the episode at index `at` (world first), which ended; its sums restart."""
        sums = self.sums[at]
        row = {
            "ego": self.egos,
            "sim_step": sim_step,
            "world": int(at[0]),
            "outcome": OUTCOME_NAMES[int(outcome)],
            "time_s": round(float(self.steps[at] * self.step_time_s), 3),
            "total_reward": float(total_reward(sums)),
            **{name: float(sums[i]) for i, name in enumerate(EGO_TERMS)},
        }
        log.write([row[f] for f in EGO_FIELDS])
        self.egos += 1
        self.sums[at] = 0.0
        self.steps[at] = 0
        return row


class EgoTracker(_EpisodeTracker):
    """Sums each world's reward terms over its current ego's episode; emits a row when it ends."""

    def __init__(self, num_worlds: int, step_time_s: float):
        super().__init__((num_worlds,), step_time_s)

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
                finished.append(self._end((w,), sim_step, outcome[w, t], log))
        return finished


class RampTracker(_EpisodeTracker):
    """Ramp flow: sums each ramp agent's reward terms over its own merge; emits an `egos.csv` row
    (the merging vehicle as the ego) when it ends. Columns of the `"ramp"` group [B, K]."""

    def __init__(self, num_worlds: int, n_agents: int, step_time_s: float):
        super().__init__((num_worlds, n_agents), step_time_s)

    def update(self, batch: TensorDictBase, sim_step_end: int, k: int, log: CsvLog) -> list[dict]:
        """batch: collector output [B, T]. Returns the ended merges' rows, in time order."""
        nxt = batch.get("next")
        terms = torch.stack([nxt.get(("ramp", "reward_terms", t)) for t in EGO_TERMS], -1)
        terms = terms.reshape(*batch.shape, *self.steps.shape[1:], len(EGO_TERMS)).numpy()
        acting = batch.get(("ramp", "mask")).numpy()  # [B, T, K]
        outcome = nxt.get(("ramp", "outcome")).numpy()  # [B, T, K]
        b, t_len = batch.batch_size
        finished = []
        for t in range(t_len):
            self.sums += terms[:, t]
            self.steps += acting[:, t]
            sim_step = sim_step_end - (t_len - 1 - t) * b * k
            for w, j in zip(*np.nonzero(outcome[:, t]), strict=True):
                finished.append(self._end((w, j), sim_step, outcome[w, t, j], log))
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


def progress_bar(total: int, initial: int, enabled: bool, desc: str = "train"):
    if not enabled:
        return None
    from tqdm import tqdm

    return tqdm(
        total=total,
        initial=initial,
        unit="step",
        unit_scale=True,
        dynamic_ncols=True,
        desc=desc,
        file=sys.stderr,
    )


def tb_loss(tb) -> Callable[[list[Any]], None] | None:
    """TensorBoard `losses/td_loss` at each logged update (each point once)."""
    if tb is None:
        return None
    return lambda row: tb.add_scalar("losses/td_loss", float(row[2]), int(row[0]))


def tb_ego(tb) -> Callable[[list[Any]], None] | None:
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


def tensorboard(out: Path):
    """A TensorBoard writer if tensorboard is installed, else None."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(out / "tb"))
