"""The actor's parameter network as plain tensor ops, and the closed-form log-prob."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import torch
from tensordict.nn import AddStateIndependentNormalScale
from torch import nn
from torchrl.modules import MLP

from torchrl_mbmf.modules.actors import TanhLoc
from torchrl_mbmf.modules.mlp import plain_layers, run_plain
from torchrl_mbmf.modules.planners.fast_model import slot_versions, tensor_slots

ParamsFn = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
_LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))


def _flat_layers(net: nn.Module) -> list[nn.Module]:
    """The modules a plain ``Sequential`` (or a non-reshaping torchrl ``MLP``) runs in turn.

    A :class:`~torchrl_mbmf.modules.actors.TanhLoc` unrolls into its network's layers and a
    ``Tanh``.
    """
    if type(net) is TanhLoc:
        return [*_flat_layers(net.net), nn.Tanh()]
    plain = type(net) is nn.Sequential or (type(net) is MLP and not net._reshape_out)
    if not plain:
        return [net]
    return [leaf for m in net for leaf in _flat_layers(m)]


def _chain(layers: list[nn.Module]) -> Callable[[torch.Tensor], torch.Tensor]:
    """``layers`` run in turn as plain ops on the live weights (:func:`run_plain`).

    Values equal the modules' own: ``nn.Linear`` on a 2-d input is ``addmm(b, x, W.t())``, a
    ReLU or Tanh right after it runs in place on that fresh output; other modules are called
    as they are.
    """
    return functools.partial(run_plain, plain_layers(layers))


class TightParams:
    """A tensor-only ``obs [N, d] -> (loc, scale)`` of an actor's parameter network.

    For a plain ``Sequential`` (or torchrl ``MLP``, or
    :class:`~torchrl_mbmf.modules.actors.TanhLoc`) chain: its layers run as plain ops on the
    live weights (:func:`~torchrl_mbmf.modules.mlp.run_plain`), with the same values as the
    network. A closing :class:`~tensordict.nn.AddStateIndependentNormalScale` gives a scale
    that does not depend on the observation: it is computed once and returned as the second
    element (``[action_dim]``). Calling the object rebuilds the function only after a tensor
    of the network changed (in place, replaced or moved): the constant scale is a snapshot,
    checked on every call against the values it was computed from, since an in-place write
    through ``.data`` leaves the version counters alone (a torchrl loss's
    ``load_state_dict`` writes its parameters so).

    Args:
        net: the parameter network.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import make_ppo_actor_critic
        >>> from torchrl_mbmf.modules.planners.actor_params import TightParams
        >>> actor, _ = make_ppo_actor_critic(make_gym_state_env("Pendulum-v1"))
        >>> params, scale = TightParams(actor.module[0].module)()
        >>> loc, same = params(torch.zeros(4, 3))
        >>> loc.shape, same is scale
        (torch.Size([4, 1]), True)
    """

    def __init__(self, net: nn.Module) -> None:
        self.net = net
        self._slots: list[tuple[dict[str, torch.Tensor | None], str]] | None = None
        self._built: tuple[ParamsFn, torch.Tensor | None] | None = None
        self._key: tuple[tuple[int, int, int], ...] | None = None
        # (the scale parameter, a copy of the values the constant scale was computed from)
        self._source: tuple[nn.Module, torch.Tensor] | None = None

    def __getstate__(self) -> dict[str, object]:
        # closures over the network: rebuilt after a copy or pickle
        return {**self.__dict__, "_slots": None, "_built": None, "_key": None, "_source": None}

    def __call__(self) -> tuple[ParamsFn, torch.Tensor | None]:
        """``(params_fn, constant_scale or None)`` for the current weights."""
        key = self._version_key()
        if key != self._key or not self._source_unchanged():
            self._built = self._build()
            self._key = key
        return self._built

    def _source_unchanged(self) -> bool:
        # the version key misses writes through ``.data``; the snapshot's few values are
        # compared instead
        if self._source is None:
            return True
        head, values = self._source
        return torch.equal(head.state_independent_scale.detach(), values)

    def _version_key(self) -> tuple[tuple[int, int, int], ...]:
        # the chain holds the live weights; it is rebuilt when a tensor is replaced or moved,
        # and when one changes in place (the constant scale is a snapshot)
        if self._slots is None:
            self._slots = tensor_slots(self.net)
        return slot_versions(self._slots)

    def _build(self) -> tuple[ParamsFn, torch.Tensor | None]:
        layers = _flat_layers(self.net)
        head = layers[-1]
        if type(head) is AddStateIndependentNormalScale and len(head.scale_shape) == 1:
            body = _chain(layers[:-1])
            source = head.state_independent_scale.detach()
            scale = head(source)[1]
            self._source = (head, source.clone())

            def constant_scale(obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
                return body(obs), scale

            return constant_scale, scale
        self._source = None
        chain = _chain(layers)

        def params(obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            loc, scale = chain(obs)
            return loc, scale

        return params, None


def normal_log_prob(
    action: torch.Tensor,
    loc: torch.Tensor,
    scale: torch.Tensor,
    squash: tuple[torch.Tensor, ...] | None = None,
) -> torch.Tensor:
    """Log-prob ``[...]`` of ``action`` under a Normal, optionally squashed, in closed form.

    Step for step what torchrl's ``IndependentNormal`` (``squash=None``) and ``TanhNormal``
    (``squash=()``: tanh; ``(mid, half)``: tanh then ``mid + half * x``) compute, without
    building the distribution objects (equal to float rounding).

    Args:
        action: the actions ``[..., A]``.
        loc: the Normal's location.
        scale: its scale.
        squash: ``None``, ``()`` or ``(mid, half)``. Defaults to ``None``.

    Examples:
        >>> import torch
        >>> from torchrl.modules import IndependentNormal
        >>> from torchrl_mbmf.modules.planners.actor_params import normal_log_prob
        >>> a, loc, scale = torch.zeros(2, 3), torch.ones(2, 3), torch.ones(2, 3)
        >>> ref = IndependentNormal(loc, scale).log_prob(a)
        >>> torch.allclose(normal_log_prob(a, loc, scale), ref)
        True
    """
    log_prob = 0.0
    y = action
    if squash is not None:
        if squash:  # the inverse of ``mid + half * x`` and its log-Jacobian
            mid, half = squash[0].to(y), squash[1].to(y)
            y = (y - mid) / half
            log_prob = log_prob - half.abs().log().expand_as(y).sum(-1)
        lim = 1.0 - torch.finfo(y.dtype).resolution
        x = y.clamp(-lim, lim).atanh()
        log_det = 2.0 * (math.log(2.0) - x - nn.functional.softplus(-2.0 * x))
        log_prob = log_prob - log_det.sum(-1)
        y = x
    normal = -((y - loc) ** 2) / (2 * scale**2) - scale.log() - _LOG_SQRT_2PI
    return log_prob + normal.sum(-1)


__all__ = ["ParamsFn", "TightParams", "normal_log_prob"]
