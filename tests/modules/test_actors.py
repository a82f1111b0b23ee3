from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import ClipPPOLoss, SACLoss

from torchrl_mbmf.envs import make_half_cheetah_env
from torchrl_mbmf.modules import make_ppo_actor_critic, make_sac_actor_critic


@pytest.fixture(scope="module")
def env():
    return make_half_cheetah_env(seed=0)


@pytest.mark.parametrize("distribution", ["tanh_normal", "normal"])
def test_ppo_actor_critic_sizes_and_keys(env, distribution):
    actor, critic = make_ppo_actor_critic(env, distribution=distribution, init_log_std=-0.5)
    linears = [m for m in actor.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(17, 64), (64, 64), (64, 6)]
    td = critic(actor(env.reset()))
    assert td["action"].shape == (6,)
    assert td["state_value"].shape == (1,)
    torch.testing.assert_close(td["scale"], torch.full((6,), float(torch.tensor(-0.5).exp())))
    dist = actor.get_dist(td)
    torch.testing.assert_close(td["action_log_prob"], dist.log_prob(td["action"]))
    if distribution == "tanh_normal":
        assert (td["action"].abs() <= 1).all()
    else:
        assert (td["loc"].abs() <= 1).all()  # tanh-squashed mean (thesis table 5)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        a1 = actor(env.reset())["action"]
    assert a1.shape == (6,)


def test_ppo_loss_runs_on_rollout(env):
    actor, critic = make_ppo_actor_critic(env)
    with torch.no_grad():
        td = env.rollout(16, actor)
    loss = ClipPPOLoss(actor, critic, entropy_coeff=1e-4, critic_coeff=0.5)
    loss.make_value_estimator(gamma=0.99, lmbda=0.95)
    out = loss(td)
    (out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]).backward()


def test_sac_actor_qvalue(env):
    actor, qvalue = make_sac_actor_critic(env, hidden_sizes=(32, 32))
    td = env.rollout(8, actor)
    assert (td["action"].abs() <= 1).all()
    loss = SACLoss(actor, qvalue, num_qvalue_nets=2, action_spec=env.action_spec)
    loss.make_value_estimator(gamma=0.99)
    out = loss(td)
    (out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]).backward()


def test_errors(env):
    with pytest.raises(ValueError, match="distribution"):
        make_ppo_actor_critic(env, distribution="beta")
    with pytest.raises(KeyError, match="'pixels'"):
        make_ppo_actor_critic(env, observation_key="pixels")


@pytest.mark.parametrize("make", [make_ppo_actor_critic, make_sac_actor_critic])
def test_hidden_sizes_are_checked(make):
    env = make_half_cheetah_env("default")
    with pytest.raises(ValueError, match=r"hidden_sizes must be a sequence of integers >= 1"):
        make(env, hidden_sizes=(0,))
