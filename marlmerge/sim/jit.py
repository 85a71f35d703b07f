"""How the simulator's kernels are compiled: one decorator for every compiled function.

- `cache=True`: machine code is cached on disk next to the sources (or in `NUMBA_CACHE_DIR`), so
  only the first run of an installation compiles.
- `error_model="numpy"`: float division by zero gives inf/nan like NumPy instead of raising.
- `_nrt=False`: no reference counting. The kernels allocate nothing and create no views, they
  only index the core's arrays, so the runtime's atomic reference counts on every array passed
  to a function (about 10 ns each) would be pure overhead in the per-vehicle loops.
- `inline=True` inlines a helper into its callers (Numba IR); `parallel=True` lets `prange`
  run worlds on all cores (that loop alone uses the runtime). Every kernel takes the state
  tuple `S` (six arrays, about 70 machine words once unpacked), so a call that is not inlined
  costs more than a small kernel's work: the functions a simulator step calls (in `step`, the
  lane lists, the per-step terms) are inlined into `run_steps`, which holds the loop over a
  call's k steps, so a world pays one such call per `rollout`, not one per step
  (`benchmarks/bench_core_against.py`). `run_steps` writes the step's sequence out rather than
  inlining a one-step function: Numba's IR inlining of a function that itself inlines others
  made the cold compile about five times longer.

With `NUMBA_DISABLE_JIT=1` every kernel runs as plain Python (slowly), for debugging.

Numba keys a cached function on its own file only, but the kernels call (and inline) functions of
other files. So the cache is dropped whenever any kernel source changes: `KERNEL_SOURCES` are
hashed on import and the hash is kept beside the cache files.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from numba import njit

_PACKAGE = Path(__file__).resolve().parent.parent
KERNEL_SOURCES = (
    "sim/draws.py",
    "sim/drivers.py",
    "sim/entrance.py",
    "sim/jit.py",
    "sim/kernels.py",
    "sim/lanes.py",
    "sim/lapses.py",
    "sim/layout.py",
    "sim/safety.py",
    "sim/sensing.py",
    "sim/step.py",
    "sim/reward.py",
)
"""The files whose compiled functions call one another (relative to the package)."""


def _cache_dirs() -> list[Path]:
    """Where Numba keeps the cache files of the kernel modules."""
    dirs = {(_PACKAGE / f).parent for f in KERNEL_SOURCES}
    root = os.environ.get("NUMBA_CACHE_DIR")
    if root:  # Numba mirrors the source folder's absolute path below the cache folder
        return [Path(root) / str(d.resolve()).lstrip(os.sep) for d in dirs]
    return [d / "__pycache__" for d in dirs]


def drop_stale_cache() -> None:
    """Delete the kernels' cache files if any kernel source changed since they were written."""
    digest = hashlib.sha256()
    for f in KERNEL_SOURCES:
        digest.update((_PACKAGE / f).read_bytes())
    stamp = digest.hexdigest()
    stems = {Path(f).stem + "." for f in KERNEL_SOURCES}
    for d in _cache_dirs():
        marker = d / "marlmerge-kernels.sha256"
        try:
            if marker.read_text() == stamp:
                continue
        except OSError:
            pass
        try:
            for cached in d.glob("*.nb[ic]"):
                if any(cached.name.startswith(stem) for stem in stems):
                    cached.unlink()
            d.mkdir(parents=True, exist_ok=True)
            marker.write_text(stamp)
        except OSError:  # a read-only installation: Numba then compiles in memory
            pass


drop_stale_cache()

F = TypeVar("F", bound=Callable[..., Any])


def kernel(fn: F | None = None, *, inline: bool = False, parallel: bool = False) -> Any:
    """`@kernel` or `@kernel(inline=True)` / `@kernel(parallel=True)`: see the module docstring."""
    options: dict[str, Any] = {"cache": True, "error_model": "numpy", "_nrt": False}
    if inline:
        options["inline"] = "always"
    if parallel:  # the parallel loop itself needs the runtime; the kernels it calls do not
        options["parallel"] = True
        options["_nrt"] = True
    decorate = njit(**options)
    return decorate if fn is None else decorate(fn)
