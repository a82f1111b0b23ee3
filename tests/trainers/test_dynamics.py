from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torchrl_mbmf.modules import DeltaDynamicsModel
from torchrl_mbmf.objectives import DynamicsLoss
from torchrl_mbmf.world_model import fit_dynamics


def _linear_system(n=2000, seed=0):
    """s' = s + A s + B a, r = c.s - |a|^2: learnable by a small MLP."""
    g = torch.Generator().manual_seed(seed)
    mat_a = 0.1 * torch.randn(4, 4, generator=g)
    mat_b = 0.5 * torch.randn(2, 4, generator=g)
    c = torch.randn(4, generator=g)
    s = torch.randn(n, 4, generator=g)
    a = torch.rand(n, 2, generator=g) * 2 - 1
    nxt = s + s @ mat_a + a @ mat_b
    r = (s * c).sum(-1, keepdim=True) - a.pow(2).sum(-1, keepdim=True)
    return TensorDict(
        state=s, action=a, next=TensorDict(state=nxt, reward=r, batch_size=[n]), batch_size=[n]
    )


def test_fit_reduces_validation_loss_and_restores_best():
    torch.manual_seed(0)
    data = _linear_system()
    model = DeltaDynamicsModel(4, 2, hidden_sizes=(64, 64))
    history = fit_dynamics(model, data, lr=1e-3, batch_size=128, max_epochs=30, seed=0)
    assert history.epochs == len(history.val_loss) == len(history.train_loss)
    assert history.val_loss[-1] < 0.2 * history.val_loss[0]
    assert history.num_train + history.num_val == 2000
    assert history.num_val == 200
    # the kept weights are the best epoch's
    assert history.best_val_loss == pytest.approx(min(history.val_loss))
    # loss module on held-out-like data agrees with a manual MSE in scaled units
    fresh = _linear_system(200, seed=0)
    loss = DynamicsLoss(model)(fresh)["loss_dynamics"]
    pred = model.predict_scaled(fresh["state"], fresh["action"])
    target = model.scale_targets(fresh["state"], fresh["next", "state"], fresh["next", "reward"])
    torch.testing.assert_close(loss, (pred - target).pow(2).mean())


def test_early_stopping_on_noise():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    n = 300
    data = TensorDict(
        state=torch.randn(n, 3, generator=g),
        action=torch.rand(n, 1, generator=g),
        next=TensorDict(
            state=torch.randn(n, 3, generator=g),
            reward=torch.randn(n, 1, generator=g),
            batch_size=[n],
        ),
        batch_size=[n],
    )
    model = DeltaDynamicsModel(3, 1, hidden_sizes=(128, 128))
    history = fit_dynamics(model, data, lr=3e-3, batch_size=32, max_epochs=200, patience=3, seed=0)
    assert history.stopped_early
    assert history.epochs < 200
    assert history.epochs - 1 - history.best_epoch == 3


def test_same_seed_same_fit():
    data = _linear_system(400)
    out = []
    for _ in range(2):
        torch.manual_seed(0)
        model = DeltaDynamicsModel(4, 2, hidden_sizes=(16,))
        fit_dynamics(model, data, lr=1e-3, batch_size=64, max_epochs=3, seed=5)
        out.append(model(data["state"], data["action"])[0])
    torch.testing.assert_close(out[0], out[1])


def test_refuses_nan_and_bad_settings():
    data = _linear_system(100)
    data["next", "reward"][7] = float("inf")
    model = DeltaDynamicsModel(4, 2, hidden_sizes=(8,))
    with pytest.raises(ValueError, match="reward has NaN or Inf in 1 transitions"):
        fit_dynamics(model, data)
    good = _linear_system(100)
    with pytest.raises(ValueError, match="val_fraction"):
        fit_dynamics(model, good, val_fraction=1.0)
    with pytest.raises(ValueError, match="at least"):
        fit_dynamics(model, good[:2])
    with pytest.raises(ValueError, match="max_epochs"):
        fit_dynamics(model, good, max_epochs=0)
