"""Eq. 17's loss and gradients for a plain ReLU MLP, by hand, in reused buffers.

The one-step fit (``fit_dynamics`` with ``multi_step=1``) spends almost all its time in
minibatch steps of a ``Linear -> ReLU -> ... -> Linear`` network. :class:`FusedMSEGradient`
runs the forward and backward pass of such a step as the same ATen kernels autograd runs
(``addmm``, in-place ReLU, ``mse_loss_backward``, ``mm``, ``sum``, ``threshold_backward``), on
the same operands in the same layouts, but writes every activation and gradient into buffers
kept across steps and skips the autograd graph: the loss and every parameter's gradient are
bit for bit those of ``mse_loss(net(x), y).backward()``. Design:
``docs/design/world_model_fit.md``.
"""

from __future__ import annotations

import torch
from torch import nn

from torchrl_mbmf.modules.mlp import affine

__all__ = ["FusedMSEGradient"]


def _relu_mlp_linears(net: nn.Module) -> list[nn.Linear] | None:
    """The ``Linear`` layers of a hook-free ``Linear, ReLU, ..., Linear`` ``Sequential``.

    ``None`` for any other network (another activation, a layer without bias, hooks).
    """
    if type(net) is not nn.Sequential or len(net) % 2 == 0:
        return None
    layers = list(net)
    for i, module in enumerate(layers):
        if type(module) is not (nn.Linear if i % 2 == 0 else nn.ReLU):
            return None
        if type(module) is nn.Linear and (
            module.bias is None or module.weight.dtype != torch.float32
        ):
            return None
    for module in (net, *layers):
        if module._forward_hooks or module._forward_pre_hooks or module._backward_hooks:
            return None
        if module._backward_pre_hooks or module._state_dict_hooks:
            return None
    for module in layers:
        for p in module.parameters(recurse=False):
            if p._backward_hooks or getattr(p, "_post_accumulate_grad_hooks", None):
                return None  # autograd would call them
            if p.is_sparse or p.device.type != "cpu":
                return None
    return layers[0::2]


class FusedMSEGradient:
    """``mse_loss(net(x), y)`` and its parameter gradients, written into reused buffers.

    For a plain ReLU MLP (a hook-free ``Sequential`` of ``Linear`` layers with bias and
    ``ReLU`` between them, float32 on the CPU: the world model's network); build it with
    :meth:`for_net`, which returns ``None`` for any other network. :meth:`loss_and_grad`
    leaves in every parameter's ``.grad`` exactly what ``mse_loss(net(x), y).backward()``
    after ``zero_grad(set_to_none=True)`` leaves there (the same kernels on the same operands;
    tested bit for bit), without building an autograd graph or allocating per step.

    Args:
        linears: the network's ``Linear`` layers, in order (ReLUs between them).

    Examples:
        >>> import torch
        >>> from torch import nn
        >>> from torchrl_mbmf.world_model.fused_step import FusedMSEGradient
        >>> net = nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Linear(8, 2))
        >>> x, y = torch.randn(5, 3), torch.randn(5, 2)
        >>> loss = FusedMSEGradient.for_net(net).loss_and_grad(x, y)
        >>> fused = [p.grad.clone() for p in net.parameters()]
        >>> net.zero_grad(set_to_none=True)
        >>> reference = nn.functional.mse_loss(net(x), y)
        >>> reference.backward()
        >>> torch.equal(loss, reference.detach())
        True
        >>> all(torch.equal(a, p.grad) for a, p in zip(fused, net.parameters()))
        True
        >>> FusedMSEGradient.for_net(nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 2)))
    """

    def __init__(self, linears: list[nn.Linear]) -> None:
        if not linears or any(type(layer) is not nn.Linear for layer in linears):
            raise ValueError(f"expects a non-empty list of nn.Linear layers, got {linears!r}")
        self.linears = linears
        self._one = torch.ones(())
        self._buffers: dict[int, tuple[list[torch.Tensor], list[torch.Tensor]]] = {}

    @classmethod
    def for_net(cls, net: nn.Module) -> FusedMSEGradient | None:
        """The fused step of ``net``, or ``None`` if ``net`` is not a plain ReLU MLP.

        Args:
            net: the network.

        Examples:
            >>> from torch import nn
            >>> from torchrl_mbmf.world_model.fused_step import FusedMSEGradient
            >>> FusedMSEGradient.for_net(nn.Sequential(nn.Linear(2, 4), nn.ReLU(),
            ...                                        nn.Linear(4, 1))) is not None
            True
        """
        linears = _relu_mlp_linears(net)
        return None if linears is None else cls(linears)

    def _workspace(self, rows: int) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Per layer: its output ``[rows, out]`` and the loss gradient w.r.t. that output."""
        if rows not in self._buffers:
            outs = [torch.empty(rows, layer.out_features) for layer in self.linears]
            grads = [torch.empty_like(out) for out in outs]
            self._buffers[rows] = (outs, grads)
        return self._buffers[rows]

    def _grad_buffer(self, param: nn.Parameter) -> torch.Tensor:
        grad = param.grad
        if grad is None or grad.shape != param.shape or not grad.is_contiguous():
            param.grad = grad = torch.empty_like(param, memory_format=torch.contiguous_format)
        return grad

    def forward(self, x: torch.Tensor, *, out: list[torch.Tensor] | None = None) -> torch.Tensor:
        """``net(x)`` without autograd (the same values), into ``out`` buffers if given.

        Args:
            x: the input ``[N, in]``.

        Keyword Args:
            out: one ``[N, out_features]`` buffer per layer. Defaults to new tensors.

        Examples:
            >>> import torch
            >>> from torch import nn
            >>> from torchrl_mbmf.world_model.fused_step import FusedMSEGradient
            >>> net = nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Linear(8, 2))
            >>> x = torch.randn(4, 3)
            >>> torch.equal(FusedMSEGradient.for_net(net).forward(x), net(x))
            True
        """
        last = len(self.linears) - 1
        with torch.no_grad():
            for i, layer in enumerate(self.linears):
                buffer = None if out is None else out[i]
                x = affine(x, layer.weight.t(), layer.bias, out=buffer)  # nn.Linear's addmm
                if i < last:
                    x.relu_()
        return x

    def loss_and_grad(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """``mse_loss(net(x), y)`` (detached), its gradients written into each ``.grad``.

        Args:
            x: scaled inputs ``[N, in]`` (contiguous rows: a slice of the epoch's buffer).
            y: scaled targets ``[N, out]``.

        Returns:
            The loss, a 0-d tensor.

        Examples:
            >>> import torch
            >>> from torch import nn
            >>> from torchrl_mbmf.world_model.fused_step import FusedMSEGradient
            >>> net = nn.Sequential(nn.Linear(3, 8), nn.ReLU(), nn.Linear(8, 2))
            >>> step = FusedMSEGradient.for_net(net)
            >>> step.loss_and_grad(torch.zeros(4, 3), torch.zeros(4, 2)).shape
            torch.Size([])
        """
        outs, grads = self._workspace(x.shape[0])
        prediction = self.forward(x, out=outs)
        with torch.no_grad():
            loss = nn.functional.mse_loss(prediction, y)
            # autograd's MseLossBackward0 with the seed gradient 1 of loss.backward()
            torch.ops.aten.mse_loss_backward.grad_input(
                self._one, prediction, y, 1, grad_input=grads[-1]
            )
            for i in range(len(self.linears) - 1, -1, -1):
                layer, grad_out = self.linears[i], grads[i]
                below = outs[i - 1] if i > 0 else x
                # AddmmBackward0 of addmm(bias, below, weight.t()): the weight's gradient as
                # grad_out.t() @ below ([out, in], the layout autograd hands to .grad), the
                # bias' as the sum over rows, the input's as grad_out @ weight
                torch.mm(grad_out.t(), below, out=self._grad_buffer(layer.weight))
                bias_grad = self._grad_buffer(layer.bias)
                torch.sum(grad_out, 0, keepdim=True, out=bias_grad.view(1, -1))
                if i > 0:
                    grad_below = grads[i - 1]
                    torch.mm(grad_out, layer.weight, out=grad_below)
                    # ReluBackward0 of the in-place ReLU: zero where its output is <= 0
                    torch.ops.aten.threshold_backward.grad_input(
                        grad_below, below, 0, grad_input=grad_below
                    )
        return loss
