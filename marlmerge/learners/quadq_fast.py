"""The quadratic-Q learner's engineered update path (the network and its loss: `quadq`).

* `fast_chunk` - k updates in one call: hand-written gradients of the same loss as
  :class:`~marlmerge.learners.quadq.QuadraticQLoss` (tested against it) and a flat Adam, on
  one flat parameter vector (`marlmerge.learners.quadq_flat`); a Q of several pieces:
  `marlmerge.learners.quadq_peaks.fast_chunk_peaks`.
* :class:`FastQuadQUpdater` - samples minibatches from a packed replay
  (`marlmerge.learners.packed_replay`) and steps them, optionally ``torch.compile``-d,
  updating the loss module's parameters in place; S seeds in one call:
  `marlmerge.learners.quadq_fused`.

All randomness comes from caller-supplied ``torch.Generator`` objects.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import replace

import torch
from tensordict import TensorDictParams
from torch import Tensor

from marlmerge.config.training import PEAK_SHARE_HEADS
from marlmerge.learners.compiling import call_update, own_code
from marlmerge.learners.packed_replay import TransitionReplay
from marlmerge.learners.quadq import (
    QuadraticQLoss,
    QuadraticQNet,
    b_bounds,
    head_rows,
)
from marlmerge.learners.quadq_flat import (
    TEACHER_CHANGED,
    FastSpec,
    Teacher,
    adam_step,
    flat_greedy,
    param_layout,
    td_weights,
    unflatten,
)
from marlmerge.learners.quadq_peaks import fast_chunk_peaks

__all__ = ["FastQuadQUpdater", "fast_chunk"]


def fast_chunk(
    spec: FastSpec,
    flat: Tensor,
    target_flat: Tensor,
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    adam_scalars: Tensor,
    rows: Tensor,
    guide: Tensor | None = None,
) -> Tensor:
    """k sequential TD(0) + Adam updates on packed minibatches ``rows`` [k, B, 2d + m + 2]
    (m action components: `FastSpec.action_dim`).

    With ``guide`` [k, B, 2m] (a teacher's command t and a 0/1 weight w per row and component,
    `FastQuadQUpdater.imitate`), each update's loss also has `spec.imitation` x mean over the
    rows of sum_j w (B_j(s) - t_j)^2, which pulls B(s) towards the teacher where w is 1; the
    losses returned stay the TD losses. With `spec.expectile` != 0.5 each row's squared TD
    error is weighted by `td_weights`.

    ``flat``/``exp_avg``/``exp_avg_sq`` [P] are updated in place; ``target_flat`` [P] is read
    only (the target is fixed within a chunk, so all k targets come from one matmul).
    ``adam_scalars`` [k, 2] = (lr / (1 - beta1^t), sqrt(1 - beta2^t)) per update, computed in
    double precision like non-capturable ``torch.optim.Adam``. Gradients are written by hand
    (checked against autograd of :class:`QuadraticQLoss` in the tests). Returns losses [k].
    """
    d, hd, m = spec.obs_dim, spec.hidden, spec.action_dim
    n = 2 * m + 1  # heads A_0..A_{m-1}, B_0..B_{m-1}, C
    rows_a, rows_b, c = head_rows(m)
    k, bsz = rows.shape[0], rows.shape[1]
    obs = rows[..., :d]  # [k, B, d]
    act = rows[..., d : d + m]  # [k, B, m]
    rew = rows[..., d + m]  # [k, B]
    not_term = 1.0 - rows[..., d + m + 1]  # [k, B]
    next_obs = rows[..., d + m + 2 :]  # [k, B, d]
    lows = (spec.low, *(lo for lo, _ in spec.extra))
    low, span = b_bounds(lows, (spec.span, *(sp for _, sp in spec.extra)), rows)

    # Target: max_a' Q_target(s', a') = C_target(s'); only the C head is evaluated.
    tw1, tb1, tw2, tb2 = unflatten(target_flat, d, hd, m)
    c_sl = slice(c * hd, (c + 1) * hd)
    h_next = torch.relu(torch.matmul(next_obs, tw1[c_sl].t()) + tb1[c_sl])  # [k, B, H]
    v_next = torch.matmul(h_next, tw2[c]) + tb2[c]  # [k, B]
    y = rew + spec.gamma * not_term * v_next  # [k, B]

    w1, b1, w2, b2 = unflatten(flat, d, hd, m)
    losses = []
    for i in range(k):
        x = obs[i]  # [B, d]
        a = act[i]  # [B, m]
        pre = torch.addmm(b1, x, w1.t())  # [B, nH]
        h = torch.relu(pre).view(bsz, n, hd)  # [B, n, H]
        z = (h * w2).sum(-1) + b2  # [B, n]
        s_a = torch.sigmoid(z[:, rows_a])  # [B, m]
        s_b = torch.sigmoid(z[:, rows_b])  # [B, m]
        big_a = -(spec.a_min + spec.a_span * s_a)  # [B, m]
        diff = low + span * s_b - a  # B(s) - a, [B, m]
        q = (big_a * diff * diff).sum(-1) + z[:, c]  # [B]
        delta = q - y[i]
        w = td_weights(spec, delta)  # the expectile's weights [B], None: all 1
        wd = delta if w is None else w * delta
        losses.append((wd * delta).mean())
        # Backward of mean(w delta^2) by hand (w is piecewise constant in delta).
        g = (wd * (2.0 / bsz)).unsqueeze(-1)  # dL/dq [B, 1]
        dz_b = g * 2.0 * big_a * diff * span * s_b * (1.0 - s_b)  # [B, m]
        if guide is not None:  # d/dz_b of imitation x mean(sum(w (B(s) - t)^2))
            miss = guide[i, :, m:] * (diff + a - guide[i, :, :m])  # w (B(s) - t), [B, m]
            dz_b = dz_b + miss * (2.0 * spec.imitation / bsz) * span * s_b * (1.0 - s_b)
        dz = torch.cat(
            [g * diff * diff * (-spec.a_span) * s_a * (1.0 - s_a), dz_b, g], dim=-1
        )  # [B, n]
        dw2 = (dz.unsqueeze(-1) * h).sum(0)  # [n, H]
        db2 = dz.sum(0)  # [n]
        dpre = torch.where(pre > 0, (dz.unsqueeze(-1) * w2).view(bsz, n * hd), 0.0)  # [B, nH]
        dw1_t = torch.mm(x.t(), dpre)  # [d, nH]; 2-3x faster than mm(dpre.t(), x) here
        db1 = dpre.sum(0)  # [nH]
        grad = torch.cat([dw1_t.t().reshape(-1), db1, dw2.reshape(-1), db2])  # [P]
        adam_step(spec, flat, exp_avg, exp_avg_sq, grad, adam_scalars[i])
    return torch.stack(losses)


class FastQuadQUpdater:
    """Engineered update path for :class:`QuadraticQLoss` with a :class:`QuadraticQNet`.

    Per call of :meth:`step`: sample ``k`` minibatches of ``batch_size`` in one ``randint`` +
    ``index_select`` from a :class:`TransitionReplay`, compute all k TD targets with the target
    network in one matmul, then run k sequential updates (hand-written gradients of the same
    loss as :class:`QuadraticQLoss`, Adam on one flat parameter vector), optionally as one
    ``torch.compile``-d call. The target is copied every ``target_update_period`` updates.

    The online and target parameters of ``loss`` (and therefore of the network passed to the
    loss) are re-pointed to views of two flat buffers, so the loss module, the acting network
    and this updater always share the same weights: no syncing is needed.

    Measured on 2 shared CPU cores (``benchmarks/bench_update.py``), minibatch 32, hidden 64,
    ``torch.set_num_threads(1)``: compiled k=10 ~18-27k updates/s (compile ~20 s cold, ~1 s
    from the inductor cache), eager k=10 ~2.6-3.8k/s, vs ~0.3-0.8k/s for the plain torchrl
    LossModule + ReplayBuffer loop. Two threads are slower (tiny kernels, shared cores).

    Semantics vs. one sample + one update per call: identical loss and optimiser; the only
    difference is that the k minibatches are drawn from the buffer as it is at the start of the
    call (k env steps of staleness at most if you interleave 1 env step per update).

    Args:
        loss: the loss module (its network must be a :class:`QuadraticQNet`).
        replay: the replay to sample from when :meth:`step` gets no rows; ``None`` if the
            caller always passes rows (e.g. sampled from a torchrl ``ReplayBuffer``).

    Keyword Args:
        lr, betas, eps: Adam hyperparameters (paper: lr 1e-3).
        batch_size: minibatch size (paper: 32).
        updates_per_call: k; must divide ``target_update_period``.
        target_update_period: p, hard copy online -> target every p updates (paper: 500).
        compile: wrap the chunk in ``torch.compile(fullgraph=True, dynamic=False)``.
        generator: RNG for sampling minibatch indices (required: no global RNG).
        expectile: tau of the TD loss (`td_weights`); 0.5: the squared error of
            :class:`QuadraticQLoss`.
        peak_share: with several peaks, the weight of each losing piece's own TD error
            (`fast_chunk_peaks`); 0: the envelope's error alone.
        peak_share_heads: the losing pieces' heads that error reaches: "abc" or "c".
        lr_end_fraction, lr_decay_updates: the learning rate of update t is lr x (1 - (1 -
            fraction) x min(t / lr_decay_updates, 1)): a linear decay to lr x fraction (1: the
            constant lr, computed as before). An input of the compiled chunk, not a constant.
        flush_denormals: run each chunk with subnormal floats flushed to zero
            (`denormals_flushed`): faster once dead units' moments are subnormal, and a change
            of the arithmetic wherever a subnormal arises (off: as before, bit for bit).
    """

    def __init__(
        self,
        loss: QuadraticQLoss,
        replay: TransitionReplay | None,
        *,
        generator: torch.Generator,
        lr: float = 1e-3,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        batch_size: int = 32,
        updates_per_call: int = 10,
        target_update_period: int = 500,
        compile: bool = False,
        compile_kwargs: dict | None = None,
        expectile: float = 0.5,
        peak_share: float = 0.0,
        peak_share_heads: str = "abc",
        lr_end_fraction: float = 1.0,
        lr_decay_updates: int = 1,
        flush_denormals: bool = False,
    ) -> None:
        net = loss.value_network
        if not 0.0 < lr_end_fraction <= 1.0 or lr_decay_updates < 1:
            raise ValueError(
                f"lr_end_fraction must be in (0, 1] and lr_decay_updates >= 1, got "
                f"{lr_end_fraction} and {lr_decay_updates}"
            )
        if not isinstance(net, QuadraticQNet):
            raise TypeError("FastQuadQUpdater needs a QuadraticQLoss built on a QuadraticQNet")
        if peak_share < 0.0 or (peak_share > 0.0 and net.peaks == 1):
            raise ValueError(
                f"peak_share = {peak_share} weighs the losing pieces of a Q of several peaks: "
                f"it must be >= 0, and 0 with one peak (this network has {net.peaks})"
            )
        if peak_share_heads not in PEAK_SHARE_HEADS:
            raise ValueError(
                f"peak_share_heads must be one of {PEAK_SHARE_HEADS}, got {peak_share_heads!r}"
            )
        if target_update_period % updates_per_call != 0:
            raise ValueError("updates_per_call must divide target_update_period")
        if replay is not None and replay.obs_dim != net.obs_dim:
            raise ValueError("replay.obs_dim != network obs_dim")
        self.loss = loss
        self.replay = replay
        self.generator = generator
        self.batch_size = int(batch_size)
        self.k = int(updates_per_call)
        self.period = int(target_update_period)
        self.lr = float(lr)
        self.lr_end_fraction = float(lr_end_fraction)
        self.lr_decay_updates = int(lr_decay_updates)
        self.flush_denormals = bool(flush_denormals)
        self.betas = (float(betas[0]), float(betas[1]))
        self.num_updates = 0
        self.spec = FastSpec(
            obs_dim=net.obs_dim,
            hidden=net.hidden_dim,
            a_min=net.a_min,
            a_span=net.a_max - net.a_min,
            low=net.action_low,
            span=net.action_span,
            gamma=float(loss.gamma),
            lr=self.lr,
            beta1=self.betas[0],
            beta2=self.betas[1],
            eps=float(eps),
            extra=tuple((lo, hi - lo) for lo, hi in net.extra_bounds),
            expectile=float(expectile),
            peaks=net.peaks,
            peak_bands=net.peak_bands,
            peak_share=float(peak_share),
            peak_share_heads=peak_share_heads,
        )
        # This object owns the target updates: silence torchrl's "no updater" warning.
        loss._has_update_associated["value_network"] = True
        self.flat = self._alias(loss.value_network_params)
        self.target_flat = self._alias(loss.target_value_network_params)
        self.exp_avg = torch.zeros_like(self.flat)
        self.exp_avg_sq = torch.zeros_like(self.flat)
        self.teacher: Teacher | None = None
        self._compile_kwargs = (
            {"fullgraph": True, "dynamic": False, **(compile_kwargs or {})} if compile else None
        )
        self._build_chunk()

    def _build_chunk(self) -> None:
        chunk = fast_chunk if self.spec.peaks == 1 else fast_chunk_peaks
        self._eager_chunk = functools.partial(chunk, self.spec)
        self._fn: Callable[..., Tensor] = self._eager_chunk
        self.compile_time_s: float | None = None
        if self._compile_kwargs is not None:
            self._fn = torch.compile(own_code(self._eager_chunk), **self._compile_kwargs)

    def imitate(self, teacher: Teacher, weight: float) -> None:
        """Add an imitation term of `weight` to the loss (`fast_chunk`'s `guide`): before each
        call, `teacher` (obs [N, d], the greedy commands B(s) [N, m] -> commands [N, m], e.g.
        the shield's verdict on them) labels the call's minibatches, and B(s) is pulled towards
        the teacher's command wherever it differs from B(s) by more than `TEACHER_CHANGED`."""
        if weight <= 0.0:
            raise ValueError(f"imitation weight must be > 0, got {weight}")
        if self.spec.peaks > 1:
            raise ValueError(f"imitation takes a network of one peak, got {self.spec.peaks}")
        self.teacher = teacher
        self.spec = replace(self.spec, imitation=float(weight))
        self._build_chunk()

    def guide(self, rows: Tensor) -> Tensor | None:
        """The teacher's labels of minibatches ``rows`` [..., B, row]: [..., B, 2m] (commands,
        then 0/1 weights); None without a teacher."""
        if self.teacher is None:
            return None
        d, m = self.spec.obs_dim, self.spec.action_dim
        obs = rows[..., :d].reshape(-1, d)  # [N, d]
        greedy = flat_greedy(self.spec, self.flat, obs)  # [N, m], the weights before this call
        taught = self.teacher(obs, greedy).to(greedy.dtype)  # [N, m]
        weight = ((taught - greedy).abs() > TEACHER_CHANGED).to(greedy.dtype)
        return torch.cat([taught, weight], -1).view(*rows.shape[:-1], 2 * m)

    def _alias(self, params: TensorDictParams, flat: Tensor | None = None) -> Tensor:
        """Copy ``params`` into one flat buffer [P] (``flat``, e.g. a row of S seeds' stacked
        buffer, or a new one) and re-point each tensor to a view of it."""
        s = self.spec
        layout = param_layout(s.obs_dim, s.hidden, s.action_dim, s.peaks)
        tensors = [params.get(key) for key, _ in layout]
        for t, (key, shape) in zip(tensors, layout, strict=True):
            if tuple(t.shape) != shape:
                raise ValueError(f"parameter {key} has shape {tuple(t.shape)}, expected {shape}")
        values = torch.cat([t.detach().reshape(-1) for t in tensors])
        flat = values if flat is None else flat.copy_(values)
        for t, view in zip(
            tensors, unflatten(flat, s.obs_dim, s.hidden, s.action_dim, s.peaks), strict=True
        ):
            t.data = view
        return flat

    def share(self, flat: Tensor, target_flat: Tensor, exp_avg: Tensor, exp_avg_sq: Tensor) -> None:
        """Keep this updater's weights, target and Adam moments in the given [P] tensors (rows
        of S seeds' stacked buffers: ``FusedQuadQUpdates`` then updates them in place, with
        nothing to gather or scatter per call); the loss module's weights become views of
        them. The values are this updater's own."""
        self.flat = self._alias(self.loss.value_network_params, flat)
        self.target_flat = self._alias(self.loss.target_value_network_params, target_flat)
        self.exp_avg = exp_avg.copy_(self.exp_avg)
        self.exp_avg_sq = exp_avg_sq.copy_(self.exp_avg_sq)

    def lr_at(self, t: int) -> float:
        """The learning rate of update t (1-based): `lr`, or its linear decay."""
        if self.lr_end_fraction == 1.0:
            return self.lr
        done = min(t / self.lr_decay_updates, 1.0)
        return self.lr * (1.0 - (1.0 - self.lr_end_fraction) * done)

    def adam_scalars(self) -> Tensor:
        """[k, 2]: (lr_t / (1 - beta1^t), sqrt(1 - beta2^t)) for the next k updates."""
        b1, b2 = self.betas
        vals = []
        for t in range(self.num_updates + 1, self.num_updates + self.k + 1):
            vals.append((self.lr_at(t) / (1.0 - b1**t), math.sqrt(1.0 - b2**t)))
        return torch.tensor(vals, dtype=self.flat.dtype, device=self.flat.device)  # [k, 2]

    def state_dict(self) -> dict[str, Tensor | int]:
        """Optimiser state (weights are in ``loss.state_dict()``, target included)."""
        return {
            "num_updates": self.num_updates,
            "exp_avg": self.exp_avg.clone(),
            "exp_avg_sq": self.exp_avg_sq.clone(),
        }

    def load_state_dict(self, state: dict[str, Tensor | int]) -> None:
        self.num_updates = int(state["num_updates"])
        self.exp_avg.copy_(state["exp_avg"])
        self.exp_avg_sq.copy_(state["exp_avg_sq"])

    @torch.no_grad()
    def step(self, rows: Tensor | None = None) -> Tensor:
        """Run k updates; ``rows`` [k, B, 2d + 3] overrides sampling. Returns losses [k]."""
        if rows is None:
            if self.replay is None:
                raise ValueError("no replay to sample from: pass rows [k, batch, 2d + 3]")
            rows = self.replay.sample((self.k, self.batch_size), self.generator)
        if rows.shape[0] != self.k:
            raise ValueError(f"rows must hold k={self.k} minibatches, got {rows.shape[0]}")
        args = (self.flat, self.target_flat, self.exp_avg, self.exp_avg_sq, self.adam_scalars())
        extra = () if self.teacher is None else (self.guide(rows),)
        first = self.compile_time_s is None and self._fn is not self._eager_chunk
        losses, took = call_update(
            self._fn, (*args, rows, *extra), compiling=first, flush=self.flush_denormals
        )
        if took is not None:
            self.compile_time_s = took
        self.advance()
        return losses

    def advance(self) -> None:
        """Count a chunk of k updates; copy the target when its period is reached."""
        self.num_updates += self.k
        if self.num_updates % self.period == 0:
            self.target_flat.copy_(self.flat)
