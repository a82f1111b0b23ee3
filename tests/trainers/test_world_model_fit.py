"""The one world-model fitter: its entry points are thin, and it refuses mixed-up options."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torchrl_mbmf.modules import DeltaDynamicsModel, EnsembleDeltaDynamicsModel
from torchrl_mbmf.world_model import (
    EnsembleFitHistory,
    FitHistory,
    fit_dynamics,
    fit_ensemble,
    fit_world_model,
    transition_tensors,
)


def _data(n: int = 200) -> TensorDict:
    g = torch.Generator().manual_seed(0)
    s, a = torch.randn(n, 4, generator=g), torch.rand(n, 2, generator=g) * 2 - 1
    nxt = s + 0.1 * torch.tanh(torch.cat([s[:, 2:], a], -1))
    done = torch.zeros(n, 1, dtype=torch.bool)
    done[49::50] = True
    r = s[:, :1] - a.pow(2).sum(-1, keepdim=True)
    return TensorDict(
        state=s,
        action=a,
        next=TensorDict(state=nxt, reward=r, done=done, batch_size=[n]),
        batch_size=[n],
    ).reshape(1, n)


@pytest.mark.parametrize("ensemble", [False, True])
def test_entry_points_are_the_one_fitter(ensemble):
    kwargs = {"lr": 1e-3, "batch_size": 32, "max_epochs": 3, "seed": 0}
    weights, histories = [], []
    for fit in (fit_world_model, fit_ensemble if ensemble else fit_dynamics):
        torch.manual_seed(0)
        if ensemble:
            model = EnsembleDeltaDynamicsModel(4, 2, num_members=2, hidden_sizes=(16,))
        else:
            model = DeltaDynamicsModel(4, 2, hidden_sizes=(16,))
        histories.append(fit(model, _data(), **kwargs))
        weights.append(model.state_dict())
    assert type(histories[0]) is (EnsembleFitHistory if ensemble else FitHistory)
    assert histories[0].val_loss == histories[1].val_loss
    for name, value in weights[0].items():
        assert torch.equal(weights[1][name], value), name


def test_options_belong_to_their_model():
    ens = EnsembleDeltaDynamicsModel(4, 2, num_members=2, hidden_sizes=(8,))
    with pytest.raises(ValueError, match="multi-step term fits one network only"):
        fit_world_model(ens, _data(), multi_step=3)
    with pytest.raises(ValueError, match="bootstrap=True resamples per member"):
        fit_world_model(DeltaDynamicsModel(4, 2, hidden_sizes=(8,)), _data(), bootstrap=True)
    with pytest.raises(ValueError, match="fit_dynamics trains one network"):
        fit_dynamics(ens, _data())
    with pytest.raises(TypeError, match="unexpected keyword argument"):
        fit_dynamics(DeltaDynamicsModel(4, 2, hidden_sizes=(8,)), _data(), epochs=3)


def test_transition_tensors_is_public_and_checks_values():
    shapes = [tuple(t.shape) for t in transition_tensors(_data())]
    assert shapes == [(200, 4), (200, 2), (200, 4), (200, 1)]
    bad = _data()
    bad["next", "reward"][0, 3] = float("inf")
    with pytest.raises(ValueError, match="reward has NaN or Inf in 1 transitions"):
        transition_tensors(bad)
