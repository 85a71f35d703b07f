"""Where independent tasks run: one after the other, in worker processes, or on a Ray cluster.

    run_tasks(fn, tasks, backend="process", on_done=lambda i, result: ...)

calls the top-level function `fn` on every task and hands each result to `on_done` in the
calling process as it arrives (in any order; the caller orders them). A task must not depend on
where or when it runs: the grid and the sweep derive every random number from the task's own
seeds, so every backend gives the same answer.

- `serial`: in this process.
- `process` (default): a pool of `workers` processes (default: every core), each pinned to one
  thread (torch, Numba, BLAS). A worker that dies takes its pool with it; the pool is rebuilt
  and the unfinished tasks are run again, each at most `max_retries` more times. Workers are
  forked where that is safe (`start_method`), so they start with this process's imports instead
  of importing torch and the kernels again (about 3 s each); else they are spawned.
- `ray`: Ray tasks of one CPU each (`pip install ".[ray]"`), retried by Ray up to `max_retries`
  times when a worker dies; `address` joins a running cluster (`ray start --head`, then
  `address="auto"` or `"ray://host:10001"`), else a local one is started with `workers` CPUs.
"""

from __future__ import annotations

import multiprocessing
import os
import socket
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

BACKENDS = ("serial", "process", "ray")
T = TypeVar("T")
R = TypeVar("R")
_ONE_THREAD = {
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "NUMBA_NUM_THREADS": "1",
}


def _pin_threads() -> None:
    """A worker uses one thread: set before torch or Numba are imported in it. A forked worker
    has Numba's config from its parent already: it is re-read now, before any thread starts
    (Numba re-reads it when it compiles, and refuses a new thread count once threads run)."""
    os.environ.update(_ONE_THREAD)
    if "numba" in sys.modules:
        from numba.np.ufunc import parallel

        if not parallel._is_initialized:
            sys.modules["numba"].config.reload_config()


def _call(fn: Callable[[T], R], task: T) -> R:
    _pin_threads()
    import torch

    torch.set_num_threads(1)  # one thread: torch then never enters an OpenMP region
    if "numba.np.ufunc.parallel" in sys.modules:  # forked: Numba read its thread count already
        import numba

        numba.set_num_threads(1)
    return fn(task)


def start_method() -> str:
    """How worker processes start: `fork` on Linux while this process has not started Numba's
    threading layer (a forked OpenMP runtime that was running can hang in the child; torch
    runs single-threaded in a worker), `spawn` otherwise."""
    if not sys.platform.startswith("linux"):
        return "spawn"
    import numba

    try:
        numba.threading_layer()  # raises until a parallel kernel has run in this process
    except ValueError:
        return "fork"
    return "spawn"


def check_backend(backend: str, workers: int | None = None, address: str | None = None) -> None:
    """A clear error for a backend that does not exist or cannot run here, before any work:
    an `address` only with Ray, and one that nothing answers at (Ray itself would retry for
    minutes)."""
    if backend not in BACKENDS:
        raise ValueError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if workers is not None and workers < 1:
        raise ValueError(f"--workers must be >= 1, got {workers}")
    if address and backend != "ray":
        raise ValueError(f"--address {address!r} joins a Ray cluster: it needs --backend ray")
    if backend == "ray":
        try:
            import ray  # noqa: F401
        except ImportError:
            raise ValueError(
                '--backend ray: Ray is not installed (pip install -c constraints.txt ".[ray]")'
            ) from None
        if address:
            check_ray_address(address)


def check_ray_address(address: str, timeout_s: float = 5.0) -> None:
    """`address` ("auto", "HOST:PORT" or "ray://HOST:PORT") answers a TCP connection within
    `timeout_s` ("auto" is Ray's to find)."""
    if address == "auto":
        return
    host, colon, port = address.removeprefix("ray://").rpartition(":")
    if not colon or not host or not port.isdigit():
        raise ValueError(f"--address {address!r}: expected auto, HOST:PORT or ray://HOST:PORT")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as err:
        raise ValueError(
            f"--address {address!r}: nothing answers there ({err}); start a cluster with "
            "`ray start --head` and give its address, or leave --address out for a local one"
        ) from None


def run_tasks(
    fn: Callable[[T], R],
    tasks: Sequence[T],
    backend: str = "process",
    on_done: Callable[[int, R], None] | None = None,
    workers: int | None = None,
    address: str | None = None,
    max_retries: int = 2,
) -> list[R]:
    """Run `fn(task)` for every task on `backend`; returns the results in task order."""
    check_backend(backend, workers, address)
    results: dict[int, R] = {}

    def done(i: int, r: R) -> None:
        results[i] = r
        if on_done is not None:
            on_done(i, r)

    if tasks:
        runner = {"serial": _serial, "process": _processes, "ray": _ray}[backend]
        runner(fn, list(tasks), done, workers or os.cpu_count() or 1, address, max_retries)
    return [results[i] for i in range(len(tasks))]


def _serial(fn, tasks, done, workers, address, max_retries) -> None:  # noqa: ANN001
    for i, task in enumerate(tasks):
        done(i, fn(task))


def _processes(fn, tasks, done, workers, address, max_retries) -> None:  # noqa: ANN001
    pending = set(range(len(tasks)))
    tries = dict.fromkeys(pending, 0)
    ctx = multiprocessing.get_context(start_method())
    while pending:
        with ProcessPoolExecutor(
            max_workers=min(workers, len(pending)), mp_context=ctx, initializer=_pin_threads
        ) as pool:
            futures = {pool.submit(_call, fn, tasks[i]): i for i in sorted(pending)}
            try:
                while futures:
                    finished, _ = wait(futures, return_when=FIRST_COMPLETED)
                    for f in finished:
                        i = futures.pop(f)
                        done(i, f.result())
                        pending.discard(i)
            except BrokenProcessPool:
                for i in pending:
                    tries[i] += 1
                    if tries[i] > max_retries:
                        raise RuntimeError(
                            f"task {i} ({tasks[i]!r}) was interrupted more than {max_retries} "
                            "times: a worker process keeps dying"
                        ) from None


def _ray(fn, tasks, done, workers, address, max_retries) -> None:  # noqa: ANN001
    import ray

    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, log_to_driver=False, include_dashboard=False)
    remote = ray.remote(num_cpus=1, max_retries=max_retries, retry_exceptions=False)(_call)
    refs: dict[Any, int] = {remote.remote(fn, t): i for i, t in enumerate(tasks)}
    while refs:
        ready, _ = ray.wait(list(refs), num_returns=1)
        for ref in ready:
            done(refs.pop(ref), ray.get(ref))
