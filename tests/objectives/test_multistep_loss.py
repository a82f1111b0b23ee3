"""Multi-step world-model loss: episode windows, the k-step rollout term and its gradients."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torchrl_mbmf.data import TransitionDataset
from torchrl_mbmf.data.transitions import consecutive_windows
from torchrl_mbmf.modules import DeltaDynamicsModel
from torchrl_mbmf.objectives import DynamicsLoss, MultiStepDynamicsLoss

META = {"env_id": "Mock-v0", "reward": {"name": "default"}}


def _batch(n_envs, steps, done_at=(), start=0.0):
    """Transitions whose state encodes (env, step): env e at step t has state t + 1000 e."""
    t = torch.arange(steps, dtype=torch.float32) + start
    state = torch.stack([t + 1000 * e for e in range(n_envs)])[..., None].expand(-1, -1, 3)
    done = torch.zeros(n_envs, steps, 1, dtype=torch.bool)
    for e, k in done_at:
        done[e, k] = True
    return TensorDict(
        state=state.clone(),
        action=torch.zeros(n_envs, steps, 1),
        next=TensorDict(
            state=state + 1,
            reward=torch.ones(n_envs, steps, 1),
            done=done,
            batch_size=[n_envs, steps],
        ),
        batch_size=[n_envs, steps],
    )


# The real episodes of _dataset(), as state values in time order.
EPISODES = [
    [0, 1, 2],  # env 0, done at t=2
    [3, 4, 5, 6, 7],  # continues into the second batch, done at t=7
    [8, 9],  # not done at the end of batch 2, but the env is reset before batch 3
    [100, 101, 102, 103],
    [1000, 1001, 1002, 1003, 1004, 1005],  # env 1, done on batch 1's last step
    [1006, 1007, 1008, 1009],  # reset before batch 3 without a done
    [1100, 1101, 1102, 1103],
]


def _dataset():
    data = TransitionDataset(META)
    data.extend(_batch(2, 6, done_at=[(0, 2), (1, 5)]))
    data.extend(_batch(2, 4, done_at=[(0, 1)], start=6.0))
    # A new collector resets its env without a done flag: batch 3 does not continue batch 2.
    data.extend(_batch(2, 4, start=100.0))
    return data


@pytest.mark.parametrize("length", [1, 2, 3, 5])
def test_windows_never_cross_an_episode_boundary(length):
    data = _dataset()
    td = data.tensors()
    windows = data.windows(length)
    state = td["state"][:, 0]
    got = sorted(state[w].tolist() for w in windows)
    expected = sorted(
        [float(v) for v in ep[i : i + length]]
        for ep in EPISODES
        for i in range(len(ep) - length + 1)
    )
    assert got == expected
    # what the windows rely on: one trajectory id, no done before the last step, and each
    # step's next state is the following step's state
    assert (td["traj_id"][windows] == td["traj_id"][windows[:, :1]]).all()
    assert not td["next", "done"][windows[:, :-1]].any()
    torch.testing.assert_close(td["next", "state"][windows[:, :-1]], td["state"][windows[:, 1:]])


def test_trajectory_ids_alone_would_join_a_reset():
    # TransitionDataset keeps an episode id open across extend calls unless the step was
    # done, so ids join [8, 9] with the reset episode [100..103]; the windows do not.
    data = _dataset()
    state = data.tensors()["state"][:, 0]
    joined = [state[idx].tolist() for idx in data.trajectories()]
    assert [8.0, 9.0, 100.0, 101.0, 102.0, 103.0] in joined
    assert not any({9.0, 100.0} <= set(w) for w in state[data.windows(2)].tolist())


def test_consecutive_windows_of_a_short_or_empty_episode():
    state = torch.arange(4.0)[:, None]
    done = torch.tensor([True, True, True, True])
    assert consecutive_windows(torch.arange(4), done, state, state + 1, 2).shape == (0, 2)
    assert consecutive_windows(torch.zeros(1), done[:1], state[:1], state[:1], 3).shape == (0, 3)
    with pytest.raises(ValueError, match="window length must be >= 1"):
        consecutive_windows(torch.zeros(4), done, state, state + 1, 0)


def _transitions(n=32, k=4, seed=0):
    """Random windows [n, k] and a model whose scaler is fitted on them."""
    g = torch.Generator().manual_seed(seed)
    s = torch.randn(n, k + 1, 4, generator=g).cumsum(1)
    a = torch.rand(n, k, 2, generator=g) * 4 - 2  # partly outside [-1, 1]: the model clips
    r = torch.randn(n, k, 1, generator=g)
    windows = TensorDict(
        state=s[:, :-1],
        action=a,
        next=TensorDict(state=s[:, 1:].clone(), reward=r, batch_size=[n, k]),
        batch_size=[n, k],
    )
    torch.manual_seed(seed)
    model = DeltaDynamicsModel(4, 2, hidden_sizes=(16,))
    flat = windows.reshape(-1)
    model.fit_normalizer(
        flat["state"], flat["action"], flat["next", "state"], flat["next", "reward"]
    )
    return model, windows


def _rollout_args(windows):
    return (
        windows["state"][:, 0],
        windows["action"],
        windows["next", "state"],
        windows["next", "reward"],
    )


def test_k1_multi_step_term_is_the_one_step_loss():
    model, windows = _transitions(k=1)
    loss = DynamicsLoss(model)
    one_step = loss(windows[:, 0])["loss_dynamics"]
    torch.testing.assert_close(loss.multi_step_loss(*_rollout_args(windows)), one_step)
    # and step 1 of a longer rollout is the one-step error of the window's first transition
    model, windows = _transitions(k=4)
    loss = DynamicsLoss(model)
    errors = loss.rollout_squared_errors(*_rollout_args(windows))
    first = windows[:, 0]
    torch.testing.assert_close(
        errors[:, 0],
        loss.squared_errors(
            first["state"], first["action"], first["next", "state"], first["next", "reward"]
        ),
    )


def _scalar_linear_model():
    """s' = s + (0.5 s + a + 0.1), r = 2 s - a: a linear model, identity scaling, float64."""
    model = DeltaDynamicsModel(1, 1, hidden_sizes=()).double()
    with torch.no_grad():
        model.net[0].weight.copy_(torch.tensor([[0.5, 1.0], [2.0, -1.0]], dtype=torch.float64))
        model.net[0].bias.copy_(torch.tensor([0.1, 0.0], dtype=torch.float64))
    return model


def _scalar_window():
    s0 = torch.tensor([[1.0]], dtype=torch.float64)
    actions = torch.tensor([[[0.5], [-0.5]]], dtype=torch.float64)
    next_states = torch.tensor([[[2.0], [3.0]]], dtype=torch.float64)
    rewards = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
    return s0, actions, next_states, rewards


def test_k_step_loss_equals_a_hand_computed_rollout():
    # By hand: s1 = 1 + 0.5 + 0.5 + 0.1 = 2.1, r0 = 2 - 0.5 = 1.5;
    # s2 = 2.1 + 1.05 - 0.5 + 0.1 = 2.75, r1 = 4.2 + 0.5 = 4.7;
    # loss = mean((2.1 - 2)^2, (1.5 - 1)^2, (2.75 - 3)^2, (4.7 - 2)^2) = 7.6125 / 4.
    loss = DynamicsLoss(_scalar_linear_model())
    value = loss.multi_step_loss(*_scalar_window())
    assert value.item() == pytest.approx(7.6125 / 4, abs=1e-12)


def test_k_step_loss_equals_a_scaled_linear_rollout_by_hand():
    torch.manual_seed(1)
    model = DeltaDynamicsModel(4, 2, hidden_sizes=(), action_low=-1.0, action_high=1.0)
    _, windows = _transitions(k=3, seed=2)
    flat = windows.reshape(-1)
    model.fit_normalizer(
        flat["state"], flat["action"], flat["next", "state"], flat["next", "reward"]
    )
    w, b = model.net[0].weight, model.net[0].bias
    s = windows["state"][:, 0]
    errors = []
    for t in range(3):
        a = windows["action"][:, t].clamp(-1, 1)
        x = torch.cat(
            [
                (s - model.state_loc) / model.state_scale,
                (a - model.action_loc) / model.action_scale,
            ],
            -1,
        )
        y = x @ w.T + b
        s = s + y[:, :4] * model.delta_scale + model.delta_loc
        state_err = (s - windows["next", "state"][:, t]) / model.delta_scale
        reward_err = y[:, 4:] - (windows["next", "reward"][:, t] - model.reward_loc) / (
            model.reward_scale
        )
        errors.append(torch.cat([state_err, reward_err], -1).pow(2))
    expected = torch.stack(errors, 1).mean()
    torch.testing.assert_close(
        DynamicsLoss(model).multi_step_loss(*_rollout_args(windows)), expected
    )


def test_gradients_flow_through_the_rollout():
    model = _scalar_linear_model()
    DynamicsLoss(model).multi_step_loss(*_scalar_window()).backward()
    # dL/dw_s = 0.5 [(s1 - S1) ds1 + (s2 - S2) ds2 + (r1 - R1) dr1] with ds1 = s0 = 1,
    # ds2 = s1 + (1 + w_s) ds1 = 3.6 and dr1 = v_s ds1 = 2: 0.5 (0.1 - 0.9 + 5.4) = 2.3.
    # Had the rollout been cut (s1 detached), it would be 0.5 (0.1 - 0.25 * 2.1) = -0.2125.
    assert model.net[0].weight.grad[0, 0].item() == pytest.approx(2.3, abs=1e-12)
    # and central finite differences of the whole k-step loss of a small MLP
    torch.manual_seed(0)
    mlp = DeltaDynamicsModel(3, 1, hidden_sizes=(5,), activation=torch.nn.Tanh).double()
    loss = DynamicsLoss(mlp)
    g = torch.Generator().manual_seed(0)
    args = (
        torch.randn(4, 3, generator=g, dtype=torch.float64),
        torch.rand(4, 3, 1, generator=g, dtype=torch.float64) - 0.5,
        torch.randn(4, 3, 3, generator=g, dtype=torch.float64),
        torch.randn(4, 3, generator=g, dtype=torch.float64),
    )
    params = list(mlp.parameters())
    grads = torch.autograd.grad(loss.multi_step_loss(*args), params)
    eps = 1e-6
    with torch.no_grad():
        for p, grad in zip(params, grads, strict=True):
            for j in range(min(4, p.numel())):
                p.view(-1)[j] += eps
                up = loss.multi_step_loss(*args).item()
                p.view(-1)[j] -= 2 * eps
                down = loss.multi_step_loss(*args).item()
                p.view(-1)[j] += eps
                assert (up - down) / (2 * eps) == pytest.approx(grad.view(-1)[j].item(), abs=1e-7)


def test_multi_step_loss_module():
    model, windows = _transitions(k=4)
    loss = MultiStepDynamicsLoss(model, multi_step_weight=0.5)
    out = loss(windows)
    assert set(out.keys()) == set(loss.out_keys)
    one_step = DynamicsLoss(model)(windows)["loss_dynamics"]
    multi = DynamicsLoss(model).multi_step_loss(*_rollout_args(windows))
    torch.testing.assert_close(out["loss_one_step"], one_step.detach())
    torch.testing.assert_close(out["loss_multi_step"], multi.detach())
    torch.testing.assert_close(out["loss_dynamics"], one_step + 0.5 * multi)
    out["loss_dynamics"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())
    with pytest.raises(ValueError, match=r"\[\.\.\., k\] windows"):
        loss(windows[:, 0])
    with pytest.raises(ValueError, match="multi_step_weight must be a finite number >= 0"):
        MultiStepDynamicsLoss(model, multi_step_weight=-1.0)
