"""Helpers for the compiled updates: every one gets a code object of its own (`own_code`),
a notice while a first call compiles (`notice_if_slow`), subnormals flushed on request
(`denormals_flushed`), and one call of an update with both (`call_update`).

**Code objects.**

torch.compile keeps the versions it compiled on the Python code object of the frame it
compiles, at most `torch._dynamo.config.recompile_limit` (8) of them. Each distinct setting baked
into a graph as a constant (an updater's `FastSpec`: gamma, learning rate, bounds; a learner's
own modules) is one version, and every updater of a kind compiled the same code (for a
`functools.partial`, torch's own wrapper around it). So the ninth updater with new settings in
one process, say a notebook trying nine discount factors, met the limit, and with
``fullgraph=True`` (the quadratic-Q fast paths, whose update is one graph) that is an error.
`own_code` wraps each updater's function in a function whose code object is its own, whose
versions that updater alone fills. (DQN's and TD3's steps break the graph at `backward` and
in torch's optimiser, whose resumed code torch shares between learners whatever wraps them;
past the limit torch runs those parts uncompiled, with a warning: `maybe_compile`.)
"""

from __future__ import annotations

import contextlib
import functools
import sys
import threading
import time
import types
from collections.abc import Callable, Iterator
from typing import Any

import torch


def own_code(fn: Callable[..., Any]) -> Callable[..., Any]:
    """A plain function that calls `fn` (any callable) and has a code object of its own, made
    for this call, for `torch.compile` (module docstring)."""

    def call(*args: Any, **kwargs: Any) -> Any:
        return fn(*args, **kwargs)

    code = call.__code__.replace()  # a new code object: torch keeps its versions on it
    wrapper = types.FunctionType(code, call.__globals__, call.__name__, None, call.__closure__)
    inner = fn.func if isinstance(fn, functools.partial) else fn
    wrapper.__name__ = getattr(inner, "__name__", "call")
    wrapper.__qualname__ = getattr(inner, "__qualname__", "call")
    wrapper.__doc__ = getattr(inner, "__doc__", None)
    return wrapper


COMPILE_NOTICE = (
    "marlmerge: compiling the update step with torch.compile (first run: up to a minute; "
    "later runs load it from the cache)..."
)


@contextlib.contextmanager
def notice_if_slow(message: str = COMPILE_NOTICE, after_s: float = 2.0) -> Iterator[None]:
    """Print `message` to stderr if the block is still running after `after_s` seconds (a first
    call that compiles), so a progress bar that stands still is explained."""
    timer = threading.Timer(after_s, lambda: print(message, file=sys.stderr, flush=True))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()


@contextlib.contextmanager
def denormals_flushed(on: bool) -> Iterator[None]:
    """With `on`, subnormal floats are flushed to zero inside the block
    (`torch.set_flush_denormal`, on the calling thread) and kept again after it, so the rest
    of the process computes as before (a flush set for the whole process beforehand is
    cleared too: torch cannot tell whether one was). Dead units' Adam moments decay into the
    subnormal range, where the CPU's arithmetic is many times slower (`docs/scale-out.md`)."""
    if not on:
        yield
        return
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


def call_update(
    fn: Callable[..., Any], args: tuple[Any, ...], *, compiling: bool, flush: bool
) -> tuple[Any, float | None]:
    """`fn(*args)`, with subnormals flushed if `flush` (`denormals_flushed`). With `compiling`
    (a compiled update's first call) the call runs under the compile notice and its wall time
    (s) is returned as well; otherwise None."""
    with denormals_flushed(flush):
        if not compiling:
            return fn(*args), None
        t0 = time.perf_counter()
        with notice_if_slow():
            out = fn(*args)
        return out, time.perf_counter() - t0
