"""The one world-model network: ``ensemble_size`` K, with K = 1 the thesis model of before.

The layouts and values below were recorded from the code before the single model and the
ensemble became one class (``DeltaDynamicsModel`` and its ``EnsembleDeltaDynamicsModel``
subclass), or are computed here with plain torch ops, never with the class under test.
"""

from __future__ import annotations

import hashlib
import math

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from torchrl_mbmf.envs import EnsembleLearnedDynamicsEnv, LearnedDynamicsEnv, make_gym_state_env
from torchrl_mbmf.modules import DeltaDynamicsModel, EnsembleDeltaDynamicsModel
from torchrl_mbmf.world_model import fit_dynamics
from torchrl_mbmf.world_model.ensemble_fit import fit_ensemble
from torchrl_mbmf.world_model.fit import fit_world_model
from torchrl_mbmf.world_model.fit_history import EnsembleFitHistory

BUFFERS = {
    "state_loc": (18,),
    "state_scale": (18,),
    "action_loc": (6,),
    "action_scale": (6,),
    "delta_loc": (18,),
    "delta_scale": (18,),
    "reward_loc": (1,),
    "reward_scale": (1,),
    "normalizer_fitted": (),
}
# the state_dict layouts of the thesis model and of a 5-member Gaussian ensemble, as saved
THESIS = {
    **BUFFERS,
    "net.0.weight": (500, 24),
    "net.0.bias": (500,),
    "net.2.weight": (500, 500),
    "net.2.bias": (500,),
    "net.4.weight": (19, 500),
    "net.4.bias": (19,),
}
ENSEMBLE5 = {
    **BUFFERS,
    "net.0.weight": (5, 24, 500),
    "net.0.bias": (5, 500),
    "net.2.weight": (5, 500, 500),
    "net.2.bias": (5, 500),
    "net.4.weight": (5, 500, 38),
    "net.4.bias": (5, 38),
}
# recorded from the code before the merge: seed-0 models fitted on _data() (see _recorded)
SINGLE_SHA = "41cea647e2b2e333d45b26c0934d91e4c9f9c84b7079c0f7f8355a02dd45fed5"
ENSEMBLE_SHA = "fadf6b69e6a5cd9bbde6050fc36228f5e161fd9c92dae64f940219c6ba2aadd1"
SINGLE_OUT = [-2.458516, -2.593783, -3.536677, 0.12054, 0.47297, 0.968831]
ENSEMBLE_OUT = [-2.410742, -2.587172, -3.621232, 0.086861, 0.609135, 0.200124]
ENSEMBLE_MEMBERS = [-8.067868, -7.836392, -7.865186]
ENSEMBLE_LOG_VAR = [-12.199121, -11.43125, -9.168539]
ENSEMBLE_DISAGREEMENT = [0.132043, 0.14019, 0.134191, 0.130161]


def _sha(state_dict: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for name, value in state_dict.items():
        h.update(name.encode())
        h.update(str(tuple(value.shape)).encode())
        h.update(value.detach().contiguous().numpy().tobytes())
    return h.hexdigest()


def _data():
    g = torch.Generator().manual_seed(1)
    s, a = torch.randn(64, 5, generator=g), torch.rand(64, 2, generator=g) * 2 - 1
    return s, a, s + 0.1 * torch.randn(64, 5, generator=g), torch.randn(64, generator=g)


def _layout(model: nn.Module) -> dict[str, tuple[int, ...]]:
    return {name: tuple(value.shape) for name, value in model.state_dict().items()}


def test_layouts_are_those_saved_before():
    thesis = DeltaDynamicsModel(18, 6)
    assert _layout(thesis) == THESIS and list(thesis.state_dict()) == list(THESIS)
    assert _layout(DeltaDynamicsModel(18, 6, ensemble_size=1)) == THESIS
    assert _layout(EnsembleDeltaDynamicsModel(18, 6, num_members=1)) == THESIS
    for ensemble in (
        EnsembleDeltaDynamicsModel(18, 6, probabilistic=True),
        DeltaDynamicsModel(18, 6, ensemble_size=5, probabilistic=True),
    ):
        assert _layout(ensemble) == ENSEMBLE5 and list(ensemble.state_dict()) == list(ENSEMBLE5)
    assert thesis.config == {
        "state_dim": 18,
        "action_dim": 6,
        "hidden_sizes": [500, 500],
        "action_low": -float("inf"),  # no clip until a learned env gives it its action spec
        "action_high": float("inf"),
    }
    ensemble = DeltaDynamicsModel(18, 6, ensemble_size=5, hidden_sizes=(8,))
    assert ensemble.config == {
        **thesis.config,
        "hidden_sizes": [8],
        "num_members": 5,
        "probabilistic": False,
        "min_log_var": -10.0,
        "max_log_var": 0.5,
    }
    thesis.set_action_bounds(-1.0, 1.0)  # what HalfCheetah's learned env sets
    assert (thesis.config["action_low"], thesis.config["action_high"]) == (-1.0, 1.0)


def _recorded(ensemble_class: bool):
    torch.manual_seed(0)
    single = DeltaDynamicsModel(5, 2, hidden_sizes=(16, 16))
    torch.manual_seed(0)
    if ensemble_class:
        kwargs = {"num_members": 3, "hidden_sizes": (16, 16), "probabilistic": True}
        ensemble = EnsembleDeltaDynamicsModel(5, 2, **kwargs)
    else:
        ensemble = DeltaDynamicsModel(
            5, 2, ensemble_size=3, hidden_sizes=(16, 16), probabilistic=True
        )
    for model in (single, ensemble):
        model.fit_normalizer(*_data())
    return single, ensemble


@pytest.mark.parametrize("ensemble_class", [True, False])
def test_seeded_weights_and_outputs_are_those_recorded_before(ensemble_class):
    single, ensemble = _recorded(ensemble_class)
    assert _sha(single.state_dict()) == SINGLE_SHA  # uniform draws: the same on every CPU
    assert _sha(ensemble.state_dict()) == ENSEMBLE_SHA
    s, a = _data()[0][:4], _data()[1][:4]

    def close(value, recorded):
        torch.testing.assert_close(value, torch.tensor(recorded), atol=2e-5, rtol=1e-5)

    close(torch.cat(single(s, a), -1).sum(0), SINGLE_OUT)
    close(torch.cat(ensemble(s, a), -1).sum(0), ENSEMBLE_OUT)
    close(ensemble.forward_members(s, a)[0].sum((1, 2)), ENSEMBLE_MEMBERS)
    close(ensemble.predict_scaled_members(s, a)[1].sum((1, 2)), ENSEMBLE_LOG_VAR)
    close(ensemble.disagreement(s, a), ENSEMBLE_DISAGREEMENT)


def test_k1_is_the_plain_thesis_mlp():
    """Seed, draw order and forward of the thesis model, rebuilt from stock torch layers."""
    torch.manual_seed(3)
    model = DeltaDynamicsModel(5, 2, hidden_sizes=(16, 16), action_low=-1.0, action_high=1.0)
    torch.manual_seed(3)
    ref = nn.Sequential(nn.Linear(7, 16), nn.ReLU(), nn.Linear(16, 16), nn.ReLU(), nn.Linear(16, 6))
    for name, value in ref.state_dict().items():
        assert torch.equal(model.net.state_dict()[name], value), name
    state, action, next_state, reward = _data()
    model.fit_normalizer(state, action, next_state, reward)
    s, a = state[:9], action[:9] * 3  # clipped
    x = torch.cat(
        [
            (s - state.mean(0)) / state.std(0),
            (a.clamp(-1, 1) - action.mean(0)) / action.std(0),
        ],
        -1,
    )
    delta = next_state - state
    out = ref(x)
    expected_state = s + out[:, :5] * delta.std(0) + delta.mean(0)
    expected_reward = out[:, 5:] * reward.std() + reward.mean()
    next_s, r = model(s, a)
    torch.testing.assert_close(next_s, expected_state, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(r, expected_reward, atol=1e-5, rtol=1e-5)


def test_k_members_are_stacked_uniform_layers():
    """K >= 2: one dropped nn.Linear draw, then each layer's [K, in, out] weight and bias."""
    torch.manual_seed(5)
    model = DeltaDynamicsModel(5, 2, ensemble_size=4, hidden_sizes=(16,))
    torch.manual_seed(5)
    nn.Linear(7, 6)
    params = []
    for n_in, n_out in ((7, 16), (16, 6)):
        bound = 1.0 / math.sqrt(n_in)
        params.append(
            (
                torch.empty(4, n_in, n_out).uniform_(-bound, bound),
                torch.empty(4, n_out).uniform_(-bound, bound),
            )
        )
    for (w, b), layer in zip(params, (model.net[0], model.net[2]), strict=True):
        assert torch.equal(layer.weight, w) and torch.equal(layer.bias, b)
    x = torch.randn(10, 7)
    h = torch.relu(torch.einsum("ni,kio->kno", x, params[0][0]) + params[0][1][:, None])
    expected = torch.einsum("kni,kio->kno", h, params[1][0]) + params[1][1][:, None]
    torch.testing.assert_close(model.members_from_scaled(x)[0], expected, atol=1e-5, rtol=1e-5)


def test_member_methods_on_an_ensemble_of_one():
    model = DeltaDynamicsModel(5, 2, hidden_sizes=(16,))
    model.fit_normalizer(*_data())
    s, a = _data()[0][:8], _data()[1][:8]
    next_s, _ = model(s, a)
    members_s, members_r = model.forward_members(s, a)
    assert members_s.shape == (1, 8, 5) and members_r.shape == (1, 8, 1)
    torch.testing.assert_close(members_s[0], next_s)
    assert torch.equal(model.disagreement(s, a), torch.zeros(8))
    assert torch.equal(model(s, a, member_index=torch.zeros(8, dtype=torch.long))[0], next_s)
    with pytest.raises(ValueError, match=r"member_index values must be in \[0, 0\]"):
        model(s, a, member_index=torch.ones(8, dtype=torch.long))
    copy = model.member(0)
    assert type(copy) is DeltaDynamicsModel and copy is not model
    for name, value in model.state_dict().items():
        assert torch.equal(copy.state_dict()[name], value), name
    with pytest.raises(ValueError, match="member index must be in"):
        model.member(1)
    x, y = model.scaled_inputs(s, a), model.scale_targets(s, _data()[2][:8], _data()[3][:8])
    loss = model.member_loss(x, y)
    assert loss.shape == (1,)
    torch.testing.assert_close(loss[0], nn.functional.mse_loss(model.net(x), y))
    torch.testing.assert_close(model.member_mse(x[None], y[None]), loss)
    with pytest.raises(ValueError, match=r"\[K=1, N, in\]"):
        model.members_from_scaled(x.expand(2, *x.shape))
    fused = model.fused_members()
    out = fused.members(s, a)
    torch.testing.assert_close(s + out[0, :, :5], next_s, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(fused.cyclic(s, a), out[0], atol=1e-6, rtol=1e-6)
    assert torch.equal(fused.disagreement(out), torch.zeros(8))


def test_ensemble_only_parts_need_two_members():
    with pytest.raises(ValueError, match="probabilistic=True needs ensemble_size >= 2"):
        DeltaDynamicsModel(5, 2, probabilistic=True)
    with pytest.raises(ValueError, match="ensemble_size must be an integer >= 1, got 0"):
        DeltaDynamicsModel(5, 2, ensemble_size=0)
    s, a, s2, r = _data()
    data = TensorDict(
        state=s,
        action=a,
        next=TensorDict(state=s2, reward=r[:, None], batch_size=[64]),
        batch_size=[64],
    )
    one = EnsembleDeltaDynamicsModel(5, 2, num_members=1, hidden_sizes=(8,))
    with pytest.raises(TypeError, match=r"ensemble_size >= 2.*ensemble_size=1"):
        fit_ensemble(one, data)
    assert type(fit_dynamics(one, data, max_epochs=1, seed=0)).__name__ == "FitHistory"
    two = DeltaDynamicsModel(5, 2, ensemble_size=2, hidden_sizes=(8,))
    history = fit_world_model(two, data, max_epochs=1, seed=0)
    assert isinstance(history, EnsembleFitHistory) and history.num_members == 2
    with pytest.raises(ValueError, match="fit_dynamics trains one network"):
        fit_dynamics(two, data)
    pendulum = make_gym_state_env("Pendulum-v1", seed=0)
    with pytest.raises(TypeError, match="ensemble_size=1"):
        EnsembleLearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), pendulum)
    with pytest.raises(TypeError, match="need an ensemble"):
        LearnedDynamicsEnv(
            DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), pendulum, member_assignment="cycle"
        )
    env = EnsembleLearnedDynamicsEnv(
        DeltaDynamicsModel(3, 1, ensemble_size=2, hidden_sizes=(8,)), pendulum
    )
    assert env.rollout(3)["next", "disagreement"].shape == (3, 1)
