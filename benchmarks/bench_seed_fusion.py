"""How one fused update of S quadratic-Q seeds compares with one seed's, as JSON.

The paper recipe's update (batch 32, a small MLP) costs per call, not per flop, so S seeds
updated by one batched call should cost little more than one. This times the fast path's chunk
(`marlmerge.learners.quadq_fast.fast_chunk`) against the fused chunk that `marlmerge train --seeds`
uses (`marlmerge.learners.quadq_fused.fused_chunk`), eager and compiled (the fused one with
inductor's C++ wrapper, as `FusedQuadQUpdates` compiles it):

- `ms_per_chunk`: one call of `updates_per_call` (10) updates, for 1 seed and for S fused;
- `ratio`: S fused against 1 seed (S x the work);
- `bit_identical`: whether each seed of the fused call equals its own single-seed call, bit
  for bit (the weights after one chunk).

With `--peaks K` (K > 1) the network has K quadratic pieces and the chunks are
`fast_chunk_peaks` and `fused_chunk_peaks`. With `--cold`, 16 MB are written before each timed
call, so the call starts with caches full of other data, as it does in training after an env
step.

    python benchmarks/bench_seed_fusion.py [--seeds 8] [--peaks 1] [--cold] [--repeats 200]
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import time

import torch

from marlmerge.learners.quadq_fast import fast_chunk
from marlmerge.learners.quadq_flat import FastSpec, param_layout
from marlmerge.learners.quadq_fused import fused_chunk, fused_chunk_peaks
from marlmerge.learners.quadq_peaks import fast_chunk_peaks

SPEC = FastSpec(obs_dim=7, hidden=64, a_min=1e-3, a_span=5 - 1e-3, low=-4.5, span=7.0,
                 gamma=0.95, lr=1e-3, beta1=0.9, beta2=0.999, eps=1e-8)  # fmt: skip
K, BATCH = 10, 32
COLD_MB = 16  # --cold: data written between calls, beyond the caches


def measure(single, fused, n_seeds: int, repeats: int, peaks: int = 1, cold: bool = False) -> dict:
    gen = torch.Generator().manual_seed(0)
    sweep = torch.zeros(COLD_MB * 2**18 if cold else 0)  # float32: 2^18 per MB
    p = sum(torch.Size(s).numel() for _, s in param_layout(SPEC.obs_dim, SPEC.hidden, 1, peaks))
    flat = torch.randn(n_seeds, p, generator=gen) * 0.1
    target = flat + 0.01
    rows = torch.randn(n_seeds, K, BATCH, 2 * SPEC.obs_dim + 3, generator=gen)
    scalars = torch.tensor([[1e-3 / (1 - 0.9**t), (1 - 0.999**t) ** 0.5] for t in range(1, K + 1)])

    def run_single(j):
        w = flat[j].clone()
        single(w, target[j], torch.zeros(p), torch.zeros(p), scalars, rows[j])
        return w

    def run_fused():
        w = flat.clone()
        fused(w, target, torch.zeros_like(w), torch.zeros_like(w), scalars, rows)
        return w

    ref = [run_single(j) for j in range(n_seeds)]
    out = run_fused()
    same = all(torch.equal(out[j], ref[j]) for j in range(n_seeds))
    times = {}
    for name, fn in (("one_seed", lambda: run_single(0)), ("fused", run_fused)):
        fn()
        total = 0.0
        for _ in range(repeats):
            sweep.add_(1.0)  # with --cold: the caches hold other data, as after an env step
            t0 = time.perf_counter()
            fn()
            total += time.perf_counter() - t0
        times[name] = 1e3 * total / repeats
    return {"ms_per_chunk": times, "ratio": times["fused"] / times["one_seed"],
            "bit_identical": same}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--peaks", type=int, default=1, help="quadratic pieces of the network")
    p.add_argument("--repeats", type=int, default=200)
    p.add_argument("--cold", action="store_true", help=f"write {COLD_MB} MB before each call")
    args = p.parse_args()
    if args.peaks < 1 or args.seeds < 1:
        raise SystemExit(f"--seeds and --peaks: need >= 1, got {args.seeds} and {args.peaks}")
    torch.set_num_threads(1)
    spec = dataclasses.replace(SPEC, peaks=args.peaks)
    pair = (fast_chunk, fused_chunk) if args.peaks == 1 else (fast_chunk_peaks, fused_chunk_peaks)
    single, fused = (functools.partial(f, spec) for f in pair)
    out = {"seeds": args.seeds, "peaks": args.peaks, "updates_per_chunk": K, "batch": BATCH}
    out["cold"] = args.cold
    out["eager"] = measure(single, fused, args.seeds, args.repeats, args.peaks, args.cold)
    compile_ = functools.partial(torch.compile, fullgraph=True, dynamic=False)
    fused_c = compile_(fused, options={"cpp_wrapper": True})
    compiled = compile_(single)
    out["compiled"] = measure(compiled, fused_c, args.seeds, args.repeats, args.peaks, args.cold)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
