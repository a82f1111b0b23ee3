from __future__ import annotations

import io

import pytest
import torch
from tensordict import TensorDict

from torchrl_mbmf.modules import DeltaDynamicsModel


def _data(n=256, s=5, a=2):
    g = torch.Generator().manual_seed(0)
    state = torch.randn(n, s, generator=g) * 3 + 1
    action = torch.rand(n, a, generator=g) * 2 - 1
    next_state = state + 0.5 * torch.randn(n, s, generator=g) + 2
    reward = torch.randn(n, 1, generator=g) * 4 - 1
    return state, action, next_state, reward


def test_thesis_architecture():
    model = DeltaDynamicsModel(18, 6)
    linears = [m for m in model.net if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(24, 500), (500, 500), (500, 19)]
    assert sum(isinstance(m, torch.nn.ReLU) for m in model.net) == 2
    assert isinstance(model.net[-1], torch.nn.Linear)  # linear output


def test_normalizer_statistics_and_targets():
    state, action, next_state, reward = _data()
    model = DeltaDynamicsModel(5, 2, hidden_sizes=(8,))
    assert not model.normalizer_fitted
    model.fit_normalizer(state, action, next_state, reward)
    assert model.normalizer_fitted
    torch.testing.assert_close(model.state_loc, state.mean(0))
    torch.testing.assert_close(model.state_scale, state.std(0))
    torch.testing.assert_close(model.delta_loc, (next_state - state).mean(0))
    torch.testing.assert_close(model.reward_scale, reward.std(0))
    targets = model.scale_targets(state, next_state, reward)
    torch.testing.assert_close(targets.mean(0), torch.zeros(6), atol=1e-5, rtol=0)
    torch.testing.assert_close(targets.std(0), torch.ones(6), atol=1e-5, rtol=0)
    # forward un-scales: a network output equal to the scaled targets reproduces the data
    next_pred, reward_pred = model.unscale(state, targets)
    torch.testing.assert_close(next_pred, next_state, atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(reward_pred, reward, atol=1e-4, rtol=1e-5)


def test_forward_adds_delta_and_clips_actions():
    state, action, next_state, reward = _data()
    model = DeltaDynamicsModel(5, 2, hidden_sizes=(8,), action_low=-1.0, action_high=1.0)
    model.fit_normalizer(state, action, next_state, reward)
    s = state[:3]
    out_clip, r_clip = model(s, torch.full((3, 2), 1.0))
    out_big, r_big = model(s, torch.full((3, 2), 7.0))
    torch.testing.assert_close(out_clip, out_big)
    torch.testing.assert_close(r_clip, r_big)
    raw = model.predict_scaled(s, torch.zeros(3, 2))
    nxt, _ = model(s, torch.zeros(3, 2))
    torch.testing.assert_close(nxt, s + raw[:, :5] * model.delta_scale + model.delta_loc)


def test_state_dict_round_trip_includes_scaling():
    state, action, next_state, reward = _data()
    model = DeltaDynamicsModel(5, 2, hidden_sizes=(8,))
    model.fit_normalizer(state, action, next_state, reward)
    buf = io.BytesIO()
    torch.save(model.state_dict(), buf)
    buf.seek(0)
    clone = DeltaDynamicsModel(5, 2, hidden_sizes=(8,))
    clone.load_state_dict(torch.load(buf, weights_only=True))
    for name in ("state_loc", "state_scale", "delta_loc", "reward_scale", "normalizer_fitted"):
        torch.testing.assert_close(getattr(clone, name), getattr(model, name))
    torch.testing.assert_close(clone(state, action)[0], model(state, action)[0])


def test_bad_input_errors():
    model = DeltaDynamicsModel(5, 2, hidden_sizes=(8,))
    with pytest.raises(ValueError, match="state_dim=5"):
        model(torch.zeros(3, 4), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="action_dim=2"):
        model(torch.zeros(3, 5), torch.zeros(3, 3))
    with pytest.raises(ValueError, match="batch"):
        model(torch.zeros(3, 5), torch.zeros(4, 2))
    state, action, next_state, reward = _data()
    next_state[3, 1] = float("nan")
    with pytest.raises(ValueError, match="delta contains NaN"):
        model.fit_normalizer(state, action, next_state, reward)
    assert not model.normalizer_fitted
    with pytest.raises(ValueError, match="at least 2"):
        model.fit_normalizer(state[:1], action[:1], state[:1], reward[:1])
    with pytest.raises(ValueError, match="state_dim"):
        DeltaDynamicsModel(0, 2)
    with pytest.raises(ValueError, match="action_low"):
        DeltaDynamicsModel(3, 2, action_low=1.0, action_high=-1.0)


def test_as_tensordict_module_any_batch():
    model = DeltaDynamicsModel(5, 2, hidden_sizes=(8,))
    module = model.as_tensordict_module(next_state_key=("next", "state"))
    td = TensorDict(state=torch.randn(2, 15, 5), action=torch.rand(2, 15, 2), batch_size=[2, 15])
    out = module(td)
    assert out["next", "state"].shape == (2, 15, 5)
    assert out["reward"].shape == (2, 15, 1)
    torch.testing.assert_close(out["next", "state"], model(td["state"], td["action"])[0])


@pytest.mark.parametrize("hidden", [(0,), (64, -1), (32.5,), (True,)])
def test_hidden_sizes_are_checked(hidden):
    with pytest.raises(ValueError, match=r"hidden_sizes must be a sequence of integers >= 1"):
        DeltaDynamicsModel(3, 1, hidden_sizes=hidden)
