"""S quadratic-Q seeds updated by one call: the fast path's chunk with a leading seed dimension.

The paper recipe's update (minibatch 32, a 7-64-3 network) costs per call, not per flop, so S
independent seeds stepped together cost little more than one. `fused_chunk` is `fast_chunk`
(`marlmerge.learners.quadq`) with every tensor given a leading seed dimension [S, ...] and
batched matrix products, `fused_chunk_peaks` the same of `fast_chunk_peaks` (a Q of K
pieces); `FusedQuadQUpdates` steps S `FastQuadQUpdater`s with the one their spec takes.

Bit for bit: each seed's weights after a fused call equal those of its own `fast_chunk` call,
eager and compiled (`tests/test_vectorized_seeds.py` checks it). Three details buy that:

- the target's matrix-vector product and the first layer's weight gradient stay one call per
  seed (batched, they round differently);
- the gradients of every update are returned, so the compiler materialises them instead of
  fusing their reductions into the Adam kernel, where the summation order would depend on S;
- each seed's loss is recomputed from its own slices rather than from the shared TD errors.

These were found by measurement (torch 2.13, inductor on the CPU); the test is what keeps
them true.

Measured with `benchmarks/bench_seed_fusion.py` (compiled, one thread): 8 seeds in about
2.7x the time of one (1.32 against 0.50 ms per 10 updates).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from marlmerge.learners.compiling import call_update, own_code
from marlmerge.learners.quadq import HEAD_A, HEAD_B, HEAD_C
from marlmerge.learners.quadq_fast import FastQuadQUpdater
from marlmerge.learners.quadq_flat import FastSpec, adam_step, td_weights, unflatten
from marlmerge.learners.quadq_peaks import peaks_targets, peaks_update


def fused_chunk(
    spec: FastSpec,
    flat: Tensor,
    target_flat: Tensor,
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    adam_scalars: Tensor,
    rows: Tensor,
    guide: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """`fast_chunk` for S seeds: flat, target_flat, exp_avg, exp_avg_sq [S, P] (the first,
    third and fourth updated in place), adam_scalars [k, 2] (the seeds are at the same update),
    rows [S, k, B, 2d + 3], each seed's imitation `guide` [S, k, B, 2] if it has a teacher.
    Returns the losses [S, k] and the gradients [S, k, P]."""
    d, hd = spec.obs_dim, spec.hidden
    s_, k, bsz = rows.shape[:3]
    obs = rows[..., :d]  # [S, k, B, d]
    act, rew = rows[..., d], rows[..., d + 1]  # [S, k, B]
    not_term = 1.0 - rows[..., d + 2]  # [S, k, B]
    next_obs = rows[..., d + 3 :]  # [S, k, B, d]

    tw1, tb1, tw2, tb2 = unflatten(target_flat, d, hd)
    c_sl = slice(HEAD_C * hd, (HEAD_C + 1) * hd)
    h_next = torch.bmm(next_obs.reshape(s_, k * bsz, d), tw1[:, c_sl].transpose(1, 2))
    h_next = torch.relu(h_next.view(s_, k, bsz, hd) + tb1[:, None, None, c_sl])  # [S, k, B, H]
    v_next = torch.stack(  # [S, k, B]; one product per seed (see the module docstring)
        [torch.matmul(h_next[j], tw2[j, HEAD_C]) + tb2[j, HEAD_C] for j in range(s_)]
    )
    y = rew + spec.gamma * not_term * v_next  # [S, k, B]

    w1, b1, w2, b2 = unflatten(flat, d, hd)
    losses, grads = [], []
    for i in range(k):
        x, a = obs[:, i], act[:, i]  # [S, B, d], [S, B]
        pre = torch.baddbmm(b1[:, None, :], x, w1.transpose(1, 2))  # [S, B, 3H]
        h = torch.relu(pre).view(s_, bsz, 3, hd)
        z = (h * w2[:, None]).sum(-1) + b2[:, None]  # [S, B, 3]
        s_a, s_b = torch.sigmoid(z[..., HEAD_A]), torch.sigmoid(z[..., HEAD_B])
        big_a = -(spec.a_min + spec.a_span * s_a)  # [S, B]
        diff = spec.low + spec.span * s_b - a  # B(s) - a, [S, B]
        delta = big_a * diff * diff + z[..., HEAD_C] - y[:, i]
        # the loss per seed, recomputed from its own slices: sharing `delta` with the
        # gradients would change how the compiler fuses (and rounds) them
        losses.append(torch.stack([_seed_loss(spec, big_a, diff, z, y, i, j) for j in range(s_)]))
        w = td_weights(spec, delta)  # [S, B], None: all 1 (the paper's loss)
        g = (delta if w is None else w * delta) * (2.0 / bsz)
        dz_b = g * 2.0 * big_a * diff * spec.span * s_b * (1.0 - s_b)  # [S, B]
        if guide is not None:  # the imitation term, as `fast_chunk` has it
            miss = guide[:, i, :, 1] * (diff + a - guide[:, i, :, 0])  # w (B(s) - t), [S, B]
            dz_b = dz_b + miss * (2.0 * spec.imitation / bsz) * spec.span * s_b * (1.0 - s_b)
        dz = torch.stack(
            [g * diff * diff * (-spec.a_span) * s_a * (1.0 - s_a), dz_b, g], dim=-1
        )  # [S, B, 3]
        dw2, db2 = (dz.unsqueeze(-1) * h).sum(1), dz.sum(1)  # [S, 3, H], [S, 3]
        dpre = torch.where(pre > 0, (dz.unsqueeze(-1) * w2[:, None]).view(s_, bsz, 3 * hd), 0.0)
        dw1_t = torch.stack([torch.mm(x[j].t(), dpre[j]) for j in range(s_)])  # [S, d, 3H]
        grad = torch.cat(
            [dw1_t.transpose(1, 2).reshape(s_, -1), dpre.sum(1), dw2.reshape(s_, -1), db2], -1
        )  # [S, P]
        grads.append(grad)
        adam_step(spec, flat, exp_avg, exp_avg_sq, grad, adam_scalars[i])
    return torch.stack(losses, -1), torch.stack(grads, 1)


def _seed_loss(
    spec: FastSpec, big_a: Tensor, diff: Tensor, z: Tensor, y: Tensor, i: int, j: int
) -> Tensor:
    """Seed j's TD loss of update i, as `fast_chunk` computes it (a scalar)."""
    delta = big_a[j] * diff[j] * diff[j] + z[j, :, HEAD_C] - y[j, i]  # [B]
    w = td_weights(spec, delta)
    return (delta * delta).mean() if w is None else (w * delta * delta).mean()


def fused_chunk_peaks(
    spec: FastSpec,
    flat: Tensor,
    target_flat: Tensor,
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    adam_scalars: Tensor,
    rows: Tensor,
) -> tuple[Tensor, Tensor]:
    """`fast_chunk_peaks` (K = `spec.peaks` > 1 quadratic pieces) for S seeds, with the
    arguments and returns of `fused_chunk` (no imitation). Each seed's targets and gradients
    are its own run's functions (`peaks_targets`, `peaks_update`) on its own slices, and
    only Adam is batched: computed on [S, ...] tensors, the compiled gradients came out a
    last bit apart. One graph of 8 seeds costs 5.2x one seed's in
    `benchmarks/bench_seed_fusion.py --peaks 3`, about 7x in training (docs/scale-out.md)."""
    d, s_ = spec.obs_dim, rows.shape[0]
    y = torch.stack([peaks_targets(spec, target_flat[j], rows[j]) for j in range(s_)])  # [S, k, B]
    params = unflatten(flat, d, spec.hidden, 1, spec.peaks)
    losses, grads = [], []
    for i in range(rows.shape[1]):
        x, act = rows[:, i, :, :d], rows[:, i, :, d : d + 1]  # [S, B, d], [S, B, 1]
        each = [
            peaks_update(spec, [t[j] for t in params], x[j], act[j], y[j, i]) for j in range(s_)
        ]
        grad = torch.stack([g for _, g in each])  # [S, P]
        losses.append(torch.stack([loss for loss, _ in each]))
        grads.append(grad)
        adam_step(spec, flat, exp_avg, exp_avg_sq, grad, adam_scalars[i])
    return torch.stack(losses, -1), torch.stack(grads, 1)


class FusedQuadQUpdates:
    """Steps S `FastQuadQUpdater`s (one per seed, equal settings, at the same update count)
    with one `fused_chunk` call. Their weights, targets and Adam moments live in [S, P]
    buffers here, each updater (and its loss module's weights) holding views of its row
    (`FastQuadQUpdater.share`), so a call updates them in place with nothing to gather or
    scatter; each updater keeps its own bookkeeping (update count, target copies)."""

    def __init__(self, updaters: Sequence[FastQuadQUpdater], compile: bool) -> None:
        specs = {u.spec for u in updaters}
        teachers = {u.teacher is None for u in updaters}
        # the first updater's Adam scalars (its learning-rate schedule) serve every seed
        steps = {
            (u.k, u.period, u.lr_end_fraction, u.lr_decay_updates, u.flush_denormals)
            for u in updaters
        }
        if len(specs) != 1 or len(steps) != 1 or len(teachers) != 1:
            raise ValueError("fused updates need seeds with the same learner settings")
        spec = next(iter(specs))
        if spec.action_dim != 1:  # (several peaks take no imitation: their updaters refuse it)
            raise ValueError("fused updates of several seeds take one action component")
        self.updaters = list(updaters)
        self.k = self.updaters[0].k
        us = self.updaters
        # [S, P] each: the seeds' state lives here, each updater holding views of its row
        self.flat = torch.stack([u.flat for u in us])
        self.target_flat = torch.stack([u.target_flat for u in us])
        self.exp_avg = torch.stack([u.exp_avg for u in us])
        self.exp_avg_sq = torch.stack([u.exp_avg_sq for u in us])
        for j, u in enumerate(us):
            u.share(self.flat[j], self.target_flat[j], self.exp_avg[j], self.exp_avg_sq[j])
        chunk = fused_chunk if spec.peaks == 1 else fused_chunk_peaks
        fn: Callable[..., tuple[Tensor, Tensor]] = functools.partial(chunk, spec)
        self.compiled = compile
        # the C++ wrapper: the per-seed products make the Python one cost 0.5 ms a call
        opts = {"cpp_wrapper": True}
        self._fn = (
            torch.compile(own_code(fn), fullgraph=True, dynamic=False, options=opts)
            if compile
            else fn
        )
        self.compile_time_s: float | None = None

    @torch.no_grad()
    def step(self, rows: Tensor) -> Tensor:
        """k updates of every seed on rows [S, k, B, 2d + 3]; returns the losses [S, k]."""
        us = self.updaters
        if len({u.num_updates for u in us}) != 1:
            raise ValueError("fused updates need the seeds at the same update count")
        if any(u.flat.data_ptr() != self.flat[j].data_ptr() for j, u in enumerate(us)):
            raise RuntimeError("a fused seed's updater was rebuilt: its state is no longer shared")
        state = (self.flat, self.target_flat, self.exp_avg, self.exp_avg_sq)
        args: tuple[Tensor, ...] = (*state, us[0].adam_scalars(), rows)
        if us[0].teacher is not None:  # each seed's teacher labels its own minibatches
            args = (*args, torch.stack([u.guide(rows[j]) for j, u in enumerate(us)]))  # type: ignore[misc]
        first = self.compiled and self.compile_time_s is None
        (losses, _), took = call_update(
            self._fn, args, compiling=first, flush=us[0].flush_denormals
        )
        if took is not None:
            self.compile_time_s = took
        for u in us:
            u.advance()
        return losses
