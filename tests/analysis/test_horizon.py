from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from torchrl_mbmf.analysis import horizon_predictions, horizon_table, multistep_mse
from torchrl_mbmf.data import TransitionDataset, collect_random_transitions
from torchrl_mbmf.envs import make_env, make_gym_state_env
from torchrl_mbmf.modules import DeltaDynamicsModel


def _dataset_and_model():
    """Real system: x' = x + a, r = 2a. Model: the same plus a constant bias of 0.1 on delta x."""
    steps = 40
    a = torch.linspace(-1, 1, steps)[:, None]
    x = torch.cat([torch.zeros(1, 1), a.cumsum(0)])
    state = torch.cat([x, torch.zeros(steps + 1, 1)], -1)  # [x, 0]
    done = torch.zeros(steps, 1, dtype=torch.bool)
    done[-1] = True
    batch = TensorDict(
        state=state[:-1],
        action=a,
        next=TensorDict(state=state[1:], reward=2 * a, done=done, batch_size=[steps]),
        batch_size=[steps],
    )
    data = TransitionDataset({"env_id": "Mock-v0", "reward": {"name": "default"}})
    data.extend(batch)
    model = DeltaDynamicsModel(2, 1, hidden_sizes=(4,))
    # make the network output zero; put the dynamics in the scaler: delta = a*scale... exact:
    # with zero weights the scaled output is 0, so delta = delta_loc and reward = reward_loc.
    for p in model.parameters():
        torch.nn.init.zeros_(p)
    model.delta_loc.copy_(torch.tensor([0.1, 0.0]))
    model.reward_loc.fill_(0.5)
    return data, model, x[:, 0], a[:, 0]


def test_multistep_mse_brute_force():
    data, model, x, a = _dataset_and_model()
    errors = multistep_mse(model, data, horizons=(1, 3, 5), num_starts=None, x_index=0)
    assert [e.horizon for e in errors] == [1, 3, 5]
    # brute force: start at every t with 5 steps ahead; prediction x_t + 0.1 k, reward 0.5
    n = 40
    starts = range(n - 5 + 1)
    for e in errors:
        h = e.horizon
        xs, rs = [], []
        for t in starts:
            for k in range(1, h + 1):
                xs.append((x[t] + 0.1 * k - x[t + k]) ** 2)
                rs.append((0.5 - 2 * a[t + k - 1]) ** 2)
        assert e.num_rollouts == len(starts)
        assert e.x_mse == pytest.approx(float(torch.stack(xs).mean()), rel=1e-5)
        assert e.reward_mse == pytest.approx(float(torch.stack(rs).mean()), rel=1e-5)
        assert len(e.state_mse) == 2
        assert e.state_mse[0] == pytest.approx(e.x_mse, rel=1e-6)
    assert errors[0].x_mse_final == pytest.approx(errors[0].x_mse)


def test_predictions_and_table():
    data, model, _, _ = _dataset_and_model()
    out = horizon_predictions(model, data, 4, num_rollouts=3, seed=0, x_index=0)
    assert out["x_pred"].shape == out["x_real"].shape == (3, 4)
    torch.testing.assert_close(
        out["x_pred"], out["x_start"][:, None] + 0.1 * torch.arange(1, 5).float()
    )
    errors = multistep_mse(model, data, horizons=(5, 10), x_index=0)
    table = horizon_table(errors)
    assert "| 10 |" in table and "2.489" in table


def test_errors():
    data, model, _, _ = _dataset_and_model()
    with pytest.raises(ValueError, match="horizons must be >= 1"):
        multistep_mse(model, data, horizons=(0, 5))
    with pytest.raises(ValueError, match="100 consecutive steps"):
        multistep_mse(model, data, horizons=(100,))
    with pytest.raises(ValueError, match="horizon must be >= 1"):
        horizon_predictions(model, data, 0)
    for bad in (-1, "x", 1.0, True):
        with pytest.raises(ValueError, match=f"x_index must be a state index.*got {bad!r}"):
            multistep_mse(model, data, horizons=(5,), x_index=bad)
    with pytest.raises(ValueError, match="x_index=2 is not an index of the 2-dim state"):
        multistep_mse(model, data, horizons=(5,), x_index=2)
    # the mock task has no known layout: no x position to plot, the rewards only
    assert sorted(horizon_predictions(model, data, 3)) == ["reward_pred", "reward_real"]


@pytest.mark.parametrize(
    ("build", "x_index"),
    [
        (lambda: make_env("Hopper-v5"), 0),  # x first; dim 1 is the height
        (lambda: make_gym_state_env("Hopper-v5", layout=False), None),  # no x in it
        (lambda: make_env("Pendulum-v1"), None),
        (lambda: make_env("MountainCarContinuous-v0"), None),  # no known layout
    ],
)
def test_x_index_is_the_tasks(build, x_index):
    """The x errors read the task's x where its state has one, and are None elsewhere."""
    env = build()
    data = collect_random_transitions(env, 60, seed=0)
    state_dim = env.full_observation_spec_unbatched["state"].shape[-1]
    action_dim = env.full_action_spec_unbatched["action"].shape[-1]
    model = DeltaDynamicsModel(state_dim, action_dim, hidden_sizes=(8,))
    errors = multistep_mse(model, data, horizons=(1, 5), num_starts=None)
    for e in errors:
        if x_index is None:
            assert e.x_mse is None and e.x_mse_final is None
        else:
            assert e.x_mse == pytest.approx(e.state_mse[x_index], rel=1e-6)
    assert ("n/a" in horizon_table(errors).splitlines()[-1]) == (x_index is None)
    # an explicit index always wins over the task's
    (dim1,) = multistep_mse(model, data, horizons=(5,), num_starts=None, x_index=1)
    assert dim1.x_mse == pytest.approx(dim1.state_mse[1], rel=1e-6)


def test_rollouts_never_cross_an_unflagged_reset():
    # Two batches of one env; a new collector resets the env between them without a done flag,
    # so the dataset keeps one trajectory id across both. An open-loop window that crossed the
    # reset would compare the model with a jump in x the model cannot know about.
    def batch(x0: float, steps: int) -> TensorDict:
        x = x0 + torch.arange(steps + 1, dtype=torch.float32)[:, None]  # x' = x + a, a = 1
        state = torch.cat([x, torch.zeros_like(x)], -1)
        return TensorDict(
            state=state[:-1],
            action=torch.ones(steps, 1),
            next=TensorDict(
                state=state[1:],
                reward=torch.full((steps, 1), 2.0),
                done=torch.zeros(steps, 1, dtype=torch.bool),
                batch_size=[steps],
            ),
            batch_size=[steps],
        )

    data = TransitionDataset({"env_id": "Mock-v0", "reward": {"name": "default"}})
    data.extend(batch(0.0, 6))
    data.extend(batch(100.0, 6))
    assert len(data.trajectories()) == 1  # the ids alone join the two episodes
    model = DeltaDynamicsModel(2, 1, hidden_sizes=(4,))
    for p in model.parameters():
        torch.nn.init.zeros_(p)
    model.delta_loc.copy_(torch.tensor([1.0, 0.0]))  # the exact dynamics
    model.reward_loc.fill_(2.0)
    (err,) = multistep_mse(model, data, horizons=(3,), num_starts=None, x_index=0)
    assert err.num_rollouts == 2 * (6 - 3 + 1)
    assert err.x_mse == 0.0 and err.reward_mse == 0.0
    out = horizon_predictions(model, data, 3, num_rollouts=8, seed=1, x_index=0)
    torch.testing.assert_close(out["x_pred"], out["x_real"])
