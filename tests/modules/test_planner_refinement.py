"""CEM/MPPI refinement around the policy prior, and the SAC min-Q terminal value."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torchrl.objectives import SACLoss

from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env, make_half_cheetah_env
from torchrl_mbmf.modules import (
    DeltaDynamicsModel,
    PolicyGuidedMPCPlanner,
    make_ppo_actor_critic,
    make_sac_actor_critic,
)
from torchrl_mbmf.modules.planners import MinQValue

C = torch.tensor([1.0, -2.0, 0.5, 3.0, -1.0, 2.0])


def closed_form_env(real):
    """Learned env with s' = s + [0, a, 0...] and r = C . a, exactly (identity scaling)."""
    model = DeltaDynamicsModel(18, 6, hidden_sizes=())
    w = torch.zeros(19, 24)
    w[1:7, 18:24] = torch.eye(6)
    w[18, 18:24] = C
    with torch.no_grad():
        model.net[0].weight.copy_(w)
        model.net[0].bias.zero_()
    return LearnedDynamicsEnv(model, real)


@pytest.fixture(scope="module")
def real():
    return make_half_cheetah_env(seed=0)


@pytest.fixture(scope="module")
def policy(real):
    torch.manual_seed(0)
    return make_ppo_actor_critic(real, init_log_std=-0.5)[0]


@pytest.mark.parametrize("refinement", ["cem", "mppi"])
def test_refinement_keeps_the_policy_round_and_improves_the_best(real, policy, refinement):
    env = closed_form_env(real)
    td = make_half_cheetah_env(num_envs=4, seed=1).reset()
    plain = PolicyGuidedMPCPlanner(env, policy, num_candidates=15, horizon=5)
    refined = PolicyGuidedMPCPlanner(
        env, policy, num_candidates=15, horizon=5, refinement=refinement, iterations=4
    )
    torch.manual_seed(0)
    p0 = plain.plan(td.clone())
    torch.manual_seed(0)
    p1 = refined.plan(td.clone())
    # The first round is the thesis' policy round, drawn identically.
    torch.testing.assert_close(p1.returns[..., :15], p0.returns)
    assert p1.returns.shape == (4, 15 * 5)
    assert (p1.returns.amax(-1) >= p0.returns.amax(-1)).all()
    # The optimum of r = C . a is a = sign(C) at every step (return 9.5 per step): the refined
    # rounds get closer to it than the policy's samples.
    assert (p1.returns.amax(-1) > p0.returns.amax(-1)).all()
    # The executed action is the first action of the best candidate over all rounds.
    torch.testing.assert_close(p1.action, p1.first_actions[torch.arange(4), p1.returns.argmax(-1)])


def test_refined_action_and_log_prob_written_as_before(real, policy):
    env = closed_form_env(real)
    planner = PolicyGuidedMPCPlanner(env, policy, refinement="cem", iterations=2)
    td = make_half_cheetah_env(num_envs=3, seed=2).reset()
    out = planner(td.clone())
    assert real.action_spec.is_in(out["action"][0])
    dist = policy.get_dist(td.clone())
    torch.testing.assert_close(out["action_log_prob"], dist.log_prob(out["action"]))


def test_cem_and_mppi_refit(real, policy):
    env = closed_form_env(real)
    cem = PolicyGuidedMPCPlanner(
        env, policy, num_candidates=4, horizon=1, refinement="cem", num_elites=2, min_std=0.0
    )
    actions = torch.tensor([[[[0.0]], [[1.0]], [[2.0]], [[3.0]]]]).expand(1, 4, 1, 6)
    returns = torch.tensor([[0.0, 5.0, 1.0, 4.0]])
    mean, std = cem._refit(actions, returns)
    torch.testing.assert_close(mean, torch.full((1, 1, 6), 2.0))  # elites 1.0 and 3.0
    torch.testing.assert_close(std, torch.full((1, 1, 6), 1.0))
    mppi = PolicyGuidedMPCPlanner(
        env, policy, num_candidates=4, horizon=1, refinement="mppi", temperature=0.5
    )
    mean, _ = mppi._refit(actions, returns)
    z = (returns - returns.max()) / (0.5 * returns.std())
    w = torch.softmax(z, -1)
    torch.testing.assert_close(mean[0, 0, 0], (w * torch.tensor([0.0, 1.0, 2.0, 3.0])).sum())


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"refinement": "icem"}, "refinement=.icem. is not supported"),
        ({"refinement": "cem", "iterations": 0}, "iterations must be"),
        ({"refinement": "cem", "num_elites": 20}, "num_elites must be"),
        ({"refinement": "mppi", "policy_fraction": 1.0}, "policy_fraction must be"),
        ({"refinement": "mppi", "temperature": 0.0}, "temperature must be"),
    ],
)
def test_refinement_errors(real, policy, kwargs, match):
    with pytest.raises(ValueError, match=match):
        PolicyGuidedMPCPlanner(closed_form_env(real), policy, **kwargs)


def test_min_q_value_is_the_minimum_of_the_loss_q_networks():
    env = make_gym_state_env("Pendulum-v1", seed=0)
    torch.manual_seed(0)
    actor, qvalue = make_sac_actor_critic(env, hidden_sizes=(8, 8))
    loss = SACLoss(actor, qvalue, num_qvalue_nets=2)
    value = MinQValue(actor, qvalue, loss.qvalue_network_params)
    td = TensorDict(observation=torch.randn(5, 3), batch_size=[5])
    out = value(td.clone())["state_value"]
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    with set_exploration_type(ExplorationType.DETERMINISTIC):
        acted = actor(td.clone())
    per_net = []
    for params in loss.qvalue_network_params.unbind(0):
        with params.to_module(qvalue):
            per_net.append(qvalue(acted.clone())["state_action_value"])
    assert not torch.allclose(per_net[0], per_net[1])  # two differently initialised nets
    torch.testing.assert_close(out, torch.minimum(per_net[0], per_net[1]))
    # The loss trains those parameters in place: the value follows an update.
    with torch.no_grad():
        for p in loss.qvalue_network_params.values(True, True):
            p.add_(0.5)
    assert not torch.allclose(value(td.clone())["state_value"], out)
    with pytest.raises(ValueError, match="stacked parameters"):
        MinQValue(actor, qvalue, loss.qvalue_network_params[0])
