"""One helper for `torch.compile`: every compiled update gets a code object of its own.

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

import functools
import types
from collections.abc import Callable
from typing import Any


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
