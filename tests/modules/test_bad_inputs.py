"""Modules refuse bad arguments and inputs by name, before any work (issue 33)."""

from __future__ import annotations

import pytest
import torch

from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
from torchrl_mbmf.modules import (
    DeltaDynamicsModel,
    PolicyGuidedMPCPlanner,
    RandomShootingMPCPlanner,
    make_ppo_actor_critic,
)


@pytest.mark.parametrize(
    ("args", "kwargs", "message"),
    [
        (("3", 1), {}, "state_dim must be an integer >= 1, got '3'"),
        ((3, 2.5), {}, "action_dim must be an integer >= 1, got 2.5"),
        (
            (3, 1),
            {"action_low": float("nan"), "action_high": 1.0},
            "action_low must be a number or None",
        ),
        ((3, 1), {"action_high": "2"}, "action_high must be a number or None"),
    ],
)
def test_dynamics_model_arguments(args, kwargs, message):
    with pytest.raises(ValueError, match=message):
        DeltaDynamicsModel(*args, **kwargs)


def test_dynamics_model_inputs_of_another_shape_or_dtype():
    model = DeltaDynamicsModel(3, 1, hidden_sizes=(8,))
    s, a, r = torch.zeros(5, 3), torch.zeros(5, 1), torch.zeros(5, 1)
    with pytest.raises(ValueError, match=r"next_state \(5, 4\) must have the state's shape"):
        model.fit_normalizer(s, a, torch.zeros(5, 4), r)
    with pytest.raises(ValueError, match=r"reward \(4, 1\) one value per transition"):
        model.fit_normalizer(s, a, s, torch.zeros(4, 1))
    with pytest.raises(ValueError, match=r"state is torch\.float64, the model is torch\.float32"):
        model(s.double(), a.double())
    # a float32 input to a float64 model is promoted, as before
    assert model.double()(s, a)[0].dtype == torch.float64


def test_learned_env_needs_the_real_env():
    with pytest.raises(TypeError, match="env must be the real TorchRL env"):
        LearnedDynamicsEnv(DeltaDynamicsModel(3, 1), None)


@pytest.fixture(scope="module")
def pendulum():
    real = make_gym_state_env("Pendulum-v1", seed=0)
    env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), real)
    actor, _ = make_ppo_actor_critic(real, hidden_sizes=(8,))
    return real, env, actor


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"refinement": "mppi", "temperature": float("nan")}, "temperature must be a finite"),
        ({"refinement": "mppi", "temperature": 0.0}, "temperature must be > 0"),
        ({"refinement": "cem", "min_std": float("nan")}, "min_std must be a finite"),
        ({"refinement": "cem", "num_elites": 2.5}, "num_elites must be an integer in"),
    ],
)
def test_refinement_settings(pendulum, kwargs, message):
    _, env, actor = pendulum
    with pytest.raises(ValueError, match=message):
        PolicyGuidedMPCPlanner(env, actor, num_candidates=5, horizon=3, **kwargs)


@pytest.mark.parametrize("guided", [True, False])
def test_planners_refuse_a_nan_or_missing_state(pendulum, guided):
    real, env, actor = pendulum
    planner = (
        PolicyGuidedMPCPlanner(env, actor, num_candidates=5, horizon=3)
        if guided
        else RandomShootingMPCPlanner(env, num_candidates=5, horizon=3)
    )
    td = real.reset()
    bad = td.clone()
    bad["state"][0] = float("nan")
    with pytest.raises(ValueError, match="got a NaN or Inf 'state'"):
        planner(bad)
    with pytest.raises(KeyError, match="plans from 'state', which its input lacks"):
        planner(td.exclude("state"))
    assert torch.isfinite(planner(td)["action"]).all()
