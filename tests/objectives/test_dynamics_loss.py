from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.objectives import LossModule

from torchrl_mbmf.modules import DeltaDynamicsModel
from torchrl_mbmf.objectives import DynamicsLoss


def _transitions(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    s = torch.randn(n, 4, generator=g)
    a = torch.rand(n, 2, generator=g) * 4 - 2  # partly outside [-1, 1]: the model clips
    return TensorDict(
        state=s,
        action=a,
        next=TensorDict(
            state=s + 0.1 * torch.randn(n, 4, generator=g),
            reward=torch.randn(n, 1, generator=g),
            batch_size=[n],
        ),
        batch_size=[n],
    )


def _model(data):
    torch.manual_seed(0)
    model = DeltaDynamicsModel(4, 2, hidden_sizes=(16,), action_low=-1.0, action_high=1.0)
    model.fit_normalizer(
        data["state"], data["action"], data["next", "state"], data["next", "reward"]
    )
    return model


def test_equals_eq17_by_hand():
    data = _transitions()
    model = _model(data)
    out = DynamicsLoss(model)(data)
    # eq. 17 by hand: standard-scale inputs, delta and reward with the model's statistics
    s, a = data["state"], data["action"].clamp(-1, 1)
    x = torch.cat(
        [(s - model.state_loc) / model.state_scale, (a - model.action_loc) / model.action_scale],
        -1,
    )
    delta = (data["next", "state"] - s - model.delta_loc) / model.delta_scale
    reward = (data["next", "reward"] - model.reward_loc) / model.reward_scale
    err = (model.net(x) - torch.cat([delta, reward], -1)).pow(2)
    torch.testing.assert_close(out["loss_dynamics"], err.mean())
    torch.testing.assert_close(out["loss_delta"], err[:, :4].mean())
    torch.testing.assert_close(out["loss_reward"], err[:, 4].mean())
    assert out["loss_dynamics"].requires_grad and not out["loss_delta"].requires_grad
    out["loss_dynamics"].backward()
    assert all(p.grad is not None for p in model.parameters())


def test_scaled_path_matches_tensordict_path():
    data = _transitions()
    loss = DynamicsLoss(_model(data))
    inputs, targets = loss.scaled_pairs(
        data["state"], data["action"], data["next", "state"], data["next", "reward"]
    )
    torch.testing.assert_close(
        loss.world_model.net(inputs), loss.world_model.predict_scaled(data["state"], data["action"])
    )
    torch.testing.assert_close(loss.scaled_loss(inputs, targets), loss(data)["loss_dynamics"])


def test_is_a_torchrl_loss_with_configurable_keys():
    model = DeltaDynamicsModel(4, 2, hidden_sizes=(8,))
    loss = DynamicsLoss(model)
    assert isinstance(loss, LossModule)
    assert loss.in_keys == ["state", "action", ("next", "state"), ("next", "reward")]
    loss.set_keys(state="s", next_state=("next", "s"), reward=("next", "r"))
    assert loss.in_keys == ["s", "action", ("next", "s"), ("next", "r")]
    data = _transitions(10)
    data.rename_key_("state", "s")
    data.rename_key_(("next", "state"), ("next", "s"))
    data.rename_key_(("next", "reward"), ("next", "r"))
    assert loss(data)["loss_dynamics"].requires_grad
    with pytest.raises(ValueError, match="not an accepted"):
        loss.set_keys(bogus="x")


def test_wrong_sizes_are_named():
    loss = DynamicsLoss(DeltaDynamicsModel(4, 2, hidden_sizes=(8,)))
    data = _transitions(5)
    data["action"] = torch.zeros(5, 3)
    with pytest.raises(ValueError, match="action_dim=2"):
        loss(data)


def _grads_of(model, x, y, loss_fn):
    model.zero_grad(set_to_none=True)
    loss = loss_fn(x, y)
    loss.backward()
    return loss.detach(), [p.grad.clone() for p in model.parameters()]


@pytest.mark.parametrize(
    "net",
    [
        lambda: torch.nn.Sequential(
            torch.nn.Linear(4, 16),
            torch.nn.ReLU(),
            torch.nn.Linear(16, 16),
            torch.nn.ReLU(),
            torch.nn.Linear(16, 4),
        ),
        lambda: torch.nn.Sequential(
            torch.nn.Linear(4, 16), torch.nn.Tanh(), torch.nn.Linear(16, 4)
        ),
        lambda: torch.nn.Sequential(
            torch.nn.Linear(4, 16), torch.nn.ReLU(), torch.nn.ReLU(), torch.nn.Linear(16, 4)
        ),
        lambda: torch.nn.Sequential(torch.nn.ReLU(), torch.nn.Linear(4, 4)),
    ],
    ids=["relu-mlp", "tanh", "relu-relu", "relu-first"],
)
def test_scaled_loss_fast_path_is_bit_identical(net):
    """The in-place ReLU forward gives the stock ``net(x)`` loss and gradients bit for bit."""
    torch.manual_seed(0)
    model = DeltaDynamicsModel(3, 1, hidden_sizes=(8,))
    model.net = net()
    loss = DynamicsLoss(model)
    x, y = torch.randn(64, 4), torch.randn(64, 4)
    x_before = x.clone()
    fast = _grads_of(model, x, y, loss.scaled_loss)
    stock = _grads_of(model, x, y, lambda a, b: torch.nn.functional.mse_loss(model.net(a), b))
    assert torch.equal(x, x_before)  # the input is never written to
    assert torch.equal(fast[0], stock[0])
    for g_fast, g_stock in zip(fast[1], stock[1], strict=True):
        assert torch.equal(g_fast, g_stock)
    with torch.no_grad():
        assert torch.equal(loss.scaled_loss(x, y), stock[0])


def test_scaled_loss_calls_forward_hooks():
    model = DeltaDynamicsModel(3, 1, hidden_sizes=(8,))
    calls = []
    model.net[1].register_forward_hook(lambda *args: calls.append(1))
    DynamicsLoss(model).scaled_loss(torch.randn(5, 4), torch.randn(5, 4))
    assert calls == [1]
