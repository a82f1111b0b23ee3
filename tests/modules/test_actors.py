from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import ClipPPOLoss, SACLoss

from torchrl_mbmf.envs import make_half_cheetah_env
from torchrl_mbmf.modules import make_ppo_actor_critic, make_sac_actor_critic
from torchrl_mbmf.modules.log_std import LOG_STD_BOUNDS, ClampedLogStdExtractor


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


def test_sac_scale_parameterisations(env):
    """``clamped_log_std`` maps a log-std through SB3's clamp; the default is torchrl's."""
    torch.manual_seed(0)
    default, _ = make_sac_actor_critic(env, hidden_sizes=(8,))
    torch.manual_seed(0)
    clamped, _ = make_sac_actor_critic(env, hidden_sizes=(8,), scale="clamped_log_std")
    net_default, net_clamped = default.module[0].module, clamped.module[0].module
    obs = torch.ones(17)
    torch.testing.assert_close(net_default[0](obs), net_clamped[0](obs))  # same MLP
    log_std = torch.tensor([-25.0, -3.0, 0.0, 1.5, 2.5, 9.0])
    raw = torch.cat([torch.linspace(-1, 1, 6), log_std])  # loc | log-std (6 actions)
    loc, scale = net_clamped[1](raw)
    torch.testing.assert_close(loc, raw[:6])
    torch.testing.assert_close(scale, log_std.clamp(-20.0, 2.0).exp())
    _, softplus_scale = net_default[1](raw)
    torch.testing.assert_close(softplus_scale[2], torch.tensor(1.0))  # both give 1 at 0
    assert softplus_scale[5] > 8.0  # unbounded above, where the clamp stops at e^2
    td = clamped(env.reset())
    assert (td["scale"] <= torch.tensor(2.0).exp()).all() and td["action"].shape == (6,)
    with pytest.raises(ValueError, match=r"scale='exp' is not a SAC actor scale"):
        make_sac_actor_critic(env, scale="exp")


def test_clamped_log_std_bounds_are_sb3s():
    sb3 = pytest.importorskip("stable_baselines3.sac.policies")
    assert LOG_STD_BOUNDS == (sb3.LOG_STD_MIN, sb3.LOG_STD_MAX)
    with pytest.raises(ValueError, match=r"low < high, got \(2.0, -20.0\)"):
        ClampedLogStdExtractor(2.0, -20.0)
