"""Draws and closed-form log-probs of an actor's Normal or TanhNormal, as tensor ops."""

from __future__ import annotations

import torch
from torch import distributions as D
from torchrl.modules import IndependentNormal, TanhNormal

from torchrl_mbmf.modules.planners.actor_params import normal_log_prob


class NormalDraws:
    """Tensor-level draws of a torchrl ``TanhNormal``, ``IndependentNormal`` or ``Normal``.

    Samples by reparameterisation with the same random numbers, and so the same values, as
    the distribution's ``sample``; the log-prob in closed form where
    :attr:`closed_form_log_prob` (see
    :func:`~torchrl_mbmf.modules.planners.actor_params.normal_log_prob`).

    Args:
        distribution_class: the actor's distribution class.
        distribution_kwargs: its keyword arguments (``low``, ``high``, ``tanh_loc``,
            ``upscale`` for a ``TanhNormal``).

    Examples:
        >>> import torch
        >>> from torchrl.modules import TanhNormal
        >>> from torchrl_mbmf.modules.planners.normal_draws import NormalDraws
        >>> draws = NormalDraws(TanhNormal, {"low": -2.0, "high": 2.0})
        >>> loc, scale = torch.zeros(4, 1), torch.ones(4, 1)
        >>> _ = torch.manual_seed(0)
        >>> a = draws.sample(loc, scale)
        >>> _ = torch.manual_seed(0)
        >>> b = TanhNormal(loc, scale, low=-2.0, high=2.0).sample()
        >>> torch.allclose(a, b), draws.action_range()
        (True, None)
    """

    def __init__(
        self, distribution_class: type[D.Distribution], distribution_kwargs: dict[str, object]
    ) -> None:
        self.distribution_class = distribution_class
        #: whether :meth:`sample` draws tensor-level (TanhNormal, IndependentNormal, Normal)
        self.fast = distribution_class in (TanhNormal, IndependentNormal, D.Normal)
        self._tanh = distribution_class is TanhNormal
        if self._tanh:
            low = torch.as_tensor(distribution_kwargs.get("low", -1.0))
            high = torch.as_tensor(distribution_kwargs.get("high", 1.0))
            self._tanh_loc = bool(distribution_kwargs.get("tanh_loc", False))
            self._upscale = distribution_kwargs.get("upscale", 5.0)
            self._mid, self._half = (high + low) / 2, (high - low) / 2
            self._affine = bool((high != 1.0).any() or (low != -1.0).any())
        # closed-form log-probs for exactly "Normal, then tanh (and the affine map to [low,
        # high])" or an independent Normal, as torchrl builds them
        kwargs = set(distribution_kwargs)
        if self._tanh:
            self.closed_form_log_prob = kwargs <= {"low", "high", "tanh_loc", "upscale"}
            self.closed_form_log_prob &= not self._tanh_loc
        else:
            self.closed_form_log_prob = distribution_class is IndependentNormal and not kwargs

    def sample(self, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """One action per row of ``loc``, as the distribution's ``sample`` draws it.

        Args:
            loc: the distribution's location ``[..., action_dim]``.
            scale: its scale, broadcastable to ``loc``.
        """
        if self._tanh:
            if self._tanh_loc:
                loc = (loc / self._upscale).tanh() * self._upscale
            x = (loc + scale * torch.randn_like(loc)).tanh()
            eps = torch.finfo(x.dtype).resolution
            x = x.clamp(-1 + eps, 1 - eps)
            if self._affine:
                x = self._mid.to(x) + self._half.to(x) * x
            return x
        return loc + scale * torch.randn_like(loc)

    def sample_into(
        self,
        loc: torch.Tensor,
        scale: torch.Tensor,
        out: torch.Tensor | None = None,
        noise: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """:meth:`sample` in place: into ``out`` and a reused ``noise`` buffer (same numbers).

        Args:
            loc: the distribution's location ``[..., action_dim]`` (not modified).
            scale: its scale, any tensor broadcastable to ``loc``.
            out: where to write the actions (any strides). Defaults to a new tensor.
            noise: a buffer shaped like ``loc`` for the draw (the same numbers as a fresh
                one; used for a contiguous ``loc``). Defaults to a new tensor.
        """
        if noise is not None and loc.is_contiguous() and noise.shape == loc.shape:
            x = noise.normal_()  # what ``randn_like`` runs on its fresh tensor
        else:
            x = torch.randn_like(loc)  # (``torch.normal``: the same draw, slower: checks std)
        if not self._tanh:
            if out is None:
                return x.mul_(scale).add_(loc)
            return torch.mul(x, scale, out=out).add_(loc)  # elementwise: the same values
        x.mul_(scale).add_(loc)
        x = x.tanh_() if out is None else torch.tanh(x, out=out)
        eps = torch.finfo(x.dtype).resolution
        x.clamp_(-1 + eps, 1 - eps)
        if self._affine:
            x.mul_(self._half.to(x)).add_(self._mid.to(x))
        return x

    def action_range(self) -> tuple[float, float] | None:
        """Bounds every action drawn lies in, or ``None`` (unbounded)."""
        if self._tanh and not self._affine:
            return -1.0, 1.0
        return None

    def log_prob(
        self, action: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor
    ) -> torch.Tensor:
        """Closed-form log-prob ``[...]`` of ``action`` (only where :attr:`closed_form_log_prob`).

        Args:
            action: the actions ``[..., action_dim]``.
            loc: the distribution's location.
            scale: its scale.
        """
        squash = None
        if self._tanh:
            squash = (self._mid, self._half) if self._affine else ()
        return normal_log_prob(action, loc, scale, squash)


__all__ = ["NormalDraws"]
