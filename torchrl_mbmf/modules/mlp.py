"""MLPs: the hidden-layer check, the builder, and the one plain-op runner of every fast path.

The fast paths (the planners' actor and model loops, the fused PPO and SAC updates, the
ensemble's batched step, the world model's training forward) run MLPs as plain tensor ops
through the helpers here: :func:`affine` (one ``addmm``, or one ``baddbmm`` for stacked
members), :func:`activate` and :func:`run_plain` over a :data:`PlainLayer` list built by
:func:`plain_layers`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import nn

#: one step of a plain MLP: ``(weight_t, bias)`` for an affine layer (``weight_t`` is
#: ``[in, out]``, or ``[K, in, out]`` for stacked members), ``"relu"``, ``"tanh"``, or any
#: other callable layer
PlainLayer = tuple[torch.Tensor, torch.Tensor] | str | Callable[[torch.Tensor], torch.Tensor]


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


def affine(
    x: torch.Tensor,
    weight_t: torch.Tensor,
    bias: torch.Tensor | None,
    *,
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """``bias + x @ weight_t`` in one op: ``addmm`` (2-d) or ``baddbmm`` (stacked members).

    For a 2-d ``x`` and ``weight_t = weight.t()`` this is exactly what ``nn.Linear`` runs
    (values and autograd); stacked ``x [K, N, in]``, ``weight_t [K, in, out]`` and
    ``bias [K, 1, out]`` run every member at once. Any other ``x`` (or no bias) goes through
    :func:`torch.nn.functional.linear` (``out`` must then be ``None``).

    Args:
        x: the input.
        weight_t: the transposed weight.
        bias: the bias, or ``None``.

    Keyword Args:
        out: where to write (2-d and stacked only). Defaults to a new tensor.

    Examples:
        >>> import torch
        >>> from torch import nn
        >>> from torchrl_mbmf.modules.mlp import affine
        >>> layer, x = nn.Linear(3, 2), torch.randn(4, 3)
        >>> torch.equal(affine(x, layer.weight.t(), layer.bias), layer(x))
        True
    """
    if weight_t.dim() == 3:
        return torch.baddbmm(bias, x, weight_t, out=out)
    if bias is None:
        if out is not None:
            raise ValueError("affine writes into out only with a bias")
        return nn.functional.linear(x, weight_t.t())
    if x.dim() == 2:
        return torch.addmm(bias, x, weight_t, out=out)
    if out is not None:
        raise ValueError(f"affine writes into out only for 2-d inputs, got {x.dim()}-d")
    return nn.functional.linear(x, weight_t.t(), bias)


def addmm_relu(bias: torch.Tensor, x: torch.Tensor, weight_t: torch.Tensor) -> torch.Tensor:
    """``relu(bias + x @ weight_t)``: ``addmm``, then a ReLU in place on its fresh output.

    The same values as ``relu(linear(x, weight, bias))`` for a 2-d ``x``, in two tensor calls
    (``torch._addmm_activation`` does the same in one call but costs more on CPU).

    Args:
        bias: ``[out]``.
        x: ``[N, in]``.
        weight_t: ``[in, out]`` (the transposed weight of a linear layer).

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.mlp import addmm_relu
        >>> addmm_relu(torch.tensor([1.0, -5.0]), torch.ones(1, 2), torch.eye(2))
        tensor([[2., 0.]])
    """
    return torch.addmm(bias, x, weight_t).relu_()


def activate(x: torch.Tensor, layer: PlainLayer, *, inplace: bool = False) -> torch.Tensor:
    """Applies a parameter-free :data:`PlainLayer` (``"relu"``, ``"tanh"`` or a callable).

    Args:
        x: the input.
        layer: the activation.

    Keyword Args:
        inplace: run ``"relu"``/``"tanh"`` in place (only on a fresh tensor nothing else
            reads). Defaults to ``False``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.modules.mlp import activate
        >>> activate(torch.tensor([-1.0, 2.0]), "relu")
        tensor([0., 2.])
    """
    if layer == "relu":
        return x.relu_() if inplace else torch.relu(x)
    if layer == "tanh":
        return x.tanh_() if inplace else torch.tanh(x)
    return layer(x)


def plain_layers(modules: Sequence[nn.Module]) -> list[PlainLayer]:
    """``modules`` as :data:`PlainLayer` steps: ``Linear`` -> ``(weight.t(), bias)``, etc.

    The affine steps hold views of the live parameters (detached: for inference loops that
    read the current weights without rebuilding); ``ReLU`` and ``Tanh`` become ``"relu"``
    and ``"tanh"``; any other module (and a ``Linear`` without bias) is kept as a callable.

    Args:
        modules: the layers in the order they run.

    Examples:
        >>> from torch import nn
        >>> from torchrl_mbmf.modules.mlp import plain_layers
        >>> [s if isinstance(s, str) else type(s).__name__
        ...  for s in plain_layers([nn.Linear(2, 3), nn.ReLU(), nn.Linear(3, 1), nn.Tanh()])]
        ['tuple', 'relu', 'tuple', 'tanh']
    """
    steps: list[PlainLayer] = []
    for m in modules:
        if type(m) is nn.Linear and m.bias is not None:
            steps.append((m.weight.detach().t(), m.bias.detach()))
        elif type(m) is nn.ReLU:
            steps.append("relu")
        elif type(m) is nn.Tanh:
            steps.append("tanh")
        else:
            steps.append(m)
    return steps


def run_plain(
    layers: Sequence[PlainLayer], x: torch.Tensor, *, record: list[torch.Tensor] | None = None
) -> torch.Tensor:
    """Runs :data:`PlainLayer` steps on ``x``: one op per affine layer and per activation.

    Without ``record``, a ReLU or Tanh right after an affine layer runs in place on that
    layer's fresh output (same values and gradients: neither op needs its own input for the
    backward pass). With ``record``, every step's output is appended to it, activations out
    of place (what a hand-written backward pass reads).

    Args:
        layers: the steps.
        x: the input.

    Keyword Args:
        record: a list to append every step's output to, or ``None``. Defaults to ``None``.

    Examples:
        >>> import torch
        >>> from torch import nn
        >>> from torchrl_mbmf.modules.mlp import plain_layers, run_plain
        >>> net = nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Linear(8, 2))
        >>> x = torch.randn(5, 3)
        >>> torch.equal(run_plain(plain_layers(list(net)), x), net(x))
        True
    """
    fresh = False
    inplace = record is None
    for layer in layers:
        if type(layer) is tuple:
            weight_t, bias = layer
            if x.dim() == 2 and weight_t.dim() == 2 and bias is not None:
                x = torch.addmm(bias, x, weight_t)  # affine's 2-d case, inlined (hot loops)
            else:
                x = affine(x, weight_t, bias)
            fresh = True
            if record is not None:
                record.append(x)
            continue
        if layer == "relu":
            x = x.relu_() if fresh and inplace else torch.relu(x)
        elif layer == "tanh":
            x = x.tanh_() if fresh and inplace else torch.tanh(x)
        else:
            x = layer(x)
        fresh = False
        if record is not None:
            record.append(x)
    return x


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
    if any(type(m) is nn.Linear and m.bias is None for m in layers):
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
    steps: list[PlainLayer] = [
        (layer.weight.t(), layer.bias) if type(layer) is nn.Linear else "relu" for layer in layers
    ]
    return run_plain(steps, x)


__all__ = [
    "PlainLayer",
    "activate",
    "addmm_relu",
    "affine",
    "build_mlp",
    "check_hidden_sizes",
    "mlp_forward",
    "plain_layers",
    "run_plain",
]
