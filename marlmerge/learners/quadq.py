"""Quadratic-in-action Q-learning (Wang & Chan, ramp merge with a continuous action space).

The Q-function is quadratic in the 1-D action (the longitudinal acceleration, m/s^2):

    Q(s, a) = A(s) * (B(s) - a)^2 + C(s),   A(s) < 0,

so the greedy action is ``a* = B(s)`` and ``max_a Q(s, a) = C(s)``. A, B and C are three
independent two-layer MLPs of the state; :class:`QuadraticQNet` stores them fused (one
``Linear(obs_dim, 3 * hidden)`` plus a block-diagonal second layer), which is the same function
as three separate MLPs with a third of the kernel launches.

Contents:

* :class:`QuadraticQNet` - the network; ``forward(obs) -> (A, B, C)``, ``q``, ``greedy``,
  ``max_value``.
* :class:`QuadraticQLoss` - a torchrl :class:`~torchrl.objectives.LossModule`, the public and
  tested definition of the TD(0) loss of the paper (eq. 10), with target parameters it owns.
* :class:`PeriodicHardUpdate` - torchrl's ``HardUpdate`` with "copy every ``period`` updates".
* :class:`GaussianExploration` - greedy action + linearly decaying Gaussian noise, clipped.

The engineered training path (packed tensor replay, many minibatches per sampling call,
hand-written gradients of the same loss, a flat Adam, optional ``torch.compile``) is
`marlmerge.learners.quadq_fast`; S seeds in one call, `marlmerge.learners.quadq_fused`.

All randomness comes from caller-supplied ``torch.Generator`` objects.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import dispatch
from tensordict.utils import NestedKey, unravel_key
from torch import Tensor, nn
from torchrl.objectives import HardUpdate, LossModule

from marlmerge.config.training import PAPER_GAMMA

__all__ = [
    "DEFAULT_ACTION_BOUNDS",
    "GaussianExploration",
    "PeriodicHardUpdate",
    "QuadraticQLoss",
    "QuadraticQNet",
    "noisy_greedy_action",
]

DEFAULT_ACTION_BOUNDS: tuple[float, float] = (-4.5, 2.5)
"""Ego acceleration bounds, m/s^2 (``EgoConfig.accel_bounds_mps2``)."""

HEAD_A, HEAD_B, HEAD_C = 0, 1, 2
"""Row of each head in the fused second layer (one action component; with m components the
rows are A_0..A_{m-1}, B_0..B_{m-1}, C: `head_rows`)."""


def head_rows(m: int) -> tuple[slice, slice, int]:
    """The rows of the A heads, the B heads and the C head for m action components."""
    return slice(0, m), slice(m, 2 * m), 2 * m


def n_heads(m: int, peaks: int = 1) -> int:
    """Heads of the network: 2m + 1 with one peak (A_0..A_{m-1}, B_0..B_{m-1}, C); 3 per
    peak with several (one action component: A_0..A_{K-1}, B_0..B_{K-1}, C_0..C_{K-1})."""
    return 2 * m + 1 if peaks == 1 else 3 * peaks


def peak_rows(peaks: int) -> tuple[slice, slice, slice]:
    """The rows of the A, B and C heads of a network with `peaks` pieces (one component)."""
    return slice(0, peaks), slice(peaks, 2 * peaks), slice(2 * peaks, 3 * peaks)


def band_bounds(low: float, span: float, peaks: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(low, span) of each of `peaks` equal bands of the command range [low, low + span]."""
    return tuple(low + span * k / peaks for k in range(peaks)), (span / peaks,) * peaks


def b_bounds(
    lows: tuple[float, ...], spans: tuple[float, ...], like: Tensor
) -> tuple[Tensor | float, Tensor | float]:
    """The B heads' (low, span), one per action component (or per piece, with `peak_bands`):
    Python numbers for the paper's one component (as it always computed them), else [m] ([K])
    tensors of `like`'s dtype and device."""
    if len(lows) == 1:
        return lows[0], spans[0]
    low, span = (torch.tensor(v, dtype=like.dtype, device=like.device) for v in (lows, spans))
    return low, span


# ----------------------------------------------------------------------------------------------
# Network
# ----------------------------------------------------------------------------------------------


class QuadraticQNet(nn.Module):
    """Q(s, a) = A(s) (B(s) - a)^2 + C(s) with three two-layer MLPs fused into one.

    With m > 1 action components (`extra_bounds`: the acceleration, then e.g. the join of
    `ego.join = "chosen"`) the form is separable, Q(s, a) = sum_i A_i(s) (B_i(s) - a_i)^2 +
    C(s), with 2m + 1 heads (A_0..A_{m-1}, B_0..B_{m-1}, C); the greedy action is still B(s)
    and the maximum C(s). With m = 1 it is the paper's network, parameter for parameter.

    With K = `peaks` > 1 (one action component) Q is the upper envelope of K such pieces,
    Q(s, a) = max_k A_k(s) (B_k(s) - a)^2 + C_k(s), with 3K heads (A_0..A_{K-1},
    B_0..B_{K-1}, C_0..C_{K-1}): it can hold several peaks (brake or go), which one quadratic
    cannot. The maximum is max_k C_k(s), the greedy action B_k*(s) with k* = argmax_k C_k(s)
    (the first on a tie). The B biases start spread over the action range, so the pieces
    begin at different commands. With `peak_bands` piece k's B is kept inside the k-th of K
    equal bands of the range (B_k = low + span (k + sigmoid(z_B_k)) / K): the pieces cannot
    drift onto one command, so brake and go stay separate candidates.

    Layer 1 is ``hidden: Linear(obs_dim, 3 * hidden)`` (rows ``[k*H:(k+1)*H]`` belong to head
    k = A, B, C), ReLU, then a block-diagonal layer 2: head k reads only its own H hidden
    units, ``z_k = <h_k, head_weight[k]> + head_bias[k]``. Initialisation matches three
    ``nn.Linear`` stacks (uniform(+-1/sqrt(fan_in))), except the A bias (see ``a_init``).

    Output activations:

    * ``A = -(a_min + (a_max - a_min) * sigmoid(z_A))`` lies in ``[-a_max, -a_min]``: strictly
      negative (the argmax is unique) and bounded below, which guards against the known failure
      of this family where the curvature runs away (|A| -> inf, then inf * 0 = NaN in the
      target). A saturated sigmoid has no gradient pushing further, and at the small end
      ``sigmoid(z) ~ exp(z)`` so |A| can still shrink multiplicatively. A softplus clamped at
      ``a_max`` would do the same but has a kink and a dead gradient above the clamp.
    * ``B = low + (high - low) * sigmoid(z_B)`` lies strictly inside ``(low, high)`` (a scaled
      tanh, written with sigmoid), so the greedy action is always feasible and
      ``max_{a in [low, high]} Q(s, a) = Q(s, B(s)) = C(s)``.
    * ``C = z_C`` is unconstrained.

    Args:
        obs_dim: observation size (7 for the paper's state).
        hidden: hidden width of each of the three MLPs.
        action_low, action_high: action bounds, m/s^2.
        extra_bounds: (low, high) of each further action component (none: the paper's 1-D
            action).
        peaks: K quadratic pieces (1: the paper's network; more: one action component only).
        peak_bands: with K > 1, piece k's B lies in the k-th of K equal bands of the range.
        a_min, a_max: bounds on the curvature magnitude |A|.
        a_init: |A| at initialisation (sets the A bias); ``None`` keeps the nn.Linear init.
        generator: seeds the initialisation; ``None`` uses a fresh ``torch.Generator``
            seeded with 0 (never the global RNG).
    """

    def __init__(
        self,
        obs_dim: int = 7,
        hidden: int = 64,
        *,
        action_low: float = DEFAULT_ACTION_BOUNDS[0],
        action_high: float = DEFAULT_ACTION_BOUNDS[1],
        a_min: float = 1e-3,
        a_max: float = 5.0,
        a_init: float | None = 0.1,
        generator: torch.Generator | None = None,
        extra_bounds: tuple[tuple[float, float], ...] = (),
        peaks: int = 1,
        peak_bands: bool = False,
    ) -> None:
        super().__init__()
        if peaks < 1 or (peaks > 1 and extra_bounds):
            raise ValueError(
                f"peaks must be >= 1, and 1 with several action components; got {peaks} with "
                f"{len(extra_bounds)} further components"
            )
        if peak_bands and peaks == 1:
            raise ValueError("peak_bands splits the command range among pieces: needs peaks > 1")
        bounds = ((float(action_low), float(action_high)), *extra_bounds)
        for lo, hi in bounds:
            if not lo < hi:
                raise ValueError(f"need action low < high, got {lo}, {hi}")
        if not 0.0 < a_min < a_max:
            raise ValueError(f"need 0 < a_min < a_max, got {a_min}, {a_max}")
        self.obs_dim = obs_dim
        self.hidden_dim = hidden
        self.action_low = float(action_low)
        self.action_high = float(action_high)
        self.a_min = float(a_min)
        self.a_max = float(a_max)
        self.extra_bounds = tuple((float(lo), float(hi)) for lo, hi in extra_bounds)
        self.action_dim = m = len(bounds)
        self.peaks = int(peaks)
        self.peak_bands = bool(peak_bands)
        self.n_heads = n = n_heads(m, self.peaks)
        self._low = tuple(lo for lo, _ in bounds)  # the B heads' bounds (no tensors: the
        self._span = tuple(hi - lo for lo, hi in bounds)  # parameters are the paper's keys)
        if self.peak_bands:  # piece k: the k-th of K equal bands of the command range
            self._low, self._span = band_bounds(self.action_low, self.action_span, self.peaks)
        self.hidden = nn.Linear(obs_dim, n * hidden)
        self.head_weight = nn.Parameter(torch.empty(n, hidden))  # [n heads, H]
        self.head_bias = nn.Parameter(torch.empty(n))  # [n heads]
        gen = generator if generator is not None else torch.Generator().manual_seed(0)
        self.reset_parameters(gen, a_init=a_init)

    @torch.no_grad()
    def reset_parameters(self, generator: torch.Generator, *, a_init: float | None = 0.1) -> None:
        """nn.Linear-style uniform init from ``generator``; optionally set the initial |A|."""
        b1 = 1.0 / math.sqrt(self.obs_dim)
        b2 = 1.0 / math.sqrt(self.hidden_dim)
        for p, bound in (
            (self.hidden.weight, b1),
            (self.hidden.bias, b1),
            (self.head_weight, b2),
            (self.head_bias, b2),
        ):
            p.copy_(torch.rand(p.shape, generator=generator) * (2 * bound) - bound)
        if a_init is not None:
            if not self.a_min < a_init < self.a_max:
                raise ValueError(f"a_init must lie in (a_min, a_max), got {a_init}")
            frac = (a_init - self.a_min) / (self.a_max - self.a_min)
            self.head_bias[self._rows()[0]] = math.log(frac / (1.0 - frac))
        if self.peaks > 1:  # B_k starts at the k-th of K evenly spread points of the range
            quantiles = (torch.arange(self.peaks, dtype=torch.float64) + 0.5) / self.peaks
            if self.peak_bands:  # the same points: the middles of the bands
                quantiles = torch.full_like(quantiles, 0.5)
            self.head_bias[self._rows()[1]] = torch.logit(quantiles).to(self.head_bias.dtype)

    def _rows(self) -> tuple[slice, slice, slice]:
        """The rows of the A, B and C heads."""
        if self.peaks > 1:
            return peak_rows(self.peaks)
        rows_a, rows_b, c = head_rows(self.action_dim)
        return rows_a, rows_b, slice(c, c + 1)

    @property
    def action_span(self) -> float:
        return self.action_high - self.action_low

    def heads(self, obs: Tensor) -> Tensor:
        """Pre-activation head outputs ``z = [z_A, z_B, z_C]``: [..., obs_dim] -> [..., n]
        (n = `n_heads`: 2m + 1, or 3K with K peaks)."""
        h = torch.relu(self.hidden(obs))  # [..., n H]
        h = h.unflatten(-1, (self.n_heads, self.hidden_dim))  # [..., n, H]
        return (h * self.head_weight).sum(-1) + self.head_bias  # [..., n]

    def forward(self, obs: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``obs [..., obs_dim] -> (A, B, C)``, [..., m], [..., m], [..., 1] (with K peaks
        [..., K] each); A < 0, B inside the bounds."""
        z = self.heads(obs)
        rows_a, rows_b, rows_c = self._rows()
        za, zb, zc = z[..., rows_a], z[..., rows_b], z[..., rows_c]
        a = -(self.a_min + (self.a_max - self.a_min) * torch.sigmoid(za))  # [..., m]
        low, span = b_bounds(self._low, self._span, zb)
        return a, low + span * torch.sigmoid(zb), zc  # B [..., m], m/s^2 (then the join)

    def q(self, obs: Tensor, action: Tensor) -> Tensor:
        """Q(s, a): obs [..., obs_dim], action [..., m] (m/s^2, ...) -> [..., 1]."""
        return q_of_heads(*self(obs), action, self.peaks)

    def greedy(self, obs: Tensor) -> Tensor:
        """argmax_a Q(s, a): B(s) (with K peaks the B of the largest C): [..., obs_dim] ->
        [..., m], inside the bounds."""
        _, b, c = self(obs)
        if self.peaks == 1:
            return b
        return b.gather(-1, c.argmax(-1, keepdim=True))  # [..., 1]

    def max_value(self, obs: Tensor) -> Tensor:
        """max over the bounded action set of Q(s, a) = C(s) (max_k C_k(s)): [..., 1]."""
        return self.heads(obs)[..., self._rows()[2]].amax(-1, keepdim=True)


def q_of_heads(a: Tensor, b: Tensor, c: Tensor, action: Tensor, peaks: int = 1) -> Tensor:
    """Q(s, a) [..., 1] from the heads (`QuadraticQNet.forward`) and the action [..., m]: the
    separable sum of the components, or with K peaks the largest of the K pieces."""
    if peaks == 1:
        return (a * (b - action).pow(2)).sum(-1, keepdim=True) + c
    return (a * (b - action).pow(2) + c).amax(-1, keepdim=True)


def get_entry(td: TensorDictBase, key: NestedKey) -> Tensor:
    """``td.get`` that raises (tensordict 0.14 ``get`` returns None for a missing key)."""
    value = td.get(key, None)
    if value is None:
        raise KeyError(f"key {key!r} not found in the input tensordict (see loss.set_keys)")
    return value


# ----------------------------------------------------------------------------------------------
# Loss
# ----------------------------------------------------------------------------------------------


class QuadraticQLoss(LossModule):
    """TD(0) loss of the quadratic Q-function with a hard-updated target network (eq. 10).

    ``loss = mean_batch (r + gamma * (1 - terminated) * max_a' Q_target(s', a') - Q(s, a))^2``

    with ``max_a' Q_target(s', a') = C_target(s')`` because B is squashed inside the action
    bounds. Only ``terminated`` masks the bootstrap; a truncated transition still bootstraps.

    The online parameters live in ``value_network_params`` (the same ``nn.Parameter`` objects
    as the network passed in, so ``net.greedy(obs)`` always acts with the current weights), the
    target parameters in ``target_value_network_params`` (detached clones, never trained). Pair
    the loss with :class:`PeriodicHardUpdate` (or torchrl ``HardUpdate``) and call its
    ``step()`` after every optimiser step, or use `quadq_fast.FastQuadQUpdater`, which does both.

    Args:
        value_network: a module whose ``forward(obs)`` returns ``(A, B, C)`` each [..., 1],
            with B inside the action bounds (e.g. :class:`QuadraticQNet`).

    Keyword Args:
        gamma: discount factor (0.95 in the paper). A buffer; ``loss.gamma = x`` updates it.
        reduction: ``"mean"`` (default, the paper), ``"sum"`` or ``"none"``.

    Tensordict keys (change with :meth:`set_keys`), torchrl conventions: ``reward`` and
    ``terminated`` are read under ``"next"``; the next observation is
    ``("next", observation)``.

    * ``observation`` [B, obs_dim], ``action`` [B, m] (m/s^2, ...), ``("next", "reward")`` [B, 1],
      ``("next", "terminated")`` [B, 1] bool, ``("next", "observation")`` [B, obs_dim].
    * Writes ``|TD error|`` [B, 1] (detached) into the input under ``priority`` ("td_error").

    Returns a TensorDict with ``loss_value`` and detached batch means ``td_error`` (|delta|),
    ``pred_value``, ``target_value``, ``A_mean``, ``B_mean``, ``C_mean``.
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (``loss.set_keys(name=key)``).

        Attributes:
            observation: state; ``("next", observation)`` is the next state.
            action: applied acceleration, [..., 1].
            reward: read at ``("next", reward)``.
            terminated: read at ``("next", terminated)``; True stops the bootstrap.
            priority: where |TD error| is written in the input tensordict.
            priority_weight: optional importance weights (prioritized replay).
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        terminated: NestedKey = "terminated"
        priority: NestedKey = "td_error"
        priority_weight: NestedKey = "priority_weight"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    default_value_estimator = None
    _schedulable_buffers = frozenset({"gamma"})
    out_keys = [
        "loss_value",
        "td_error",
        "pred_value",
        "target_value",
        "A_mean",
        "B_mean",
        "C_mean",
    ]

    value_network: nn.Module
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams
    gamma: Tensor

    def __init__(
        self,
        value_network: nn.Module,
        *,
        gamma: float = PAPER_GAMMA,
        reduction: str = "mean",
        use_prioritized_weights: str | bool = "auto",
    ) -> None:
        super().__init__()
        self._in_keys = None
        self.reduction = reduction
        self.use_prioritized_weights = use_prioritized_weights
        self.convert_to_functional(value_network, "value_network", create_target_params=True)
        self.register_coeff_buffer("gamma", float(gamma))

    # --- keys -----------------------------------------------------------------------------

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        # No torchrl value estimator: the TD(0) target is computed in forward().
        self._set_in_keys()

    def _set_in_keys(self) -> None:
        k = self.tensor_keys
        self._in_keys = [
            unravel_key(k.observation),
            unravel_key(k.action),
            unravel_key(("next", k.reward)),
            unravel_key(("next", k.terminated)),
            unravel_key(("next", k.observation)),
        ]

    @property
    def in_keys(self) -> list[NestedKey]:
        if self._in_keys is None:
            self._set_in_keys()
        return self._in_keys

    @in_keys.setter
    def in_keys(self, values: list[NestedKey]) -> None:
        self._in_keys = values

    # --- loss -----------------------------------------------------------------------------

    def td_target(self, tensordict: TensorDictBase) -> Tensor:
        """``r + gamma * (1 - terminated) * C_target(s')`` [B, 1], without gradient."""
        k = self.tensor_keys
        reward = get_entry(tensordict, ("next", k.reward))
        terminated = get_entry(tensordict, ("next", k.terminated))
        next_obs = get_entry(tensordict, ("next", k.observation))
        with torch.no_grad():
            with self.target_value_network_params.to_module(
                self.value_network, preserve_module_state=False
            ):
                next_value = self.value_network(next_obs)[2]  # [B, 1] ([B, K]: K peaks)
            next_value = next_value.amax(-1, keepdim=True)  # max_k C_k; one peak: C
            not_term = (~terminated.bool()).to(next_value.dtype).reshape(next_value.shape)
            return reward.reshape(next_value.shape) + self.gamma * not_term * next_value

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        """Loss on a batch of transitions; see the class docstring for keys and outputs."""
        k = self.tensor_keys
        obs = get_entry(tensordict, k.observation)
        action = get_entry(tensordict, k.action)
        with self.value_network_params.to_module(self.value_network, preserve_module_state=False):
            a, b, c = self.value_network(obs)  # [B, m], [B, m], [B, 1] ([B, K] with K peaks)
        peaks = c.shape[-1]
        action = action.reshape(*b.shape[:-1], b.shape[-1] // peaks).to(b.dtype)
        pred = q_of_heads(a, b, c, action, peaks)  # [B, 1]
        target = self.td_target(tensordict)  # [B, 1]
        delta = pred - target
        weights = self._maybe_get_priority_weight(tensordict)
        loss = self._reduce_loss(delta.pow(2).squeeze(-1), tensordict=tensordict, weights=weights)
        abs_delta = delta.detach().abs()
        tensordict.set(k.priority, abs_delta, inplace=True)
        with torch.no_grad():
            out = TensorDict(
                {
                    "td_error": abs_delta.mean(),
                    "pred_value": pred.mean(),
                    "target_value": target.mean(),
                    "A_mean": a.mean(),
                    "B_mean": b.mean(),
                    "C_mean": c.mean(),
                },
                batch_size=[],
            )
        out.set("loss_value", loss)
        self._clear_weakrefs(tensordict, out, "value_network_params", "target_value_network_params")
        return out


class PeriodicHardUpdate(HardUpdate):
    """torchrl ``HardUpdate`` that copies online -> target after exactly every ``period`` calls.

    torchrl 0.14.1 ``HardUpdate(loss, value_network_update_interval=n)`` copies on the
    (n+1)-th, 2(n+1)-th ... call to ``step()`` (its counter runs 0..n inclusive), so the
    paper's "every p updates" is ``value_network_update_interval = p - 1``.
    """

    def __init__(self, loss_module: LossModule, *, period: int = 500) -> None:
        if period < 1:
            raise ValueError(f"period must be >= 1, got {period}")
        super().__init__(loss_module, value_network_update_interval=period - 1)
        self.period = period


# ----------------------------------------------------------------------------------------------
# Exploration
# ----------------------------------------------------------------------------------------------


def noisy_greedy_action(
    greedy_action: Tensor,
    sigma: float,
    generator: torch.Generator,
    *,
    low: float | tuple[float, ...] = DEFAULT_ACTION_BOUNDS[0],
    high: float | tuple[float, ...] = DEFAULT_ACTION_BOUNDS[1],
) -> Tensor:
    """``clip(greedy + sigma * N(0, 1), low, high)``, noise drawn from ``generator``.

    ``greedy_action`` [..., m] (m/s^2, ...); `low`, `high` numbers, or one per component. The
    noise is drawn on the generator's device and moved to the action's, so a CPU generator
    draws the same noise for a policy on any device.
    """
    noise = torch.randn(
        greedy_action.shape,
        generator=generator,
        device=generator.device,
        dtype=greedy_action.dtype,
    )
    noisy = greedy_action + sigma * noise.to(greedy_action.device)
    if isinstance(low, tuple):  # one bound per component
        as_t = functools.partial(torch.tensor, dtype=noisy.dtype, device=noisy.device)
        return torch.clamp(noisy, as_t(low), as_t(high))
    return noisy.clamp(low, high)


@dataclass
class GaussianExploration:
    """Greedy action plus Gaussian noise whose std decays linearly, clipped to the bounds.

    ``sigma(step) = sigma_start + (sigma_end - sigma_start) * min(step / decay_steps, 1)``,
    m/s^2. Stateless: pass the global step; deterministic given the generator state.
    """

    sigma_start: float = 1.0
    sigma_end: float = 0.1
    decay_steps: int = 1_000_000
    low: float | tuple[float, ...] = DEFAULT_ACTION_BOUNDS[0]
    high: float | tuple[float, ...] = DEFAULT_ACTION_BOUNDS[1]
    """Numbers, or one per action component."""

    def sigma(self, step: int) -> float:
        frac = min(max(step, 0) / max(self.decay_steps, 1), 1.0)
        return self.sigma_start + (self.sigma_end - self.sigma_start) * frac

    def __call__(self, greedy_action: Tensor, step: int, generator: torch.Generator) -> Tensor:
        """[..., m] greedy action -> [..., m] noisy action inside [low, high]."""
        return noisy_greedy_action(
            greedy_action, self.sigma(step), generator, low=self.low, high=self.high
        )


# ----------------------------------------------------------------------------------------------
# Engineered fast path
# ----------------------------------------------------------------------------------------------
