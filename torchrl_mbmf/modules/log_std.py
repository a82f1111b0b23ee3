"""SAC actor heads: how the network's second half becomes the TanhNormal's scale.

Two parameterisations are offered (``sac.scale`` in the config):

- ``"biased_softplus"``: torchrl's default :class:`~tensordict.nn.NormalParamExtractor`,
  ``scale = softplus(x + b)`` with ``b`` such that ``x = 0`` gives 1, floored at 1e-4; the
  builders' default, and the recipes' until 2026-12-06.
- ``"clamped_log_std"``: the second half is a log-std, clamped to ``[-20, 2]`` and exponentiated,
  as in SAC's reference code and Stable-Baselines3 (``LOG_STD_MIN``/``LOG_STD_MAX``): the scale
  is bounded above by ``e^2`` (about 7.4) where the softplus is not; the recipes' default since
  2026-12-06 (``configs/algo/sac.yaml``).
"""

from __future__ import annotations

import torch
from tensordict.nn import NormalParamExtractor

__all__ = ["LOG_STD_BOUNDS", "SAC_SCALES", "ClampedLogStdExtractor", "make_sac_head"]

#: The SAC actor's scale parameterisations (see the module docstring).
SAC_SCALES: tuple[str, ...] = ("biased_softplus", "clamped_log_std")
#: SAC's reference code's and Stable-Baselines3's log-std bounds.
LOG_STD_BOUNDS: tuple[float, float] = (-20.0, 2.0)


class ClampedLogStdExtractor(NormalParamExtractor):
    """Splits its input into ``loc`` and ``scale = exp(clamp(log_std, low, high))``.

    A :class:`~tensordict.nn.NormalParamExtractor` whose scale mapping is the clamped
    exponential of SAC's reference code and Stable-Baselines3 (with no further floor).

    Args:
        low: the smallest log-std. Defaults to -20.
        high: the largest log-std. Defaults to 2.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.log_std import ClampedLogStdExtractor
        >>> loc, scale = ClampedLogStdExtractor()(torch.tensor([0.5, -30.0, 0.0, 5.0]))
        >>> loc.tolist(), [round(s, 4) for s in scale.tolist()]
        ([0.5, -30.0], [1.0, 7.3891])
    """

    def __init__(self, low: float = LOG_STD_BOUNDS[0], high: float = LOG_STD_BOUNDS[1]) -> None:
        if not low < high:
            raise ValueError(f"the log-std bounds must satisfy low < high, got ({low}, {high})")
        super().__init__(scale_mapping="exp", scale_lb=0.0)
        self.low, self.high = float(low), float(high)

    def forward(self, *tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``(loc, scale, *others)`` of the first tensor's halves (the others passed on)."""
        tensor, *others = tensors
        loc, log_std = tensor.chunk(2, -1)
        return (loc, log_std.clamp(self.low, self.high).exp(), *others)

    def extra_repr(self) -> str:
        """The bounds, in the module's repr."""
        return f"low={self.low}, high={self.high}"


def make_sac_head(scale: str = "biased_softplus") -> NormalParamExtractor:
    """The SAC actor's head for a scale parameterisation of :data:`SAC_SCALES`.

    Args:
        scale: ``"biased_softplus"`` (torchrl's default) or ``"clamped_log_std"`` (SAC's
            reference code, Stable-Baselines3). Defaults to ``"biased_softplus"``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.log_std import make_sac_head
        >>> [round(float(make_sac_head(s)(torch.zeros(2))[1]), 4) for s in ("biased_softplus",
        ...     "clamped_log_std")]
        [1.0, 1.0]
    """
    if scale == "biased_softplus":
        return NormalParamExtractor(scale_mapping="biased_softplus_1.0", scale_lb=1e-4)
    if scale == "clamped_log_std":
        return ClampedLogStdExtractor()
    raise ValueError(f"scale={scale!r} is not a SAC actor scale; expected one of {SAC_SCALES}")
