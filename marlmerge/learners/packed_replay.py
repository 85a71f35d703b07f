"""The packed transition replay of the quadratic-Q fast path (`quadq_fast`): one float row per
transition, so one ``index_select`` gathers many minibatches, and the rows' view as the
tensordict that :class:`~marlmerge.learners.quadq.QuadraticQLoss` reads."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from marlmerge.learners.quadq import (
    QuadraticQLoss,
    get_entry,
)


class TransitionReplay:
    """Uniform ring-buffer replay of packed transitions (one float tensor, one row each).

    Row layout (``obs_dim = d``): ``[obs (d) | action | reward | terminated | next_obs (d)]``,
    so one ``index_select`` gathers a whole batch of minibatches.

    Args:
        capacity: number of transitions kept (oldest overwritten first).
        obs_dim: observation size.
        action_dim: action components (the action takes that many columns).
    """

    def __init__(
        self,
        capacity: int,
        obs_dim: int = 7,
        *,
        device: torch.device | str | None = None,
        dtype: torch.dtype = torch.float32,
        action_dim: int = 1,
    ) -> None:
        self.capacity = int(capacity)
        self.obs_dim = int(obs_dim)
        self.action_dim = int(action_dim)
        self.row_dim = 2 * self.obs_dim + self.action_dim + 2
        self.storage = torch.zeros(self.capacity, self.row_dim, device=device, dtype=dtype)
        self._cursor = 0
        self._size = 0

    def __len__(self) -> int:
        return self._size

    def pack(
        self, obs: Tensor, action: Tensor, reward: Tensor, terminated: Tensor, next_obs: Tensor
    ) -> Tensor:
        """[N, d], [N, 1], [N, 1], [N, 1] (bool), [N, d] -> packed rows [N, 2d + 3]."""
        n = obs.shape[0]
        dt = self.storage.dtype
        return torch.cat(
            [
                obs.reshape(n, self.obs_dim).to(dt),
                action.reshape(n, self.action_dim).to(dt),
                reward.reshape(n, 1).to(dt),
                terminated.reshape(n, 1).to(dt),
                next_obs.reshape(n, self.obs_dim).to(dt),
            ],
            dim=-1,
        )

    def extend(
        self, obs: Tensor, action: Tensor, reward: Tensor, terminated: Tensor, next_obs: Tensor
    ) -> None:
        """Append N transitions (leading dim N; see :meth:`pack` for shapes)."""
        self.extend_packed(self.pack(obs, action, reward, terminated, next_obs))

    def extend_tensordict(
        self, td: TensorDictBase, keys: QuadraticQLoss._AcceptedKeys | None = None
    ) -> None:
        """Append a flat [N] tensordict laid out as :class:`QuadraticQLoss` reads it."""
        k = keys if keys is not None else QuadraticQLoss._AcceptedKeys()
        self.extend(
            get_entry(td, k.observation),
            get_entry(td, k.action),
            get_entry(td, ("next", k.reward)),
            get_entry(td, ("next", k.terminated)),
            get_entry(td, ("next", k.observation)),
        )

    def extend_packed(self, rows: Tensor) -> None:
        """Append packed rows [N, 2d + 3]; keeps the newest ``capacity`` if N is larger."""
        rows = rows[-self.capacity :].to(self.storage.dtype)
        n = rows.shape[0]
        first = min(n, self.capacity - self._cursor)
        self.storage[self._cursor : self._cursor + first] = rows[:first]
        if n > first:
            self.storage[: n - first] = rows[first:]
        self._cursor = (self._cursor + n) % self.capacity
        self._size = min(self._size + n, self.capacity)

    def sample_indices(self, shape: tuple[int, ...], generator: torch.Generator) -> Tensor:
        """Uniform indices with replacement, e.g. shape ``(k, 32)`` for k minibatches."""
        if self._size == 0:
            raise RuntimeError("cannot sample from an empty TransitionReplay")
        return torch.randint(0, self._size, shape, generator=generator, device=self.storage.device)

    def sample(self, shape: tuple[int, ...], generator: torch.Generator) -> Tensor:
        """Packed rows ``[*shape, 2d + 3]``."""
        idx = self.sample_indices(shape, generator)
        return self.storage.index_select(0, idx.reshape(-1)).reshape(*shape, self.row_dim)

    def to_tensordict(self, rows: Tensor, keys: QuadraticQLoss._AcceptedKeys | None = None):
        """Packed rows [..., 2d + 3] -> TensorDict with the :class:`QuadraticQLoss` layout."""
        return unpack_rows(rows, self.obs_dim, keys, self.action_dim)


def unpack_rows(
    rows: Tensor,
    obs_dim: int,
    keys: QuadraticQLoss._AcceptedKeys | None = None,
    action_dim: int = 1,
) -> TensorDict:
    """Packed transitions ``[obs | action | reward | terminated | next_obs]`` [..., 2d + m + 2]
    (m = `action_dim` action components) -> TensorDict with the :class:`QuadraticQLoss` layout
    (torchrl conventions)."""
    k = keys if keys is not None else QuadraticQLoss._AcceptedKeys()
    d, m = obs_dim, action_dim
    return TensorDict(
        {
            k.observation: rows[..., :d],
            k.action: rows[..., d : d + m],
            ("next", k.reward): rows[..., d + m : d + m + 1],
            ("next", k.terminated): rows[..., d + m + 1 : d + m + 2] > 0.5,
            ("next", k.observation): rows[..., d + m + 2 :],
        },
        batch_size=rows.shape[:-1],
    )
