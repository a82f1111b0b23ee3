"""The hidden-layer check and the MLP builder of the world model (one model or stacked members)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

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


__all__ = ["build_mlp", "check_hidden_sizes"]
