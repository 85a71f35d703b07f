"""How far one fused update of S quadratic-Q seeds gets towards "many seeds in one run", as JSON.

The paper recipe's update (batch 32, a small MLP) costs per call, not per flop, so S seeds
updated by one batched call should cost little more than one. This measures it on the fast
path's hand-written gradients (`marlmerge.learners.quadq._fast_chunk`) and a batched copy of it
(`fused_chunk` below: the same operations with a leading seed dimension, batched matmuls, and
the target's matrix-vector product kept per seed), eager and compiled:

- `ms_per_chunk`: one call of `updates_per_call` (10) updates, for 1 seed and for S fused;
- `ratio`: S fused against 1 seed (S x the work);
- `bit_identical`: whether each seed of the fused call equals its own single-seed call, bit
  for bit (the weights after one chunk).

    python benchmarks/bench_seed_fusion.py [--seeds 8] [--repeats 200]
"""

from __future__ import annotations

import argparse
import functools
import json
import time

import torch

from marlmerge.learners.quadq import HEAD_A, HEAD_B, HEAD_C, _fast_chunk, _FastSpec

SPEC = _FastSpec(obs_dim=7, hidden=64, a_min=1e-3, a_span=5 - 1e-3, low=-4.5, span=7.0,
                 gamma=0.95, lr=1e-3, beta1=0.9, beta2=0.999, eps=1e-8)  # fmt: skip
K, BATCH = 10, 32
SHAPES = ((3 * 64, 7), (3 * 64,), (3, 64), (3,))


def unflatten_seeds(flat: torch.Tensor) -> list[torch.Tensor]:
    out, o = [], 0
    for shape in SHAPES:
        n = 1
        for x in shape:
            n *= x
        out.append(flat[:, o : o + n].view(flat.shape[0], *shape))
        o += n
    return out


def fused_chunk(spec, flat, target_flat, exp_avg, exp_avg_sq, adam_scalars, rows):
    """`_fast_chunk` for S seeds at once: flat [S, P], rows [S, k, B, 2d + 3]."""
    d, hd = spec.obs_dim, spec.hidden
    s_, k, bsz = rows.shape[:3]
    obs, act, rew = rows[..., :d], rows[..., d], rows[..., d + 1]
    not_term, next_obs = 1.0 - rows[..., d + 2], rows[..., d + 3 :]
    tw1, tb1, tw2, tb2 = unflatten_seeds(target_flat)
    c_sl = slice(HEAD_C * hd, (HEAD_C + 1) * hd)
    h_next = torch.relu(
        torch.bmm(next_obs.reshape(s_, k * bsz, d), tw1[:, c_sl].transpose(1, 2)).view(
            s_, k, bsz, hd
        )
        + tb1[:, None, None, c_sl]
    )
    # per seed: a batched bmm rounds this product differently from the single-seed matmul
    v_next = torch.stack([torch.matmul(h_next[j], tw2[j, HEAD_C]) for j in range(s_)])
    y = rew + spec.gamma * not_term * (v_next + tb2[:, HEAD_C, None, None])
    w1, b1, w2, b2 = unflatten_seeds(flat)
    losses = []
    for i in range(k):
        x, a = obs[:, i], act[:, i]
        pre = torch.baddbmm(b1[:, None, :], x, w1.transpose(1, 2))
        h = torch.relu(pre).view(s_, bsz, 3, hd)
        z = (h * w2[:, None]).sum(-1) + b2[:, None]
        s_a, s_b = torch.sigmoid(z[..., HEAD_A]), torch.sigmoid(z[..., HEAD_B])
        big_a = -(spec.a_min + spec.a_span * s_a)
        diff = spec.low + spec.span * s_b - a
        delta = big_a * diff * diff + z[..., HEAD_C] - y[:, i]
        losses.append((delta * delta).mean(-1))
        g = delta * (2.0 / bsz)
        dz = torch.stack(
            [
                g * diff * diff * (-spec.a_span) * s_a * (1.0 - s_a),
                g * 2.0 * big_a * diff * spec.span * s_b * (1.0 - s_b),
                g,
            ],
            dim=-1,
        )
        dw2, db2 = (dz.unsqueeze(-1) * h).sum(1), dz.sum(1)
        dpre = torch.where(pre > 0, (dz.unsqueeze(-1) * w2[:, None]).view(s_, bsz, 3 * hd), 0.0)
        dw1_t, db1 = torch.bmm(x.transpose(1, 2), dpre), dpre.sum(1)
        grad = torch.cat([dw1_t.transpose(1, 2).reshape(s_, -1), db1, dw2.reshape(s_, -1), db2], -1)
        exp_avg.lerp_(grad, 1.0 - spec.beta1)
        exp_avg_sq.mul_(spec.beta2).addcmul_(grad, grad, value=1.0 - spec.beta2)
        denom = exp_avg_sq.sqrt() / adam_scalars[i, 1] + spec.eps
        flat.sub_(adam_scalars[i, 0] * exp_avg / denom)
    return torch.stack(losses, -1)


def measure(single, fused, n_seeds: int, repeats: int) -> dict:
    gen = torch.Generator().manual_seed(0)
    p = sum(torch.Size(s).numel() for s in SHAPES)
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
        t0 = time.perf_counter()
        for _ in range(repeats):
            fn()
        times[name] = 1e3 * (time.perf_counter() - t0) / repeats
    return {"ms_per_chunk": times, "ratio": times["fused"] / times["one_seed"],
            "bit_identical": same}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seeds", type=int, default=8)
    p.add_argument("--repeats", type=int, default=200)
    args = p.parse_args()
    torch.set_num_threads(1)
    single = functools.partial(_fast_chunk, SPEC)
    fused = functools.partial(fused_chunk, SPEC)
    out = {"seeds": args.seeds, "updates_per_chunk": K, "batch": BATCH}
    out["eager"] = measure(single, fused, args.seeds, args.repeats)
    compile_ = functools.partial(torch.compile, fullgraph=True, dynamic=False)
    out["compiled"] = measure(compile_(single), compile_(fused), args.seeds, args.repeats)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
