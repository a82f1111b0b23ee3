"""The world model's MLP: the hidden-layer check, the builder and the in-place-ReLU forward."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import nn


def check_hidden_sizes(hidden_sizes: Sequence[int], name: str = "hidden_sizes") -> tuple[int, ...]:
    """Checks hidden layer widths: a sequence (possibly empty) of integers >= 1.

    A width of 0 builds a layer whose output is always 0; a float or a bool is a typo.

    Args:
        hidden_sizes: the widths.
        name: the argument's name in the error message. Defaults to ``"hidden_sizes"``.

    Returns:
        The widths as a tuple of ints.

    Raises:
        ValueError: naming the argument and the value.

    Examples:
        >>> from torchrl_mbmf.modules.mlp import check_hidden_sizes
        >>> check_hidden_sizes([64, 64])
        (64, 64)
        >>> try:
        ...     check_hidden_sizes((0,))
        ... except ValueError as err:
        ...     print(err)
        hidden_sizes must be a sequence of integers >= 1, got (0,)
    """
    ok = isinstance(hidden_sizes, Sequence) and not isinstance(hidden_sizes, str)
    if ok:
        ok = all(isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in hidden_sizes)
    if not ok:
        raise ValueError(f"{name} must be a sequence of integers >= 1, got {hidden_sizes!r}")
    return tuple(int(h) for h in hidden_sizes)


def build_mlp(
    in_features: int,
    hidden_sizes: Sequence[int],
    out_features: int,
    activation: type[nn.Module],
    linear: Callable[[int, int], nn.Module] = nn.Linear,
) -> nn.Sequential:
    """``linear -> activation`` per hidden width, then a last ``linear``: the world model's net.

    Args:
        in_features: input size.
        hidden_sizes: hidden widths (checked by :func:`check_hidden_sizes` by the caller).
        out_features: output size.
        activation: hidden activation class.
        linear: builds a linear layer from ``(in, out)``: :class:`torch.nn.Linear` for one
            model, ``EnsembleLinear`` with a member count for stacked members. Defaults to
            :class:`torch.nn.Linear`.

    Examples:
        >>> from torch import nn
        >>> from torchrl_mbmf.modules.mlp import build_mlp
        >>> build_mlp(4, (8,), 2, nn.ReLU)
        Sequential(
          (0): Linear(in_features=4, out_features=8, bias=True)
          (1): ReLU()
          (2): Linear(in_features=8, out_features=2, bias=True)
        )
    """
    layers: list[nn.Module] = []
    width = in_features
    for h in hidden_sizes:
        layers += [linear(width, h), activation()]
        width = h
    layers.append(linear(width, out_features))
    return nn.Sequential(*layers)


def _plain_mlp(net: nn.Module) -> list[nn.Module] | None:
    """The layers of ``net`` if it is a plain MLP that an in-place ReLU may run on, else None.

    That is a hook-free ``Sequential`` of ``Linear``/``ReLU`` layers in which every ReLU
    follows a ``Linear``, so an in-place ReLU only ever overwrites a fresh linear output
    (never the caller's input nor a tensor saved for the backward pass).
    """
    if type(net) is not nn.Sequential or len(net) == 0:
        return None
    layers = list(net)
    if type(layers[0]) is not nn.Linear:
        return None
    for i, module in enumerate((net, *layers)):
        if type(module) not in (nn.Sequential, nn.Linear, nn.ReLU):
            return None
        if type(module) is nn.ReLU and type(layers[i - 2]) is not nn.Linear:
            return None  # an in-place ReLU must follow a Linear (whose output nothing saves)
        if module._forward_hooks or module._forward_pre_hooks or module._backward_hooks:
            return None
    return layers


def mlp_forward(net: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """``net(x)``, with in-place ReLUs for a plain MLP (same values and gradients, bit for bit).

    For a hook-free :class:`~torch.nn.Sequential` of ``Linear`` and ``ReLU`` layers (the
    thesis network) the hidden ReLUs run in place on the fresh linear outputs, which saves an
    allocation and a pass per layer; any other network is called as ``net(x)``. The training
    loss of the one network (``DynamicsLoss.scaled_loss``) runs through it.

    Args:
        net: the network.
        x: its input.

    Examples:
        >>> import torch
        >>> from torch import nn
        >>> from torchrl_mbmf.modules.mlp import build_mlp, mlp_forward
        >>> net, x = build_mlp(4, (8,), 2, nn.ReLU), torch.randn(5, 4)
        >>> torch.equal(mlp_forward(net, x), net(x))
        True
    """
    layers = _plain_mlp(net)
    if layers is None or torch.torch.nn.modules.module._has_any_global_hook():
        return net(x)
    for layer in layers:
        if type(layer) is nn.Linear:
            x = nn.functional.linear(x, layer.weight, layer.bias)
        else:
            x = torch.relu_(x)
    return x


__all__ = ["build_mlp", "check_hidden_sizes", "mlp_forward"]
