"""Replay sampling as plain tensors: the rows a ``TensorDictReplayBuffer`` would draw."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey
from torch import Tensor
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer

__all__ = ["ReplaySampler"]


class ReplaySampler:
    """Draws replay batches as plain tensors, the rows the buffer's own ``sample()`` would draw.

    ``TensorDictReplayBuffer.sample()`` on a ``LazyTensorStorage`` with the stock
    ``RandomSampler`` draws ``torch.randint(0, len(storage), (batch_size,))`` and gathers the
    rows through tensordict indexing; this draws the same indices from the same (global) random
    stream and gathers only the requested entries with :meth:`torch.Tensor.index_select` on
    views of the storage's preallocated tensors, so a run samples the same rows either way
    (tested). The buffer keeps owning the data: writes, ``len``, checkpoints
    (``buffer.storage[:filled]``, ``buffer.writer.state_dict()``) are unchanged. Rows come
    back as new tensors (the buffer may overwrite its rows later).

    Args:
        buffer: a ``TensorDictReplayBuffer`` over a ``LazyTensorStorage`` (one-dimensional)
            with a ``RandomSampler`` (the default).
        keys: the entries to return, in order (e.g.
            :attr:`~torchrl_mbmf.objectives.fused_sac.FusedSACUpdate.batch_keys`).

    Keyword Args:
        batch_size: rows per batch. Defaults to the buffer's batch size.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> from torchrl_mbmf.data import ReplaySampler
        >>> buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=4)
        >>> data = TensorDict({"x": torch.arange(10.0), "next": {"y": torch.ones(10, 2)}}, [10])
        >>> _ = buffer.extend(data)
        >>> sampler = ReplaySampler(buffer, ["x", ("next", "y")])
        >>> x, y = sampler()
        >>> x.shape, y.shape
        (torch.Size([4]), torch.Size([4, 2]))
    """

    def __init__(
        self,
        buffer: TensorDictReplayBuffer,
        keys: Sequence[NestedKey],
        *,
        batch_size: int | None = None,
    ) -> None:
        if not isinstance(buffer.storage, LazyTensorStorage) or buffer.storage.ndim != 1:
            raise ValueError(
                f"ReplaySampler expects a one-dimensional LazyTensorStorage, got {buffer.storage}"
            )
        if type(buffer.sampler) is not RandomSampler:
            raise ValueError(
                f"ReplaySampler draws what RandomSampler draws, got {type(buffer.sampler).__name__}"
            )
        batch_size = buffer.batch_size if batch_size is None else batch_size
        if batch_size is None or int(batch_size) < 1:
            raise ValueError(f"ReplaySampler needs a positive batch_size, got {batch_size}")
        if not keys:
            raise ValueError("ReplaySampler needs at least one key")
        self.buffer = buffer
        self.keys = list(keys)
        self.batch_size = int(batch_size)
        self._leaves: list[Tensor] | None = None
        self._seen = 0

    def refresh(self) -> None:
        """Looks the storage tensors up again (done automatically when the buffer shrinks)."""
        storage = self.buffer.storage
        if len(storage) == 0:
            raise RuntimeError("ReplaySampler: the replay buffer is empty")
        first = storage[:1]
        leaves = []
        for key in self.keys:
            row = first.get(key)
            if not row.is_contiguous():
                raise ValueError(f"ReplaySampler: storage entry {key!r} is not contiguous")
            shape = (storage.max_size, *row.shape[1:])
            leaves.append(row.as_strided(shape, row.stride(), row.storage_offset()))
        self._leaves = leaves

    def __call__(self) -> tuple[Tensor, ...]:
        """One batch: a tensor ``[batch_size, ...]`` per key."""
        filled = len(self.buffer.storage)
        if self._leaves is None or filled < self._seen:
            self.refresh()
        self._seen = filled
        index = torch.randint(0, filled, (self.batch_size,))
        return tuple(leaf.index_select(0, index) for leaf in self._leaves)
