"""What the torchrl-loss learners (DQN, TD3) share: randomness without the global RNG, the MLP,
the compiled-step helpers and `BaselineLearner`, the learner protocol over a torchrl loss; and
`sample_uniform`, the quadratic-Q fast path's minibatch draw.

A learner owns its networks, loss, optimiser(s), target updater and counters; the training loop
owns the env, the replay (packed rows ``[obs (d) | action | reward | terminated | next_obs (d)]``,
the action column being what the loss reads: the level index for DQN, the acceleration for TD3)
and the generators for exploration and minibatch sampling.

No global RNG: networks are initialised inside :func:`seeded_init` (which restores the global
state afterwards) and TD3's target-policy noise, which torchrl draws with ``torch.randn_like``, is
drawn from a private stream swapped in around the critic loss (:class:`GlobalRngStream`).
"""

from __future__ import annotations

import contextlib
import time
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn
from torchrl.data.replay_buffers.samplers import RandomSampler
from torchrl.data.replay_buffers.storages import TensorStorage
from torchrl.modules import MLP

from marlmerge.learners.base import Learner
from marlmerge.learners.compiling import notice_if_slow
from marlmerge.learners.packed_replay import unpack_rows
from marlmerge.sim.observation import EGO_FEATURES

OBS_DIM = len(EGO_FEATURES)
"""The paper's ego observation size (the learners take `obs_dim` for the other layouts)."""


# ----------------------------------------------------------------------------------------------
# Randomness without the global RNG
# ----------------------------------------------------------------------------------------------


@contextlib.contextmanager
def seeded_init(seed: int) -> Iterator[None]:
    """Run a block (network construction) on the global CPU RNG seeded with ``seed``.

    ``torch.nn`` initialisers and torchrl's twin-network re-initialisation draw from the global
    RNG; inside this block they are deterministic, and the caller's global state is restored on
    exit (``torch.random.fork_rng``), so nothing outside sees a change.
    """
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


class GlobalRngStream:
    """A private random stream for library code that can only draw from the global RNG.

    ``with stream.active():`` swaps the stream's state into the global generator of ``device``
    (the CPU's, or the CUDA device's where the library draws on it) and swaps it back out
    afterwards, so draws inside the block continue this stream (deterministic, checkpointable
    via :meth:`get_state`) and the global state outside is left unchanged.
    """

    def __init__(self, seed: int, device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)
        self.state: Tensor = torch.Generator(self.device).manual_seed(seed).get_state()

    def _get(self) -> Tensor:
        if self.device.type == "cuda":
            return torch.cuda.get_rng_state(self.device)
        return torch.get_rng_state()

    def _set(self, state: Tensor) -> None:
        if self.device.type == "cuda":
            torch.cuda.set_rng_state(state, self.device)
        else:
            torch.set_rng_state(state)

    @contextlib.contextmanager
    def active(self) -> Iterator[None]:
        outer = self._get()
        self._set(self.state)
        try:
            yield
        finally:
            self.state = self._get()
            self._set(outer)

    def get_state(self) -> Tensor:
        return self.state.clone()

    def set_state(self, state: Tensor) -> None:
        self.state = state.clone()


def resolve_device(name: str) -> torch.device:
    """The torch device of a run's `device` setting, refused with an error naming the value when
    this machine or this torch build does not have it (checked before a run does any work)."""
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(
                f"device = {name!r}: this torch build finds no CUDA device "
                "(torch.cuda.is_available() is False); train on device = 'cpu'"
            )
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise ValueError(f"device = {name!r}: this machine has {count} CUDA device(s)")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"device = {name!r}: MPS is not available on this machine")
    return device


# ----------------------------------------------------------------------------------------------
# Networks and losses
# ----------------------------------------------------------------------------------------------


def make_mlp(in_features: int, out_features: int, hidden: int, layers: int) -> MLP:
    """torchrl MLP, ``layers`` hidden ReLU layers of width ``hidden``."""
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=[hidden] * layers,
        activation_class=nn.ReLU,
    )


# ----------------------------------------------------------------------------------------------
# Learners
# ----------------------------------------------------------------------------------------------


def maybe_compile(fn: Callable[..., Any], compile: bool) -> Callable[..., Any]:
    """``torch.compile(fn)`` (default mode; graph breaks at backward and the optimiser) or
    ``fn`` itself. torch files the versions of the functions it resumes in after a break (and
    of torch's own optimiser code) under code it shares between learners: past 8 learners with
    distinct settings in one process it runs those parts uncompiled, with a warning (slower),
    which `own_code` cannot prevent."""
    return torch.compile(fn) if compile else fn


@contextlib.contextmanager
def quiet_tracing() -> Iterator[None]:
    """Silence two harmless library warnings raised while dynamo traces the torchrl losses."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Using lock_\(\) inside a compiled graph")
        warnings.filterwarnings("ignore", message=r".*inline_inbuilt_nn_modules is deprecated")
        yield


def rows_to_td(rows: Tensor, d: int, action: Tensor) -> TensorDictBase:
    """Packed rows [M, 2d + 3] -> the tensordict the torchrl losses read (batch [M])."""
    td = unpack_rows(rows, d)
    td.set("action", action)
    td.set(("next", "done"), td.get(("next", "terminated")))  # the losses need the key to exist
    return td


class BaselineLearner(Learner):
    """A torchrl-loss learner (DQN, TD3): one gradient update per minibatch.

    Attributes:
        num_updates: gradient updates (critic updates for TD3) made so far.
    """

    num_updates: int = 0
    _uncompiled_calls: set[str]
    """Names of compiled steps not called yet (their first call compiles them)."""

    def _timed(self, name: str, fn: Callable[..., Any], *args: Any) -> Any:
        """Call ``fn``; the first call of a compiled step counts as compile time."""
        if name not in self._uncompiled_calls:
            return fn(*args)
        t0 = time.perf_counter()
        with quiet_tracing(), notice_if_slow():
            out = fn(*args)
        self.compile_time_s = (self.compile_time_s or 0.0) + time.perf_counter() - t0
        self._uncompiled_calls.discard(name)
        return out

    def update(self, rows: Tensor) -> Tensor:
        """One gradient update on packed rows [M, 2d + 3]; returns the (critic) loss, detached."""
        raise NotImplementedError

    def learn(self, replay: Any, owed: int, batch_size: int) -> Tensor:
        """`owed` updates, their minibatches drawn in one sampling call."""
        if owed <= 0:
            return torch.empty(0)
        mbs = sample_uniform(replay, owed * batch_size).view(owed, batch_size, -1)
        return torch.stack([self.update(mbs[j]) for j in range(owed)])


def sample_uniform(replay: Any, n: int, out: Tensor | None = None) -> Tensor:
    """`replay.sample(n)` of a plain torchrl `ReplayBuffer` of packed rows (uniform sampler,
    one-dimensional tensor storage, no transforms): the same draw from the same generator,
    without the buffer's per-call machinery (locks, collation, transform checks), which costs
    more than the draw (about 13 against 80 us for 320 rows; the fast path samples every 10
    updates). Any other buffer is sampled by its own `sample`. `tests/test_vectorized_seeds.py`
    checks the two against each other. The indices are drawn on the CPU generator whatever the
    storage's device, so the minibatches are the same rows on every device. `out` [n, row]:
    write the rows there (S seeds' minibatches gathered into one tensor)."""
    storage = getattr(replay, "_storage", None)
    rows = getattr(storage, "_storage", None)
    plain = (
        isinstance(rows, Tensor)
        and type(getattr(replay, "_sampler", None)) is RandomSampler
        and isinstance(storage, TensorStorage)
        and storage.ndim == 1
        and not len(getattr(replay, "_transform", None) or ())
    )
    size = len(storage) if plain else 0  # type: ignore[arg-type]
    if size == 0:
        drawn = replay.sample(n)
        return drawn if out is None else out.copy_(drawn)
    index = torch.randint(0, size, (n,), generator=storage._rng)  # type: ignore[union-attr]
    return torch.index_select(rows, 0, index.to(rows.device), out=out)  # type: ignore[arg-type]
