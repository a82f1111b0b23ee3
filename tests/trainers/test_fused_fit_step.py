"""The fit's hand-written step equals autograd bit for bit; other networks take autograd."""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from torchrl_mbmf.modules import DeltaDynamicsModel
from torchrl_mbmf.objectives import DynamicsLoss
from torchrl_mbmf.world_model import fit_dynamics
from torchrl_mbmf.world_model.fused_step import FusedMSEGradient


@pytest.fixture
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("hidden", [(), (40,), (64, 48, 32)])
def test_steps_equal_autograd_bit_for_bit(one_thread, hidden):
    """Adam steps on full and partial batches: same losses, gradients and weights."""
    torch.manual_seed(0)
    model = DeltaDynamicsModel(7, 3, hidden_sizes=hidden)
    twin = copy.deepcopy(model)
    loss_module = DynamicsLoss(model)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    opt_twin = torch.optim.Adam(twin.parameters(), lr=1e-2)
    step = FusedMSEGradient.for_net(twin.net)
    g = torch.Generator().manual_seed(1)
    x, y = torch.randn(700, 10, generator=g), torch.randn(700, 8, generator=g)
    for start, stop in [(0, 128), (128, 256), (256, 300), (300, 428), (600, 601)] * 3:
        loss = loss_module.scaled_loss(x[start:stop], y[start:stop])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        fused = step.loss_and_grad(x[start:stop], y[start:stop])
        assert torch.equal(fused, loss.detach())
        for p, q in zip(model.parameters(), twin.parameters(), strict=True):
            assert torch.equal(p.grad, q.grad)
        opt.step()
        opt_twin.step()
    for p, q in zip(model.parameters(), twin.parameters(), strict=True):
        assert torch.equal(p, q)
    with torch.no_grad():
        assert torch.equal(step.forward(x), model.net(x))


def test_only_plain_relu_networks():
    relu = nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 2))
    assert FusedMSEGradient.for_net(relu) is not None
    others = [
        nn.Sequential(nn.Linear(3, 4), nn.Tanh(), nn.Linear(4, 2)),
        nn.Sequential(nn.Linear(3, 4, bias=False), nn.ReLU(), nn.Linear(4, 2)),
        nn.Sequential(nn.Linear(3, 4), nn.ReLU()),
        nn.Sequential(nn.Linear(3, 4).double(), nn.ReLU(), nn.Linear(4, 2).double()),
        nn.Linear(3, 2),
    ]
    hooked = copy.deepcopy(relu)
    hooked[2].register_forward_hook(lambda *args: None)
    grad_hooked = copy.deepcopy(relu)
    grad_hooked[0].weight.register_post_accumulate_grad_hook(lambda p: None)
    for net in [*others, hooked, grad_hooked]:
        assert FusedMSEGradient.for_net(net) is None
    with pytest.raises(ValueError, match=r"nn\.Linear layers"):
        FusedMSEGradient([])


def test_other_networks_fit_through_autograd(one_thread):
    """A tanh network is not a plain ReLU MLP: its fit takes the autograd loop and learns."""
    torch.manual_seed(0)
    model = DeltaDynamicsModel(4, 2, hidden_sizes=(16,), activation=nn.Tanh)
    g = torch.Generator().manual_seed(0)
    s, a = torch.randn(300, 4, generator=g), torch.rand(300, 2, generator=g) * 2 - 1
    nxt = s + 0.1 * torch.tanh(torch.cat([s[:, 2:], a], -1))
    data = TensorDict(
        state=s,
        action=a,
        next=TensorDict(state=nxt, reward=s[:, :1], batch_size=[300]),
        batch_size=[300],
    )
    history = fit_dynamics(model, data, lr=1e-2, batch_size=64, max_epochs=5, seed=0)
    assert history.val_loss[-1] < history.val_loss[0]
