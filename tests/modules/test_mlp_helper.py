"""The plain-op MLP runner of the fast paths equals torch's own modules, value and gradient.

The reference is ``nn.Sequential`` of ``nn.Linear`` / activations (and, for stacked members,
each member's own ``nn.functional.linear``), never the helper under test.
"""

from __future__ import annotations

import pytest
import torch
from torch import nn

from torchrl_mbmf.modules.mlp import activate, affine, plain_layers, run_plain


@pytest.mark.parametrize("act", [nn.ReLU, nn.Tanh])
@pytest.mark.parametrize("shape", [(7, 5), (3, 7, 5)])
def test_run_plain_equals_the_modules_bit_for_bit(act: type[nn.Module], shape: tuple) -> None:
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(5, 16), act(), nn.Linear(16, 16), act(), nn.Linear(16, 3))
    x = torch.randn(*shape, requires_grad=True)
    ref = net(x)
    (ref_grad,) = torch.autograd.grad(ref.square().sum(), x)
    ref_w = torch.autograd.grad(net(x).square().sum(), net[0].weight)[0]
    steps = [
        (m.weight.t(), m.bias) if isinstance(m, nn.Linear) else plain_layers([m])[0] for m in net
    ]
    out = run_plain(steps, x)
    assert torch.equal(out, ref)
    (grad,) = torch.autograd.grad(out.square().sum(), x)
    assert torch.equal(grad, ref_grad)
    w_grad = torch.autograd.grad(run_plain(steps, x).square().sum(), net[0].weight)[0]
    assert torch.equal(w_grad, ref_w)
    record: list[torch.Tensor] = []
    assert torch.equal(run_plain(steps, x, record=record), ref)
    assert len(record) == len(net)
    assert torch.equal(record[1], act()(net[0](x)))  # recorded activations are kept intact


def test_plain_layers_keeps_other_modules_as_callables() -> None:
    torch.manual_seed(0)
    net = nn.Sequential(nn.Linear(4, 6), nn.ELU(), nn.Linear(6, 2, bias=False))
    steps = plain_layers(list(net))
    assert isinstance(steps[0], tuple)
    assert steps[1] is net[1] and steps[2] is net[2]
    x = torch.randn(5, 4)
    assert torch.equal(run_plain(steps, x), net(x))


def test_affine_runs_stacked_members_as_each_members_linear() -> None:
    torch.manual_seed(0)
    weight_t, bias, x = torch.randn(3, 4, 6), torch.randn(3, 1, 6), torch.randn(3, 5, 4)
    out = affine(x, weight_t, bias)
    for k in range(3):
        ref = nn.functional.linear(x[k], weight_t[k].t(), bias[k, 0])
        assert torch.allclose(out[k], ref, atol=1e-6)
    buffer = torch.empty(3, 5, 6)
    assert affine(x, weight_t, bias, out=buffer) is buffer
    assert torch.equal(buffer, out)


def test_affine_without_bias_and_bad_out() -> None:
    torch.manual_seed(0)
    layer, x = nn.Linear(4, 2, bias=False), torch.randn(5, 4)
    assert torch.equal(affine(x, layer.weight.t(), None), layer(x))
    with pytest.raises(ValueError, match="out only"):
        affine(x, layer.weight.t(), None, out=torch.empty(5, 2))
    with pytest.raises(ValueError, match="2-d"):
        affine(torch.randn(2, 5, 4), layer.weight.t(), torch.zeros(2), out=torch.empty(2, 5, 2))


def test_activate_in_place_only_when_asked() -> None:
    x = torch.tensor([-1.0, 2.0])
    assert torch.equal(activate(x, "relu"), torch.tensor([0.0, 2.0]))
    assert torch.equal(x, torch.tensor([-1.0, 2.0]))
    assert activate(x, "tanh", inplace=True) is x
    assert torch.equal(activate(torch.ones(1), nn.Sigmoid()), torch.sigmoid(torch.ones(1)))
