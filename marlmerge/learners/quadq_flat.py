"""The quadratic-Q network as one flat parameter vector, for the fast path's hand-written
updates (`quadq_fast`, `quadq_peaks`, `quadq_fused`): the constants baked into an update
(`FastSpec`), the parameters' order (`param_layout`, `unflatten`), the greedy action from flat
parameters, the expectile weights of the TD loss and a flat Adam step."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from marlmerge.learners.quadq import (
    b_bounds,
    head_rows,
    n_heads,
)

Teacher = Callable[[Tensor, Tensor], Tensor]
"""obs [N, d], commands [N, m] (m/s^2) -> the teacher's commands [N, m]
(`FastQuadQUpdater.imitate`)."""


TEACHER_CHANGED = 1e-4
"""A teacher's command further than this (m/s^2) from B(s) is imitated; nearer, it agrees."""


@dataclass(frozen=True)
class FastSpec:
    """Constants baked into the fast update (Python floats, so compile treats them as such)."""

    obs_dim: int
    hidden: int
    a_min: float
    a_span: float
    low: float
    span: float
    gamma: float
    lr: float
    beta1: float
    beta2: float
    eps: float
    extra: tuple[tuple[float, float], ...] = ()
    """(low, span) of each action component after the first (`QuadraticQNet.extra_bounds`)."""
    imitation: float = 0.0
    """Weight of the imitation term (`FastQuadQUpdater.imitate`); 0: none, the paper's loss."""
    expectile: float = 0.5
    """tau of the TD loss's expectile (`td_weights`); 0.5: the paper's squared error."""
    peaks: int = 1
    """K quadratic pieces (`QuadraticQNet.peaks`); 1: the paper's network."""
    peak_bands: bool = False
    """With K > 1 pieces: piece k's B in the k-th of K equal bands (`QuadraticQNet.peak_bands`)."""
    peak_share: float = 0.0
    """With K > 1 pieces: weight of each losing piece's own squared error to the same target
    (`fast_chunk_peaks`); 0: only the envelope's error, the winning piece alone learns."""
    peak_share_heads: str = "abc"
    """The heads of a losing piece that `peak_share` reaches: "abc" all three, "c" its level."""

    @property
    def action_dim(self) -> int:
        return 1 + len(self.extra)


def param_layout(
    obs_dim: int, hidden: int, action_dim: int = 1, peaks: int = 1
) -> list[tuple[tuple[str, ...], tuple[int, ...]]]:
    """Order and shapes of the :class:`QuadraticQNet` parameters in the flat buffers."""
    n = n_heads(action_dim, peaks)
    return [
        (("hidden", "weight"), (n * hidden, obs_dim)),
        (("hidden", "bias"), (n * hidden,)),
        (("head_weight",), (n, hidden)),
        (("head_bias",), (n,)),
    ]


def unflatten(
    flat: Tensor, obs_dim: int, hidden: int, action_dim: int = 1, peaks: int = 1
) -> list[Tensor]:
    """Flat parameters [..., P] -> views w1 [..., nH, d], b1 [..., nH], w2 [..., n, H],
    b2 [..., n] with n = `n_heads` (the leading dimensions, e.g. seeds, kept)."""
    out, o = [], 0
    lead = flat.shape[:-1]
    for _, shape in param_layout(obs_dim, hidden, action_dim, peaks):
        n = math.prod(shape)
        out.append(flat[..., o : o + n].view(*lead, *shape))
        o += n
    return out


def flat_greedy(spec: FastSpec, flat: Tensor, obs: Tensor) -> Tensor:
    """B(s) [N, m] of the network with flat parameters ``flat`` [P] for obs [N, d] (as
    `QuadraticQNet.greedy`)."""
    m = spec.action_dim
    w1, b1, w2, b2 = unflatten(flat, spec.obs_dim, spec.hidden, m)
    rows_b = head_rows(m)[1]
    h = torch.relu(torch.addmm(b1, obs, w1.t())).view(obs.shape[0], 2 * m + 1, spec.hidden)
    z_b = (h * w2).sum(-1)[:, rows_b] + b2[rows_b]  # [N, m]
    lows = (spec.low, *(lo for lo, _ in spec.extra))
    low, span = b_bounds(lows, (spec.span, *(sp for _, sp in spec.extra)), obs)
    return low + span * torch.sigmoid(z_b)


def td_weights(spec: FastSpec, delta: Tensor) -> Tensor | None:
    """The expectile loss's weight per TD error delta = Q(s, a) - y [...]: 2 (1 - tau) where
    Q is above its target, 2 tau where below (tau = `spec.expectile`). Below 0.5 the fit
    follows the worse outcomes more (Q is a low expectile of the return: risk averse). None
    at 0.5, where every weight is 1: the paper's squared error, untouched."""
    if spec.expectile == 0.5:
        return None
    return torch.where(delta > 0, 2.0 * (1.0 - spec.expectile), 2.0 * spec.expectile)


def adam_step(
    spec: FastSpec,
    flat: Tensor,
    exp_avg: Tensor,
    exp_avg_sq: Tensor,
    grad: Tensor,
    scalars: Tensor,
) -> None:
    """One Adam step in place (torch.optim.Adam semantics: no weight decay, no amsgrad) on
    ``flat``, ``exp_avg``, ``exp_avg_sq`` [..., P] from ``grad`` [..., P]; ``scalars`` [2] =
    (lr / (1 - beta1^t), sqrt(1 - beta2^t)) of this update (`FastQuadQUpdater.adam_scalars`)."""
    exp_avg.lerp_(grad, 1.0 - spec.beta1)
    exp_avg_sq.mul_(spec.beta2).addcmul_(grad, grad, value=1.0 - spec.beta2)
    denom = exp_avg_sq.sqrt() / scalars[1] + spec.eps
    flat.sub_(scalars[0] * exp_avg / denom)
