"""Ensemble world model, bootstrapped fit, ensemble env and the adaptive-horizon planner."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs
from torchrl.modules import ValueOperator

from torchrl_mbmf.data import collect_random_transitions
from torchrl_mbmf.envs import (
    EnsembleLearnedDynamicsEnv,
    LearnedDynamicsEnv,
    make_env,
    make_gym_state_env,
    make_half_cheetah_env,
)
from torchrl_mbmf.modules import (
    DeltaDynamicsModel,
    EnsembleDeltaDynamicsModel,
    EnsemblePolicyGuidedPlanner,
    PolicyGuidedMPCPlanner,
    make_ppo_actor_critic,
)
from torchrl_mbmf.modules.ensemble import EnsembleLinear
from torchrl_mbmf.world_model import fit_dynamics
from torchrl_mbmf.world_model.ensemble_fit import calibrate_disagreement_threshold, fit_ensemble


def _data(n=256, s=5, a=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    state = torch.randn(n, s, generator=g) * 3 + 1
    action = torch.rand(n, a, generator=g) * 2 - 1
    next_state = state + 0.5 * torch.randn(n, s, generator=g) + 2
    reward = torch.randn(n, 1, generator=g) * 4 - 1
    return state, action, next_state, reward


def _linear_system(n=1500, seed=0, noise=0.0, state_range=1.0):
    """s' = s + A s + B a, r = c.s - |a|^2 (+ noise on r): learnable by a small MLP."""
    g = torch.Generator().manual_seed(seed)
    mat_a = 0.1 * torch.randn(4, 4, generator=torch.Generator().manual_seed(100))
    mat_b = 0.5 * torch.randn(2, 4, generator=torch.Generator().manual_seed(101))
    c = torch.randn(4, generator=torch.Generator().manual_seed(102))
    s = (torch.rand(n, 4, generator=g) * 2 - 1) * state_range
    a = torch.rand(n, 2, generator=g) * 2 - 1
    nxt = s + s @ mat_a + a @ mat_b
    r = (s * c).sum(-1, keepdim=True) - a.pow(2).sum(-1, keepdim=True)
    r = r + noise * torch.randn(n, 1, generator=g)
    return TensorDict(
        state=s, action=a, next=TensorDict(state=nxt, reward=r, batch_size=[n]), batch_size=[n]
    )


def _per_member_mlp(model, k):
    """Member k rebuilt by hand as nn.Linear layers (weights [in, out] -> [out, in])."""
    layers = []
    linears = [m for m in model.net if isinstance(m, EnsembleLinear)]
    for i, lin in enumerate(linears):
        layer = nn.Linear(lin.in_features, lin.out_features)
        with torch.no_grad():
            layer.weight.copy_(lin.weight[k].T)
            layer.bias.copy_(lin.bias[k])
        layers.append(layer)
        if i < len(linears) - 1:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


# ----------------------------------------------------------------------------- the model
def test_batched_members_equal_a_loop_of_single_mlps():
    state, action, next_state, reward = _data()
    model = EnsembleDeltaDynamicsModel(
        5, 2, num_members=4, hidden_sizes=(16, 8), action_low=-1.0, action_high=1.0
    )
    model.fit_normalizer(state, action, next_state, reward)
    s, a = state[:6].reshape(2, 3, 5), action[:6].reshape(2, 3, 2) * 1.5  # some clipped
    next_members, reward_members = model.forward_members(s, a)
    assert next_members.shape == (4, 2, 3, 5) and reward_members.shape == (4, 2, 3, 1)
    x = torch.cat(
        [
            (s - model.state_loc) / model.state_scale,
            (a.clamp(-1, 1) - model.action_loc) / model.action_scale,
        ],
        -1,
    )
    fused = model.fused_members().members(s, a)
    for k in range(4):
        out = _per_member_mlp(model, k)(x)
        expected_next = s + out[..., :5] * model.delta_scale + model.delta_loc
        expected_reward = out[..., 5:] * model.reward_scale + model.reward_loc
        torch.testing.assert_close(next_members[k], expected_next, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(reward_members[k], expected_reward, rtol=1e-5, atol=1e-5)
        # the extracted member is that MLP too, and the folded fast path agrees
        single_next, single_reward = model.member(k)(s, a)
        torch.testing.assert_close(single_next, expected_next, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(single_reward, expected_reward, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(s + fused[k, ..., :5], expected_next, rtol=1e-4, atol=1e-4)
    # as a DeltaDynamicsModel: the members' mean
    mean_next, mean_reward = model(s, a)
    torch.testing.assert_close(mean_next, next_members.mean(0), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(mean_reward, reward_members.mean(0), rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(model.fused_step()(s, a)[0], mean_next, rtol=1e-4, atol=1e-4)


def test_members_are_independently_initialised():
    model = EnsembleDeltaDynamicsModel(5, 2, num_members=5, hidden_sizes=(32, 32))
    for lin in (m for m in model.net if isinstance(m, EnsembleLinear)):
        flat = lin.weight.reshape(5, -1)
        assert torch.cdist(flat, flat).masked_fill(torch.eye(5, dtype=torch.bool), 1).min() > 0
        # each member has nn.Linear's init scale
        bound = 1 / math.sqrt(lin.in_features)
        assert lin.weight.abs().max() <= bound
        assert lin.weight.std().item() == pytest.approx(bound / math.sqrt(3), rel=0.15)
    state, action, _, _ = _data(8)
    assert (model.disagreement(state, action) > 0).all()


def test_member_index_routing_and_errors():
    state, action, next_state, reward = _data()
    model = EnsembleDeltaDynamicsModel(5, 2, num_members=3, hidden_sizes=(16,))
    model.fit_normalizer(state, action, next_state, reward)
    s, a = state[:8].reshape(2, 4, 5), action[:8].reshape(2, 4, 2)
    members, rewards = model.forward_members(s, a)
    index = torch.tensor([[2, 0, 1, 1], [0, 0, 2, 1]])
    routed, routed_reward = model(s, a, member_index=index)
    for b in range(2):
        for i in range(4):
            torch.testing.assert_close(routed[b, i], members[index[b, i], b, i])
            torch.testing.assert_close(routed_reward[b, i], rewards[index[b, i], b, i])
    # the tensordict module and the cyclic convention
    cyc = EnsembleDeltaDynamicsModel.cyclic_member_index((2, 4), 3)
    assert cyc.tolist() == [[0, 1, 2, 0], [0, 1, 2, 0]]
    torch.testing.assert_close(
        model.fused_members().cyclic(s, a)[..., :5], model(s, a, cyc)[0] - s, atol=1e-5, rtol=1e-5
    )
    with pytest.raises(ValueError, match=r"member_index values must be in \[0, 2\].*max 3"):
        model(s, a, member_index=torch.full((2, 4), 3))
    with pytest.raises(ValueError, match=r"member_index has shape \(4,\), expected .*\(2, 4\)"):
        model(s, a, member_index=torch.zeros(4, dtype=torch.long))
    with pytest.raises(TypeError, match="integers"):
        model(s, a, member_index=torch.zeros(2, 4))
    with pytest.raises(ValueError, match="state has last dim 4, expected state_dim=5"):
        model.forward_members(torch.zeros(3, 4), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="member index must be in"):
        model.member(3)


@pytest.mark.parametrize("k", [0, -1, 2.0, True])
def test_num_members_must_be_a_positive_int(k):
    with pytest.raises(ValueError, match=f"num_members must be an integer >= 1, got {k!r}"):
        EnsembleDeltaDynamicsModel(3, 1, num_members=k)


def test_fused_cyclic_groups_candidates_by_member():
    model = EnsembleDeltaDynamicsModel(4, 2, num_members=3, hidden_sizes=(8, 8))
    s, a = torch.randn(2, 7, 4), torch.rand(2, 7, 2) * 2 - 1  # 7 is not a multiple of 3
    fused = model.fused_members()
    expected = model(s, a, model.cyclic_member_index((2, 7), 3))[0] - s
    torch.testing.assert_close(fused.cyclic(s, a)[..., :4], expected, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(
        fused.cyclic(s[0, 0], a[0, 0])[:4], model.member(0)(s[0, 0], a[0, 0])[0] - s[0, 0]
    )


def test_disagreement_is_the_std_of_the_normalised_delta():
    state, action, next_state, reward = _data()
    model = EnsembleDeltaDynamicsModel(5, 2, num_members=4, hidden_sizes=(16,))
    model.fit_normalizer(state, action, next_state, reward)
    s, a = state[:10], action[:10]
    members = model.forward_members(s, a)[0]
    normalised = (members - s - model.delta_loc) / model.delta_scale
    expected = normalised.std(0, unbiased=False).mean(-1)
    torch.testing.assert_close(model.disagreement(s, a), expected, rtol=1e-5, atol=1e-6)
    fused = model.fused_members()
    torch.testing.assert_close(fused.disagreement(fused.members(s, a)), expected, rtol=1e-4, atol=0)
    one = EnsembleDeltaDynamicsModel(5, 2, num_members=1, hidden_sizes=(16,))
    assert (one.disagreement(s, a) == 0).all()


def test_gaussian_outputs_and_nll():
    model = EnsembleDeltaDynamicsModel(
        4, 2, num_members=3, hidden_sizes=(16,), probabilistic=True, min_log_var=-4, max_log_var=1
    )
    x, y = torch.randn(10, 6), torch.randn(10, 5)
    mean, log_var = model.members_from_scaled(x)
    assert mean.shape == log_var.shape == (3, 10, 5)
    expected = (0.5 * (log_var + (mean - y).pow(2) / log_var.exp())).mean((-2, -1))
    torch.testing.assert_close(model.member_loss(x, y), expected)
    # real-unit predictions, the fused path and single members use the means
    s, a = torch.randn(7, 4), torch.rand(7, 2) * 2 - 1
    next_members = model.forward_members(s, a)[0]
    fused = model.fused_members().members(s, a)
    torch.testing.assert_close(s + fused[..., :4], next_members, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(model.member(2)(s, a)[0], next_members[2], atol=1e-5, rtol=1e-5)
    # the log-variance stays inside its soft bounds even for extreme raw outputs
    with torch.no_grad():
        model.net[-1].bias[..., 5:] = 1e4
    assert model.members_from_scaled(x)[1].max() <= 1 + 1e-5
    with torch.no_grad():
        model.net[-1].bias[..., 5:] = -1e4
    assert model.members_from_scaled(x)[1].min() >= -4 - 1e-5
    with pytest.raises(ValueError, match=r"min_log_var=1.0 must be < max_log_var=0.0"):
        EnsembleDeltaDynamicsModel(4, 2, probabilistic=True, min_log_var=1.0, max_log_var=0.0)


def test_probabilistic_fit_learns_where_the_noise_is():
    torch.manual_seed(0)
    data = _linear_system(1500, noise=2.0)  # the reward is mostly noise, the delta is exact
    model = EnsembleDeltaDynamicsModel(4, 2, num_members=3, hidden_sizes=(64,), probabilistic=True)
    history = fit_ensemble(model, data, lr=3e-3, batch_size=128, max_epochs=25, seed=0)
    assert history.train_loss[-1] < history.train_loss[0]
    assert all(math.isfinite(v) for v in history.train_loss + history.val_loss)
    _, log_var = model.predict_scaled_members(data["state"][:200], data["action"][:200])
    # scaled units: the noisy reward keeps a variance near 1, the exact delta much less
    assert log_var[..., 4].mean() > -1.0
    assert log_var[..., :4].mean() < log_var[..., 4].mean() - 2.0


# ------------------------------------------------------------------------------ fitting
@pytest.fixture(scope="module")
def fitted():
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    data = _linear_system(1500)
    model = EnsembleDeltaDynamicsModel(4, 2, num_members=4, hidden_sizes=(32, 32))
    before = [p.detach().clone() for p in model.parameters()]
    history = fit_ensemble(model, data, lr=2e-3, batch_size=128, max_epochs=25, seed=0)
    torch.set_num_threads(threads)
    return model, history, before


def test_fit_ensemble_reduces_loss_and_keeps_members_apart(fitted):
    model, history, before = fitted
    assert history.epochs == len(history.val_loss) == len(history.train_loss)
    assert history.val_loss[-1] < 0.2 * history.val_loss[0]
    assert history.train_loss[-1] < history.train_loss[0]
    assert history.best_val_loss == pytest.approx(min(history.val_loss))
    assert history.best_val_loss == pytest.approx(sum(history.member_val_loss) / 4, rel=1e-5)
    assert (history.num_train, history.num_val, history.num_members) == (1350, 150, 4)
    # every member trained (weights moved), on its own bootstrap sample, and they still differ
    assert all(not torch.equal(p, q) for p, q in zip(model.parameters(), before, strict=True))
    assert all(0.58 < u < 0.69 for u in history.unique_fraction)
    assert len(set(history.unique_fraction)) > 1
    weights = model.net[0].weight.reshape(4, -1)
    assert torch.cdist(weights, weights).masked_fill(torch.eye(4, dtype=torch.bool), 1).min() > 0
    test = _linear_system(300, seed=5)
    assert (model.disagreement(test["state"], test["action"]) > 0).all()
    # the loss module reads the members' mean, and the disagreement grows off the data
    far = _linear_system(300, seed=6, state_range=4.0)
    near_d = model.disagreement(test["state"], test["action"]).mean()
    far_d = model.disagreement(far["state"], far["action"]).mean()
    assert far_d > 2 * near_d


def test_fit_ensemble_is_reproducible_and_bootstrap_optional():
    data = _linear_system(400)
    results = []
    for bootstrap in (True, True, False):
        torch.manual_seed(1)
        model = EnsembleDeltaDynamicsModel(4, 2, num_members=2, hidden_sizes=(8,))
        h = fit_ensemble(
            model, data, lr=1e-3, batch_size=64, max_epochs=2, seed=3, bootstrap=bootstrap
        )
        results.append((h, model.net[0].weight.detach().clone()))
    assert results[0][0].val_loss == results[1][0].val_loss
    torch.testing.assert_close(results[0][1], results[1][1], rtol=0, atol=0)
    assert results[2][0].unique_fraction == [1.0, 1.0]
    assert not results[2][0].bootstrap


def test_fit_ensemble_early_stopping_on_noise():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(1)
    n = 300
    data = TensorDict(
        state=torch.randn(n, 3, generator=g),
        action=torch.rand(n, 1, generator=g) * 2 - 1,
        next=TensorDict(
            state=torch.randn(n, 3, generator=g),
            reward=torch.randn(n, 1, generator=g),
            batch_size=[n],
        ),
        batch_size=[n],
    )
    model = EnsembleDeltaDynamicsModel(3, 1, num_members=3, hidden_sizes=(64, 64))
    h = fit_ensemble(model, data, lr=3e-3, batch_size=32, max_epochs=60, patience=4, seed=0)
    assert h.stopped_early
    assert h.epochs == h.best_epoch + 1 + 4
    assert h.best_val_loss == pytest.approx(min([*h.val_loss, h.best_val_loss]))


def test_state_dict_round_trip_and_single_model_fit_is_refused():
    state, action, next_state, reward = _data()
    model = EnsembleDeltaDynamicsModel(5, 2, num_members=3, hidden_sizes=(8,), probabilistic=True)
    model.fit_normalizer(state, action, next_state, reward)
    copy = EnsembleDeltaDynamicsModel(5, 2, num_members=3, hidden_sizes=(8,), probabilistic=True)
    copy.load_state_dict(model.state_dict())
    torch.testing.assert_close(copy(state, action)[0], model(state, action)[0])
    assert copy.config == model.config and model.config["num_members"] == 3
    # fit_dynamics trains one network: it fails loudly on an ensemble, pointing to fit_ensemble
    with pytest.raises(ValueError, match="fit_ensemble"):
        fit_dynamics(EnsembleDeltaDynamicsModel(4, 2, num_members=2), _linear_system(50))


def test_fit_ensemble_rejects_bad_input():
    data = _linear_system(50)
    with pytest.raises(TypeError, match="EnsembleDeltaDynamicsModel, got DeltaDynamicsModel"):
        fit_ensemble(DeltaDynamicsModel(4, 2, hidden_sizes=(8,)), data)
    model = EnsembleDeltaDynamicsModel(4, 2, num_members=2, hidden_sizes=(8,))
    with pytest.raises(ValueError, match="val_fraction must be in"):
        fit_ensemble(model, data, val_fraction=1.0)
    bad = data.clone()
    bad["state"][3, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN or Inf"):
        fit_ensemble(model, bad)


def test_calibrated_threshold_is_the_held_out_quantile(fitted):
    model, _, _ = fitted
    held_out = _linear_system(400, seed=7)
    s, a, s2 = held_out["state"], held_out["action"], held_out["next", "state"]
    cal = calibrate_disagreement_threshold(model, s, a, s2, quantile=0.8, batch_size=64)
    d = model.disagreement(s, a).detach()
    assert cal.threshold == pytest.approx(float(torch.quantile(d, 0.8)), rel=1e-6)
    assert (d <= cal.threshold).float().mean().item() == pytest.approx(0.8, abs=0.003)
    assert cal.num_transitions == 400 and cal.quantile == 0.8
    # on a fitted ensemble the transitions it disagrees on are those it gets wrong
    mixed = torch.cat([s, _linear_system(100, seed=8, state_range=3.0)["state"]])
    a2 = torch.cat([a, a[:100]])
    nxt = mixed + mixed @ (0.1 * torch.randn(4, 4, generator=torch.Generator().manual_seed(100)))
    nxt = nxt + a2 @ (0.5 * torch.randn(2, 4, generator=torch.Generator().manual_seed(101)))
    cal2 = calibrate_disagreement_threshold(model, mixed, a2, nxt, quantile=0.8)
    assert cal2.error_above > cal2.error_below
    assert cal2.rank_correlation > 0.3
    with pytest.raises(ValueError, match=r"quantile must be in \(0, 1\], got 0"):
        calibrate_disagreement_threshold(model, s, a, s2, quantile=0)
    with pytest.raises(ValueError, match="actions must be"):
        calibrate_disagreement_threshold(model, s, a[:5], s2)
    one = EnsembleDeltaDynamicsModel(4, 2, num_members=1, hidden_sizes=(8,))
    with pytest.raises(ValueError, match="no positive threshold"):
        calibrate_disagreement_threshold(one, s, a, s2)


# ---------------------------------------------------------------------------------- envs
@pytest.fixture(scope="module")
def pendulum():
    return make_gym_state_env("Pendulum-v1", seed=0)


@pytest.mark.parametrize("assignment", ["cycle", "mean"])
def test_ensemble_env_specs_routing_and_disagreement(pendulum, assignment):
    model = EnsembleDeltaDynamicsModel(3, 1, num_members=3, hidden_sizes=(16,))
    env = EnsembleLearnedDynamicsEnv(model, pendulum, member_assignment=assignment)
    check_env_specs(env)
    start = pendulum.reset().expand(5).clone()
    start["state"] = torch.randn(5, 3)
    td = env.reset(start)
    assert (td["disagreement"] == 0).all()
    td["action"] = torch.rand(5, 1) * 4 - 2
    out = env.step(td)["next"]
    index = torch.tensor([0, 1, 2, 0, 1]) if assignment == "cycle" else None
    expected_state, expected_reward = model(td["state"], td["action"], index)
    torch.testing.assert_close(out["state"], expected_state)
    torch.testing.assert_close(out["reward"], expected_reward)
    torch.testing.assert_close(out["observation"], expected_state)  # Pendulum drops no dim
    torch.testing.assert_close(
        out["disagreement"][..., 0], model.disagreement(td["state"], td["action"])
    )
    torch.testing.assert_close(env.predict(td["state"], td["action"])[0], expected_state)
    fast = env.fast_predictor()(td["state"], td["action"])[0]
    torch.testing.assert_close(fast, expected_state, atol=1e-5, rtol=1e-5)


def test_learned_env_takes_the_ensemble_as_its_mean(pendulum):
    model = EnsembleDeltaDynamicsModel(3, 1, num_members=3, hidden_sizes=(16,))
    env = LearnedDynamicsEnv(model, pendulum)
    check_env_specs(env)
    td = env.reset(pendulum.reset().expand(4).clone())
    td["action"] = torch.rand(4, 1) * 2 - 1
    out = env.step(td)["next"]
    torch.testing.assert_close(out["state"], model(td["state"], td["action"])[0])
    # the plain planner runs on it too (the cached step falls back to the fused mean)
    actor, _ = make_ppo_actor_critic(pendulum, hidden_sizes=(8,))
    planner = PolicyGuidedMPCPlanner(env, actor, num_candidates=4, horizon=3)
    assert planner(pendulum.reset())["action"].shape == (1,)


def test_ensemble_env_rejects_a_single_model(pendulum):
    with pytest.raises(TypeError, match="EnsembleDeltaDynamicsModel, got DeltaDynamicsModel"):
        EnsembleLearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), pendulum)
    model = EnsembleDeltaDynamicsModel(3, 1, num_members=2, hidden_sizes=(8,))
    with pytest.raises(ValueError, match="member_assignment must be one of"):
        EnsembleLearnedDynamicsEnv(model, pendulum, member_assignment="random")


# ------------------------------------------------------------------------------ planner
C = torch.tensor([1.0, -2.0, 0.5, 3.0, -1.0, 2.0])
CUT = 0.5  # members disagree where state[1] > CUT
SPREAD = torch.tensor([0.0, 1.0, 2.0])  # member k adds SPREAD[k] * relu(s1 - CUT) to delta 0


def region_ensemble(real, spread=SPREAD):
    """Closed-form ensemble on HalfCheetah sizes (identity scaling), members identical except
    where state[1] > CUT: s'[1:7] = s[1:7] + clip(a), s'[17] = s[17] + 1 (a clock),
    s'[0] = s[0] + spread[k] * relu(s[1] - CUT), r = C . clip(a). The disagreement is therefore
    std(spread) * relu(s[1] - CUT) / 18 exactly."""
    k = len(spread)
    model = EnsembleDeltaDynamicsModel(18, 6, num_members=k, hidden_sizes=(13,))
    w1, b1 = torch.zeros(k, 24, 13), torch.zeros(k, 13)
    w2, b2 = torch.zeros(k, 13, 19), torch.zeros(k, 19)
    for j in range(6):
        w1[:, 18 + j, j], w1[:, 18 + j, 6 + j] = 1.0, -1.0  # relu(a), relu(-a)
        w2[:, j, 1 + j], w2[:, 6 + j, 1 + j] = 1.0, -1.0  # delta 1..6 = a
        w2[:, j, 18], w2[:, 6 + j, 18] = C[j], -C[j]  # reward = C . a
    w1[:, 1, 12], b1[:, 12] = 1.0, -CUT  # the region unit relu(s1 - CUT)
    w2[:, 12, 0] = spread
    b2[:, 17] = 1.0  # the clock
    with torch.no_grad():
        for layer, w, b in ((model.net[0], w1, b1), (model.net[2], w2, b2)):
            if k == 1:  # an ensemble of one is the thesis network: nn.Linear weights [out, in]
                w, b = w[0].T, b[0]
            layer.weight.copy_(w)
            layer.bias.copy_(b)
    return model


def clock_value():
    """V(observation) = observation[-1] = state[17], the clock."""
    lin = nn.Linear(17, 1)
    with torch.no_grad():
        lin.weight.zero_()
        lin.weight[0, 16] = 1.0
        lin.bias.zero_()
    return ValueOperator(lin, in_keys=["observation"])


@pytest.fixture(scope="module")
def cheetah():
    return make_half_cheetah_env(seed=0)


@pytest.fixture(scope="module")
def policy(cheetah):
    torch.manual_seed(0)
    return make_ppo_actor_critic(cheetah, init_log_std=-0.5)[0]


def hand_computed(planner, state, seed, threshold, discount):
    """Re-draws the planner's candidates; returns trusted steps and scores by the closed form."""
    torch.manual_seed(seed)
    m, h = planner.num_candidates, planner.horizon
    s = state.unsqueeze(-2).expand(*state.shape[:-1], m, 18).clone()
    std = SPREAD.std(unbiased=False).item()
    trusted = torch.full(s.shape[:-1], h)
    scores = torch.zeros(s.shape[:-1])
    alive = torch.ones(s.shape[:-1], dtype=torch.bool)
    margin = math.inf
    for t in range(h):
        a = planner.sampler.sample(s[..., 1:]).clamp(-1, 1)
        d = std * torch.relu(s[..., 1] - CUT) / 18
        margin = min(margin, (d - threshold).abs().min().item())
        alive = alive & (d <= threshold)
        trusted = torch.where(alive | (trusted < h), trusted, torch.full_like(trusted, t))
        scores += alive * discount**t * (a * C).sum(-1)
        s[..., 1:7] += a
        s[..., 17] += 1
    start_clock = state[..., 17].unsqueeze(-1)
    scores += discount**trusted * (start_clock + trusted)  # V at the last trusted state
    assert margin > 1e-4  # no candidate sits on the threshold: the float path cannot flip it
    return trusted, scores


@pytest.mark.parametrize("threshold", [0.01, None])
def test_adaptive_horizon_truncates_exactly_at_the_threshold(cheetah, policy, threshold):
    env = EnsembleLearnedDynamicsEnv(region_ensemble(cheetah), cheetah)
    discount = 0.9
    planner = EnsemblePolicyGuidedPlanner(
        env,
        policy,
        disagreement_threshold=threshold,
        num_candidates=15,
        horizon=8,
        value_module=clock_value(),
        discount=discount,
    )
    td = make_half_cheetah_env(num_envs=2, seed=1).reset()
    state = torch.zeros(2, 18)
    state[1, 1] = 0.4  # the second real state starts near the uncertain region
    state[:, 17] = torch.tensor([0.0, 3.0])
    td["state"], td["observation"] = state, state[:, 1:]
    torch.manual_seed(7)
    plan = planner.plan(td.clone())
    trusted, scores = hand_computed(planner, state, 7, threshold or math.inf, discount)
    assert torch.equal(plan.trusted_steps, trusted)
    torch.testing.assert_close(plan.returns, scores, rtol=1e-5, atol=1e-5)
    assert torch.equal(plan.best, scores.argmax(-1))
    if threshold is None:
        assert (trusted == 8).all()
    else:  # the test exercises early, late and no truncation
        assert trusted.min() < 3 and trusted.max() == 8 and len(trusted.unique()) >= 3
    torch.manual_seed(7)
    out = planner(td.clone())
    expected_h = trusted.gather(-1, plan.best[:, None]).float()
    torch.testing.assert_close(out["planner", "effective_horizon"], expected_h)
    torch.testing.assert_close(
        out["planner", "disagreement"], plan.disagreement.mean((-2, -1))[:, None]
    )
    torch.testing.assert_close(out["action"], plan.action)
    assert torch.equal(out["state"], state)  # its input is untouched


def test_untrusted_real_state_falls_back_to_the_first_policy_sample(cheetah, policy):
    env = EnsembleLearnedDynamicsEnv(region_ensemble(cheetah), cheetah)
    planner = EnsemblePolicyGuidedPlanner(
        env,
        policy,
        disagreement_threshold=1e-3,
        num_candidates=6,
        horizon=4,
        value_module=clock_value(),
    )
    td = cheetah.reset()
    state = torch.zeros(18)
    state[1], state[17] = 2.0, 5.0  # deep in the region: every first step is untrusted
    td["state"], td["observation"] = state, state[1:]
    plan = planner.plan(td)
    assert (plan.trusted_steps == 0).all()
    torch.testing.assert_close(plan.returns, torch.full((6,), 5.0))  # V(s_0) only
    assert plan.best.item() == 0


def test_without_threshold_it_is_the_plain_planner_on_identical_members(cheetah, policy):
    single = region_ensemble(cheetah, spread=torch.zeros(1)).member(0)
    same = region_ensemble(cheetah, spread=torch.zeros(3))
    kwargs = {"num_candidates": 15, "horizon": 6, "value_module": clock_value(), "discount": 0.95}
    plain = PolicyGuidedMPCPlanner(LearnedDynamicsEnv(single, cheetah), policy, **kwargs)
    ens = EnsemblePolicyGuidedPlanner(LearnedDynamicsEnv(same, cheetah), policy, **kwargs)
    td = make_half_cheetah_env(num_envs=3, seed=2).reset()
    torch.manual_seed(3)
    p0 = plain.plan(td.clone())
    torch.manual_seed(3)
    p1 = ens.plan(td.clone())
    torch.testing.assert_close(p1.returns, p0.returns, rtol=1e-5, atol=1e-5)
    assert torch.equal(p1.best, p0.best)
    assert (p1.trusted_steps == 6).all() and (p1.disagreement.abs() < 1e-6).all()


def test_cyclic_path_without_statistics_gives_the_same_plan(cheetah, policy):
    model = EnsembleDeltaDynamicsModel(18, 6, num_members=5, hidden_sizes=(32,))
    env = LearnedDynamicsEnv(model, cheetah)
    td = make_half_cheetah_env(num_envs=2, seed=3).reset()
    plans = []
    for stats_key in ("planner", None):
        planner = EnsemblePolicyGuidedPlanner(env, policy, stats_key=stats_key, horizon=5)
        assert planner.tracks_disagreement == (stats_key is not None)
        torch.manual_seed(4)
        plans.append(planner.plan(td.clone()))
    torch.testing.assert_close(plans[0].returns, plans[1].returns, rtol=1e-4, atol=1e-4)
    assert torch.equal(plans[0].best, plans[1].best)
    # and the candidates did follow different members: rolled in the ensemble env instead
    ens_env = EnsembleLearnedDynamicsEnv(model, cheetah)
    start = td.unsqueeze(-1).expand(2, 15).clone()
    planner = EnsemblePolicyGuidedPlanner(ens_env, policy, horizon=5)
    torch.manual_seed(4)
    sample = TensorDictModule(planner.sampler.sample, in_keys=["observation"], out_keys=["action"])
    rollout = ens_env.rollout(
        5,
        sample,
        tensordict=ens_env.reset(start),
        auto_reset=False,
    )
    torch.testing.assert_close(
        rollout["next", "reward"].sum((-2, -1)), plans[0].returns, rtol=1e-4, atol=1e-4
    )
    torch.testing.assert_close(
        rollout["next", "disagreement"][..., 0], plans[0].disagreement, rtol=1e-4, atol=1e-5
    )


# ----------------------------------------------------------------- refinement (LOOP's acting)
@pytest.mark.parametrize("refinement", ["cem", "mppi"])
def test_refined_plan_on_identical_members_is_the_single_model_refined_plan(
    cheetah, policy, refinement
):
    # An ensemble of one is the thesis network, which the single-model planner plans with (the
    # ensemble planner needs K >= 2): K identical members stand in for it here.
    single = region_ensemble(cheetah, spread=torch.zeros(1)).member(0)
    same = region_ensemble(cheetah, spread=torch.zeros(3))
    kwargs = {
        "num_candidates": 15,
        "horizon": 6,
        "value_module": clock_value(),
        "discount": 0.95,
        "refinement": refinement,
        "iterations": 3,
    }
    plain = PolicyGuidedMPCPlanner(LearnedDynamicsEnv(single, cheetah), policy, **kwargs)
    ens = EnsemblePolicyGuidedPlanner(LearnedDynamicsEnv(same, cheetah), policy, **kwargs)
    td = make_half_cheetah_env(num_envs=3, seed=2).reset()
    torch.manual_seed(3)
    p0 = plain.plan(td.clone())
    torch.manual_seed(3)
    p1 = ens.plan(td.clone())
    assert p1.returns.shape == p0.returns.shape == (3, 15 * 4)
    torch.testing.assert_close(p1.returns, p0.returns, rtol=1e-5, atol=1e-5)
    assert torch.equal(p1.best, p0.best)
    torch.testing.assert_close(p1.action, p0.action)
    assert (p1.trusted_steps == 6).all() and p1.disagreement.shape == (3, 60, 6)
    # the refined rounds found better candidates than the policy round
    assert (p1.returns[:, 15:].amax(-1) > p1.returns[:, :15].amax(-1)).all()


def member_scaled_ensemble(real):
    """:func:`region_ensemble` whose member ``k`` rewards ``(k + 1) C . clip(a)``."""
    model = region_ensemble(real)
    with torch.no_grad():
        for k in range(len(SPREAD)):
            model.net[2].weight[k, :12, 18] *= k + 1
    return model


def member_scores(state, actions, threshold, discount):
    """Trusted steps and scores of candidates ``[B, m, h, 6]`` of :func:`member_scaled_ensemble`
    by the closed form, candidate ``i`` in member ``i mod K``, value the clock."""
    b, m, h, _ = actions.shape
    s = state.unsqueeze(-2).expand(b, m, 18).clone()
    scale = (torch.arange(m) % len(SPREAD) + 1).float()
    std = SPREAD.std(unbiased=False).item()
    trusted = torch.full((b, m), h)
    scores = torch.zeros(b, m)
    alive = torch.ones(b, m, dtype=torch.bool)
    margin = math.inf
    for t in range(h):
        a = actions[..., t, :].clamp(-1, 1)
        d = std * torch.relu(s[..., 1] - CUT) / 18
        margin = min(margin, (d - threshold).abs().min().item())
        alive = alive & (d <= threshold)
        trusted = torch.where(alive | (trusted < h), trusted, torch.full_like(trusted, t))
        scores += alive * discount**t * scale * (a * C).sum(-1)
        s[..., 1:7] += a
        s[..., 17] += 1
    scores += discount**trusted * (state[..., 17:18] + trusted)
    assert margin > 1e-4  # no candidate sits on the threshold: the float path cannot flip it
    return trusted, scores


@pytest.mark.parametrize("refinement", ["cem", "mppi"])
def test_refinement_scores_every_round_in_the_candidates_own_member(cheetah, policy, refinement):
    env = EnsembleLearnedDynamicsEnv(member_scaled_ensemble(cheetah), cheetah)
    m, h, rounds, threshold, discount = 15, 6, 3, 0.008, 0.9
    kwargs = {"num_candidates": m, "horizon": h, "value_module": clock_value()}
    kwargs.update(disagreement_threshold=threshold, discount=discount)
    plain = EnsemblePolicyGuidedPlanner(env, policy, **kwargs)
    planner = EnsemblePolicyGuidedPlanner(
        env, policy, refinement=refinement, iterations=rounds - 1, num_elites=4, **kwargs
    )
    rollouts, refits, sequences = [], [], []

    def rollout(state, source=None):
        rollouts.append(type(planner).rollout(planner, state, source))
        return rollouts[-1]

    def refit(actions, returns):
        refits.append((actions, returns, *type(planner)._refit(planner, actions, returns)))
        return refits[-1][2:]

    def refined(rollout, returns):
        sequences.append(type(planner).refined_sequences(planner, rollout, returns))
        return sequences[-1]

    planner.rollout, planner._refit, planner.refined_sequences = rollout, refit, refined
    td = make_half_cheetah_env(num_envs=2, seed=1).reset()
    state = torch.zeros(2, 18)
    state[1, 1] = 0.4  # the second real state starts near the uncertain region
    state[:, 17] = torch.tensor([0.0, 3.0])
    td["state"], td["observation"] = state, state[:, 1:]
    torch.manual_seed(7)
    first = plain.plan(td.clone())
    torch.manual_seed(7)
    plan = planner.plan(td.clone())
    assert len(rollouts) == rounds and plan.returns.shape == (2, rounds * m)
    # the policy round is the unrefined plan, drawn identically
    torch.testing.assert_close(plan.returns[:, :m], first.returns)
    n_policy = round(m / 3)
    for r, out in enumerate(rollouts):
        # every candidate of every round: its own member's truncated return plus the value
        trusted, scores = member_scores(state, out.actions, threshold, discount)
        assert torch.equal(plan.trusted_steps[:, r * m : (r + 1) * m], trusted)
        torch.testing.assert_close(plan.returns[:, r * m : (r + 1) * m], scores)
        if r == 0:
            continue
        # a refined round: policy samples first, then the sequences drawn from the Gaussian
        # refitted to the previous round's candidates and their own-member scores
        torch.testing.assert_close(out.actions[:, n_policy:], sequences[r - 1])
        actions, returns, mean, std = refits[r - 1]
        assert torch.equal(actions, rollouts[r - 1].actions)
        assert torch.equal(returns, plan.returns[:, (r - 1) * m : r * m])
        if refinement == "cem":
            elite = returns.topk(4, dim=-1).indices
            chosen = torch.stack([actions[b, elite[b]] for b in range(2)])
            expected_mean, expected_std = chosen.mean(1), chosen.std(1, unbiased=False)
        else:
            z = (returns - returns.amax(-1, keepdim=True)) / returns.std(-1, keepdim=True)
            w = torch.softmax(z, -1)[..., None, None]
            expected_mean = (w * actions).sum(1)
            expected_std = (w * (actions - expected_mean[:, None]).square()).sum(1).sqrt()
        torch.testing.assert_close(mean, expected_mean)
        torch.testing.assert_close(std, expected_std.clamp_min(0.05))
    assert (plan.trusted_steps < h).any() and (plan.trusted_steps == h).any()
    assert torch.equal(plan.best, plan.returns.argmax(-1))
    # the written action, horizon and disagreement are over all rounds' candidates
    rollouts.clear()
    torch.manual_seed(7)
    out = planner(td.clone())
    torch.testing.assert_close(out["action"], plan.action)
    expected_h = plan.trusted_steps.gather(-1, plan.best[:, None]).float()
    torch.testing.assert_close(out["planner", "effective_horizon"], expected_h)
    disagreement = torch.cat([o.disagreement for o in rollouts], dim=-2)
    torch.testing.assert_close(out["planner", "disagreement"], disagreement.mean((-2, -1))[:, None])


def test_planner_rejects_bad_settings(cheetah, policy):
    model = EnsembleDeltaDynamicsModel(18, 6, num_members=2, hidden_sizes=(8,))
    env = LearnedDynamicsEnv(model, cheetah)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="disagreement_threshold must be > 0"):
            EnsemblePolicyGuidedPlanner(env, policy, disagreement_threshold=bad)
    with pytest.raises(TypeError, match="disagreement_threshold must be a float"):
        EnsemblePolicyGuidedPlanner(env, policy, disagreement_threshold="0.1")
    single = LearnedDynamicsEnv(DeltaDynamicsModel(18, 6, hidden_sizes=(8,)), cheetah)
    with pytest.raises(TypeError, match="LearnedDynamicsEnv on an EnsembleDeltaDynamicsModel"):
        EnsemblePolicyGuidedPlanner(single, policy)


def test_planner_in_a_collector_on_pendulum():
    torch.manual_seed(0)
    real = make_env("Pendulum-v1", seed=0)
    data = collect_random_transitions(real, 600, seed=0)
    model = EnsembleDeltaDynamicsModel(3, 1, num_members=3, hidden_sizes=(64, 64))
    fit_ensemble(model, data, lr=1e-3, batch_size=64, max_epochs=8, seed=0)
    held = collect_random_transitions(make_env("Pendulum-v1", seed=1), 200, seed=1).tensors()
    cal = calibrate_disagreement_threshold(
        model, held["state"], held["action"], held["next", "state"], quantile=0.9
    )
    actor, critic = make_ppo_actor_critic(real, hidden_sizes=(16, 16))
    planner = EnsemblePolicyGuidedPlanner(
        EnsembleLearnedDynamicsEnv(model, real),
        actor,
        disagreement_threshold=cal.threshold,
        value_module=critic,
        num_candidates=15,
        horizon=10,
    )
    collector = Collector(
        real, planner, frames_per_batch=60, total_frames=60, auto_register_policy_transforms=False
    )
    batch = next(iter(collector))
    collector.shutdown()
    assert batch.numel() == 60
    horizon = batch["planner", "effective_horizon"]
    assert horizon.shape == (60, 1)
    assert ((horizon >= 0) & (horizon <= 10) & (horizon == horizon.round())).all()
    assert (batch["planner", "disagreement"] >= 0).all()
    assert batch["action"].abs().max() <= 2.0
    torch.testing.assert_close(
        actor.get_dist(batch).log_prob(batch["action"]), batch["action_log_prob"]
    )


def test_ensemble_hidden_sizes_are_checked():
    with pytest.raises(ValueError, match=r"hidden_sizes must be a sequence of integers >= 1"):
        EnsembleDeltaDynamicsModel(3, 1, num_members=2, hidden_sizes=(0,))
