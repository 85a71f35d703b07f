"""Updates/s of the quadratic-Q training step: torchrl eager baseline vs. the engineered path.

Each thread count runs in its own subprocess (``torch.set_num_threads`` before any work, and
inductor bakes the thread count into compiled kernels). Prints one JSON document.

    python benchmarks/bench_update.py                   # threads 1 and 2, ~1.5 s per variant
    python benchmarks/bench_update.py --cold-cache      # fresh inductor cache: cold compile times
    python benchmarks/bench_update.py --threads 1 --no-compile

Variants (minibatch 32, obs_dim 7, hidden 64, Adam lr 1e-3, target copy every 500 updates):

* ``eager_3mlp_lossmodule_torchrl_rb``: three ``nn.Sequential`` MLPs, :class:`QuadraticQLoss`,
  ``torch.optim.Adam`` (default impl), torchrl ``ReplayBuffer(LazyTensorStorage)`` ``.sample()``
  and :class:`PeriodicHardUpdate` ``.step()`` every update: the straightforward implementation.
* ``eager_fused_lossmodule_torchrl_rb[_adam_foreach|_adam_fused]``: same with the fused
  :class:`QuadraticQNet` and the given Adam implementation.
* ``compiled_lossmodule_autograd``: ``torch.compile`` of the loss module call and of
  ``opt.step()``, autograd backward, hand-rolled replay sampling.
* ``fast_eager_k{k}`` / ``fast_compiled_k{k}``: :class:`FastQuadQUpdater` (k minibatches sampled
  in one call from :class:`TransitionReplay`, hand-written gradients, flat Adam), eager or
  ``torch.compile``-d; ``_torchrl_rb`` samples the packed rows from a torchrl ReplayBuffer.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable

import torch
from torch import nn

OBS_DIM, HIDDEN, BATCH, PERIOD, CAPACITY = 7, 64, 32, 500, 200_000


class ThreeMLPNet(nn.Module):
    """Reference: A, B, C as three separate two-layer ``nn.Sequential`` (same activations)."""

    def __init__(self, obs_dim: int = OBS_DIM, hidden: int = HIDDEN) -> None:
        super().__init__()
        self.mlps = nn.ModuleList(
            nn.Sequential(nn.Linear(obs_dim, hidden), nn.ReLU(), nn.Linear(hidden, 1))
            for _ in range(3)
        )
        self.low, self.high, self.a_min, self.a_max = -4.5, 2.5, 1e-3, 5.0

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        za, zb, zc = (m(obs) for m in self.mlps)
        a = -(self.a_min + (self.a_max - self.a_min) * torch.sigmoid(za))
        b = self.low + (self.high - self.low) * torch.sigmoid(zb)
        return a, b, zc


def _rate(step: Callable[[], None], updates_per_call: int, seconds: float, warmup: int) -> float:
    for _ in range(warmup):
        step()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        step()
        n += updates_per_call
    return n / (time.perf_counter() - t0)


def _worker(threads: int, seconds: float, do_compile: bool) -> dict:
    torch.set_num_threads(threads)
    warnings.filterwarnings("ignore")
    os.environ.setdefault("RL_WARNINGS", "False")
    from torchrl.data import LazyTensorStorage, ReplayBuffer

    from marlmerge.learners.packed_replay import TransitionReplay
    from marlmerge.learners.quadq import PeriodicHardUpdate, QuadraticQLoss, QuadraticQNet
    from marlmerge.learners.quadq_fast import FastQuadQUpdater

    g = torch.Generator().manual_seed(0)
    replay = TransitionReplay(CAPACITY, OBS_DIM)
    replay.extend(
        torch.randn(CAPACITY, OBS_DIM, generator=g),
        torch.rand(CAPACITY, 1, generator=g) * 7.0 - 4.5,
        torch.randn(CAPACITY, 1, generator=g),
        torch.rand(CAPACITY, 1, generator=g) < 0.05,
        torch.randn(CAPACITY, OBS_DIM, generator=g),
    )
    td_all = replay.to_tensordict(replay.storage)
    res: dict = {"updates_per_s": {}, "compile_time_s": {}, "sampling_us": {}}
    ups, ctime = res["updates_per_s"], res["compile_time_s"]
    full = threads == 1  # thread-count comparison only for the main variants

    def eager(net: nn.Module, adam_kw: dict) -> float:
        loss = QuadraticQLoss(net, gamma=0.95)
        upd = PeriodicHardUpdate(loss, period=PERIOD)
        opt = torch.optim.Adam(loss.parameters(), lr=1e-3, **adam_kw)
        rb = ReplayBuffer(
            storage=LazyTensorStorage(CAPACITY),
            batch_size=BATCH,
            generator=torch.Generator().manual_seed(1),
        )
        rb.extend(td_all)

        def step() -> None:
            out = loss(rb.sample())
            opt.zero_grad()
            out["loss_value"].backward()
            opt.step()
            upd.step()

        return _rate(step, 1, seconds, warmup=20)

    def new_net() -> QuadraticQNet:
        return QuadraticQNet(OBS_DIM, HIDDEN, generator=torch.Generator().manual_seed(0))

    if full:
        ups["eager_3mlp_lossmodule_torchrl_rb"] = eager(ThreeMLPNet(), {})
    ups["eager_fused_lossmodule_torchrl_rb"] = eager(new_net(), {})
    if full:
        ups["eager_fused_lossmodule_torchrl_rb_adam_foreach"] = eager(new_net(), {"foreach": True})
        ups["eager_fused_lossmodule_torchrl_rb_adam_fused"] = eager(new_net(), {"fused": True})

    def fast(k: int, comp: bool, torchrl_rb: bool = False) -> tuple[float, float | None]:
        loss = QuadraticQLoss(new_net(), gamma=0.95)
        f = FastQuadQUpdater(
            loss,
            replay,
            generator=torch.Generator().manual_seed(2),
            batch_size=BATCH,
            updates_per_call=k,
            target_update_period=PERIOD,
            compile=comp,
        )
        if torchrl_rb:
            rb = ReplayBuffer(
                storage=LazyTensorStorage(CAPACITY), generator=torch.Generator().manual_seed(3)
            )
            rb.extend(replay.storage)

            def step() -> None:
                f.step(rb.sample(k * BATCH).view(k, BATCH, -1))
        else:

            def step() -> None:
                f.step()

        t0 = time.perf_counter()
        step()
        first = time.perf_counter() - t0
        return _rate(step, k, seconds, warmup=5), (first if comp else None)

    for k in (1, 10) if full else (10,):
        ups[f"fast_eager_k{k}"], _ = fast(k, False)

    if do_compile:
        if full:
            loss = QuadraticQLoss(new_net(), gamma=0.95)
            upd = PeriodicHardUpdate(loss, period=PERIOD)
            opt = torch.optim.Adam(loss.parameters(), lr=1e-3)
            closs = torch.compile(lambda td: loss(td)["loss_value"])
            copt = torch.compile(opt.step)
            gs = torch.Generator().manual_seed(4)

            def cstep() -> None:
                lv = closs(replay.to_tensordict(replay.sample((BATCH,), gs)))
                opt.zero_grad()
                lv.backward()
                copt()
                upd.step()

            t0 = time.perf_counter()
            for _ in range(2):
                cstep()
            ctime["compiled_lossmodule_autograd"] = time.perf_counter() - t0
            ups["compiled_lossmodule_autograd"] = _rate(cstep, 1, seconds, warmup=5)
        for k in (1, 10) if full else (10,):
            ups[f"fast_compiled_k{k}"], ctime[f"fast_compiled_k{k}"] = fast(k, True)
        if full:
            ups["fast_compiled_k10_torchrl_rb"], _ = fast(10, True, torchrl_rb=True)

    if full:
        rb = ReplayBuffer(
            storage=LazyTensorStorage(CAPACITY), generator=torch.Generator().manual_seed(5)
        )
        rb.extend(td_all)
        rb_packed = ReplayBuffer(
            storage=LazyTensorStorage(CAPACITY), generator=torch.Generator().manual_seed(6)
        )
        rb_packed.extend(replay.storage)
        gs = torch.Generator().manual_seed(7)
        for name, fn, per in (
            ("torchrl_rb_tensordict_sample_32", lambda: rb.sample(BATCH), 1),
            ("torchrl_rb_tensordict_sample_10x32", lambda: rb.sample(10 * BATCH), 10),
            ("torchrl_rb_packed_tensor_sample_10x32", lambda: rb_packed.sample(10 * BATCH), 10),
            ("transition_replay_sample_32", lambda: replay.sample((1, BATCH), gs), 1),
            ("transition_replay_sample_10x32", lambda: replay.sample((10, BATCH), gs), 10),
        ):
            res["sampling_us"][name + "_per_minibatch"] = 1e6 / _rate(
                fn, per, min(seconds, 0.5), warmup=5
            )
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", default="1,2", help="comma-separated torch thread counts")
    ap.add_argument("--seconds", type=float, default=1.5, help="timed seconds per variant")
    ap.add_argument("--no-compile", action="store_true", help="skip torch.compile variants")
    ap.add_argument("--cold-cache", action="store_true", help="fresh TORCHINDUCTOR_CACHE_DIR")
    ap.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()

    if args.worker is not None:
        print(json.dumps(_worker(args.worker, args.seconds, not args.no_compile)))
        return

    t_start = time.perf_counter()
    out: dict = {
        "torch": torch.__version__,
        "cpu_count": os.cpu_count(),
        "minibatch": BATCH,
        "hidden": HIDDEN,
        "seconds_per_variant": args.seconds,
        "cold_inductor_cache": args.cold_cache,
        "by_threads": {},
    }
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ)
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    env["RL_WARNINGS"] = "False"
    with tempfile.TemporaryDirectory() as cache:
        if args.cold_cache:
            env["TORCHINDUCTOR_CACHE_DIR"] = cache
        for threads in (int(t) for t in args.threads.split(",")):
            cmd = [sys.executable, os.path.abspath(__file__), "--worker", str(threads)]
            cmd += ["--seconds", str(args.seconds)] + (["--no-compile"] if args.no_compile else [])
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
            if proc.returncode != 0:
                out["by_threads"][threads] = {"error": proc.stderr[-2000:]}
                continue
            out["by_threads"][threads] = json.loads(proc.stdout.strip().splitlines()[-1])
    out["total_wall_s"] = time.perf_counter() - t_start
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
