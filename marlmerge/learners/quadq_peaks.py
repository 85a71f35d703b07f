"""The fast path's update of a quadratic Q of several pieces (`QuadraticQNet.peaks` > 1):
Q(s, a) = max_k A_k (B_k - a)^2 + C_k, hand-written gradients of its TD loss (checked against
autograd in the tests) on the flat parameters of `quadq_flat`."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from marlmerge.learners.quadq import (
    b_bounds,
    band_bounds,
    peak_rows,
)
from marlmerge.learners.quadq_flat import FastSpec, adam_step, td_weights, unflatten


def fast_chunk_peaks(
    spec: FastSpec,
    flat: Tensor,
    target_flat: Tensor,
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    adam_scalars: Tensor,
    rows: Tensor,
) -> Tensor:
    """`fast_chunk` for a network of K = `spec.peaks` > 1 pieces (one action component):
    Q(s, a) = max_k A_k (B_k - a)^2 + C_k, the target max_k C_target_k(s'). The TD error's
    gradient reaches only the piece that is largest at the replayed action (the envelope's
    derivative). With `spec.peak_share` = w > 0 the loss gains w (q_k(s, a) - y)^2 for every
    other piece k, so a piece that never wins still learns and can come back into the envelope
    (a piece that never wins otherwise never moves); with `spec.peak_share_heads` = "c" that
    error reaches only the losing pieces' levels C_k, not their A and B. With
    `spec.peak_bands` piece k's B lies in the k-th band of the range (`band_bounds`). Same
    arguments and return as `fast_chunk` (no imitation); the losses returned stay the TD
    losses."""
    d = spec.obs_dim
    y = peaks_targets(spec, target_flat, rows)  # [k, B]
    params = unflatten(flat, d, spec.hidden, 1, spec.peaks)
    losses = []
    for i in range(rows.shape[0]):
        loss, grad = peaks_update(spec, params, rows[i, :, :d], rows[i, :, d : d + 1], y[i])
        losses.append(loss)
        adam_step(spec, flat, exp_avg, exp_avg_sq, grad, adam_scalars[i])
    return torch.stack(losses)


def peaks_targets(spec: FastSpec, target_flat: Tensor, rows: Tensor) -> Tensor:
    """The TD targets r + gamma (1 - terminal) max_k C_target_k(s') [k, B] of packed
    minibatches rows [k, B, 2d + 3], from the target network (flat [P]): only its C heads are
    evaluated."""
    d, hd, kp = spec.obs_dim, spec.hidden, spec.peaks
    k, bsz = rows.shape[:2]
    rew = rows[..., d + 1]  # [k, B]
    not_term = 1.0 - rows[..., d + 2]  # [k, B]
    next_obs = rows[..., d + 3 :]  # [k, B, d]
    tw1, tb1, tw2, tb2 = unflatten(target_flat, d, hd, 1, kp)
    rows_c = peak_rows(kp)[2]
    c_sl = slice(2 * kp * hd, 3 * kp * hd)
    h_next = torch.relu(torch.matmul(next_obs, tw1[c_sl].t()) + tb1[c_sl])  # [k, B, K H]
    h_next = h_next.view(k, bsz, kp, hd)
    v_next = ((h_next * tw2[rows_c]).sum(-1) + tb2[rows_c]).amax(-1)  # [k, B]
    return rew + spec.gamma * not_term * v_next


def peaks_update(
    spec: FastSpec, params: Sequence[Tensor], x: Tensor, act: Tensor, y: Tensor
) -> tuple[Tensor, Tensor]:
    """One update's TD loss (a scalar) and its gradient [P] for the K-piece network with
    parameters `params` (w1, b1, w2, b2: `unflatten`'s views) on the minibatch x [B, d],
    act [B, 1], targets y [B] (`peaks_targets`; `fast_chunk_peaks` applies Adam)."""
    hd, kp = spec.hidden, spec.peaks
    w1, b1, w2, b2 = params
    b_low, b_span = spec.low, spec.span  # B_k = b_low + b_span * sigmoid(z_B_k)
    if spec.peak_bands:
        b_low, b_span = b_bounds(*band_bounds(spec.low, spec.span, kp), x)  # [K] each
    n = 3 * kp
    rows_a, rows_b, rows_c = peak_rows(kp)
    bsz = x.shape[0]
    pre = torch.addmm(b1, x, w1.t())  # [B, 3K H]
    h = torch.relu(pre).view(bsz, n, hd)  # [B, 3K, H]
    z = (h * w2).sum(-1) + b2  # [B, 3K]
    s_a = torch.sigmoid(z[:, rows_a])  # [B, K]
    s_b = torch.sigmoid(z[:, rows_b])  # [B, K]
    big_a = -(spec.a_min + spec.a_span * s_a)  # [B, K]
    diff = b_low + b_span * s_b - act  # B_k(s) - a, [B, K]
    q_k = big_a * diff * diff + z[:, rows_c]  # [B, K]
    q, best = q_k.max(-1)  # [B]
    top = (torch.arange(kp, device=x.device) == best.unsqueeze(-1)).to(q.dtype)  # [B, K]
    delta = q - y
    w = td_weights(spec, delta)
    wd = delta if w is None else w * delta
    loss = (wd * delta).mean()
    g = (wd * (2.0 / bsz)).unsqueeze(-1) * top  # dL/dq_k [B, K]
    g_c = g  # dL/dC_k; g stays dL/dA_k, dL/dB_k
    if spec.peak_share > 0.0:  # the losing pieces' own errors
        g_c = g + (spec.peak_share * 2.0 / bsz) * (1.0 - top) * (q_k - y.unsqueeze(-1))
        if spec.peak_share_heads == "abc":  # "c": they reach the levels only
            g = g_c
    dz = torch.cat(
        [
            g * diff * diff * (-spec.a_span) * s_a * (1.0 - s_a),
            g * 2.0 * big_a * diff * b_span * s_b * (1.0 - s_b),
            g_c,
        ],
        dim=-1,
    )  # [B, 3K]
    dw2 = (dz.unsqueeze(-1) * h).sum(0)  # [3K, H]
    db2 = dz.sum(0)  # [3K]
    dpre = torch.where(pre > 0, (dz.unsqueeze(-1) * w2).view(bsz, n * hd), 0.0)
    dw1_t = torch.mm(x.t(), dpre)  # [d, 3K H]
    return loss, torch.cat([dw1_t.t().reshape(-1), dpre.sum(0), dw2.reshape(-1), db2])  # [P]
