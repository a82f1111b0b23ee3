"""Update batches drawn from two replay buffers in a fixed proportion (MBPO's real/model mix)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import NestedKey, TensorDictBase
from torch import Tensor
from torchrl.data import TensorDictReplayBuffer

from torchrl_mbmf.checks import check_number
from torchrl_mbmf.data.replay import ReplaySampler

__all__ = ["MixedReplaySampler"]


class MixedReplaySampler:
    """Batches of ``batch_size`` rows: ``round(real_ratio * batch_size)`` real, the rest imagined.

    The real rows come first, then the model rows; each part is drawn uniformly with
    replacement from its buffer (the rows its own ``sample()`` would draw,
    :class:`~torchrl_mbmf.data.ReplaySampler`), on the global torch generator. Called, it
    returns the entries ``keys`` as plain tensors (the fused SAC update's inputs);
    :meth:`sample` returns a TensorDict of the entries ``keys`` (the stock ``SACLoss``'s).

    Args:
        real: the real replay buffer (a one-dimensional ``LazyTensorStorage``).
        model: the model replay buffer (the same layout and entries).
        keys: the entries returned, in order.
        batch_size: rows per batch.
        real_ratio: the share of real rows, in ``[0, 1]``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
        >>> real = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=1)
        >>> model = TensorDictReplayBuffer(storage=LazyTensorStorage(10), batch_size=1)
        >>> _ = real.extend(TensorDict({"x": torch.zeros(10)}, [10]))
        >>> _ = model.extend(TensorDict({"x": torch.ones(10)}, [10]))
        >>> (x,) = MixedReplaySampler(real, model, ["x"], batch_size=8, real_ratio=0.25)()
        >>> x.tolist()
        [0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]
    """

    def __init__(
        self,
        real: TensorDictReplayBuffer,
        model: TensorDictReplayBuffer,
        keys: Sequence[NestedKey],
        batch_size: int,
        real_ratio: float,
    ) -> None:
        batch_size = check_number(batch_size, "batch_size", minimum=1, integer=True)
        ratio = check_number(real_ratio, "real_ratio", minimum=0)
        if ratio > 1:
            raise ValueError(f"real_ratio must be in [0, 1], got {real_ratio}")
        self.real, self.model = real, model
        self.keys = list(keys)
        self.batch_size = int(batch_size)
        self.num_real = round(ratio * self.batch_size)
        self.num_model = self.batch_size - self.num_real
        self._samplers = [
            ReplaySampler(buffer, self.keys, batch_size=n)
            for buffer, n in ((real, self.num_real), (model, self.num_model))
            if n > 0
        ]

    def __call__(self) -> tuple[Tensor, ...]:
        """One batch as the tensors of :attr:`keys` (real rows first).

        Raises:
            RuntimeError: a buffer that must give rows is empty.
        """
        self._check_filled()
        parts = [sampler() for sampler in self._samplers]
        if len(parts) == 1:
            return parts[0]
        return tuple(torch.cat(pair) for pair in zip(*parts, strict=True))

    def sample(self) -> TensorDictBase:
        """One batch as a TensorDict of :attr:`keys` (real rows first)."""
        self._check_filled()
        parts = [
            buffer.sample(n).select(*self.keys)
            for buffer, n in ((self.real, self.num_real), (self.model, self.num_model))
            if n > 0
        ]
        return parts[0] if len(parts) == 1 else torch.cat(parts)

    def _check_filled(self) -> None:
        for name, buffer, n in (
            ("real", self.real, self.num_real),
            ("model", self.model, self.num_model),
        ):
            if n > 0 and len(buffer) == 0:
                raise RuntimeError(
                    f"MixedReplaySampler: the {name} replay is empty but {n} of every "
                    f"{self.batch_size} rows come from it"
                )
