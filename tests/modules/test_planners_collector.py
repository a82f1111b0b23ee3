"""Planners as TorchRL policies: Collector, ClipPPOLoss (GAE), replay buffer + SACLoss."""

from __future__ import annotations

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.objectives import ClipPPOLoss, SACLoss
from torchrl.objectives.value import GAE

from torchrl_mbmf.data import collect_random_transitions
from torchrl_mbmf.envs import LearnedDynamicsEnv, make_env, make_half_cheetah_env
from torchrl_mbmf.modules import (
    DeltaDynamicsModel,
    PolicyGuidedMPCPlanner,
    RandomShootingMPCPlanner,
    make_ppo_actor_critic,
    make_sac_actor_critic,
)
from torchrl_mbmf.world_model import fit_dynamics


def _collect(env, policy, frames):
    collector = Collector(
        env,
        policy,
        frames_per_batch=frames,
        total_frames=frames,
        auto_register_policy_transforms=False,
    )
    batch = next(iter(collector))
    collector.shutdown()
    return batch


@pytest.mark.parametrize("num_envs", [1, 8])
def test_ppo_mpc_batch_feeds_clip_ppo_loss(num_envs):
    real = make_half_cheetah_env(num_envs=num_envs, seed=0)
    actor, critic = make_ppo_actor_critic(real)
    model_env = LearnedDynamicsEnv(DeltaDynamicsModel(18, 6, hidden_sizes=(32,)), real)
    planner = PolicyGuidedMPCPlanner(model_env, actor, num_candidates=5, horizon=3)
    batch = _collect(real, planner, 16)
    assert batch.numel() == 16
    assert batch["action_log_prob"].shape == batch.batch_size
    assert not batch["action_log_prob"].requires_grad
    gae = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=False)
    loss = ClipPPOLoss(actor, critic, entropy_coeff=1e-4, critic_coeff=0.5)
    with torch.no_grad():
        gae(batch)
    out = loss(batch.reshape(-1))
    total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
    total.backward()
    assert all(p.grad is not None for p in actor.parameters())
    # the importance ratio starts at 1: the log-prob written is the actor's own at that state
    torch.testing.assert_close(
        actor.get_dist(batch.reshape(-1)).log_prob(batch.reshape(-1)["action"]),
        batch.reshape(-1)["action_log_prob"],
    )


def test_mpc_batch_and_sac_replay_buffer():
    real = make_half_cheetah_env(num_envs=2, seed=1)
    actor, qvalue = make_sac_actor_critic(real, hidden_sizes=(32, 32))
    model_env = LearnedDynamicsEnv(DeltaDynamicsModel(18, 6, hidden_sizes=(32,)), real)
    for planner in (
        PolicyGuidedMPCPlanner(model_env, actor, num_candidates=4, horizon=2),
        RandomShootingMPCPlanner(model_env, num_candidates=4, horizon=2),
    ):
        batch = _collect(real, planner, 12)
        rb = TensorDictReplayBuffer(storage=LazyTensorStorage(100), batch_size=8)
        rb.extend(batch.reshape(-1))
        loss = SACLoss(actor, qvalue, num_qvalue_nets=2, action_spec=real.action_spec)
        loss.make_value_estimator(gamma=0.99)
        out = loss(rb.sample())
        (out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]).backward()


@pytest.fixture(scope="module")
def pendulum_model():
    """A small model fitted on random Pendulum data (shared by the full-stack tests)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    real = make_env("Pendulum-v1", seed=0)
    data = collect_random_transitions(real, 600, seed=0)
    model = DeltaDynamicsModel(3, 1, hidden_sizes=(64, 64))
    history = fit_dynamics(model, data, lr=1e-3, batch_size=64, max_epochs=15, seed=0)
    torch.set_num_threads(threads)
    assert history.best_val_loss < 0.5
    return real, data, model


@pytest.mark.parametrize("planner_cls", [PolicyGuidedMPCPlanner, RandomShootingMPCPlanner])
def test_pendulum_full_stack(pendulum_model, planner_cls):
    """Fit a model on random Pendulum data, plan with it, collect real steps."""
    real, data, model = pendulum_model
    torch.manual_seed(0)
    actor, _ = make_ppo_actor_critic(real, hidden_sizes=(16, 16))
    model_env = LearnedDynamicsEnv(model, real)
    if planner_cls is PolicyGuidedMPCPlanner:
        planner = planner_cls(model_env, actor, num_candidates=15, horizon=10)
    else:
        planner = planner_cls(model_env, num_candidates=64, horizon=10, actor=actor)
    batch = _collect(real, planner, 200)
    assert batch["action"].abs().max() <= 2.0
    assert torch.isfinite(batch["action_log_prob"]).all()
    if planner_cls is RandomShootingMPCPlanner:
        # a fitted model plus many candidates beats random actions on the real reward
        random_return = data.tensors()["next", "reward"][:200].mean()
        assert batch["next", "reward"].mean() > random_return
