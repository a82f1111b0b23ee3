"""Planners stop each candidate's score at its first imagined terminal state, on every path."""

from __future__ import annotations

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.envs import RewardScaling, TransformedEnv

from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env
from torchrl_mbmf.envs.terminations import termination_rule
from torchrl_mbmf.modules import (
    DeltaDynamicsModel,
    EnsembleDeltaDynamicsModel,
    EnsemblePolicyGuidedPlanner,
    PolicyGuidedMPCPlanner,
    RandomShootingMPCPlanner,
    make_ppo_actor_critic,
)
from torchrl_mbmf.modules.planners import TrustedHorizon

X_FIRST = {"exclude_current_positions_from_observation": False}
H = 6


@pytest.fixture(scope="module")
def hopper():
    return make_gym_state_env("Hopper-v5", seed=0, **X_FIRST)


@pytest.fixture(scope="module")
def actor(hopper):
    torch.manual_seed(0)
    return make_ppo_actor_critic(hopper, hidden_sizes=(16, 16), init_log_std=-0.3)[0]


def reward_of_first_action(model: DeltaDynamicsModel) -> DeltaDynamicsModel:
    """``s' = s`` and reward ``relu(a_0)`` exactly (identity scaling)."""
    d, a = model.state_dim, model.action_dim
    with torch.no_grad():
        for p in model.parameters():
            p.zero_()
        first, last = model.net[0], model.net[-1]
        if model.ensemble_size == 1:
            first.weight[0, d] = 1.0  # hidden unit 0 = relu(action 0)
            last.weight[d, 0] = 1.0  # reward = hidden unit 0
        else:  # members' weights are [K, in, out]
            first.weight[:, d, 0] = 1.0
            last.weight[:, 0, d] = 1.0
    assert a >= 1
    return model


class ConstantValue(nn.Module):
    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.full((*obs.shape[:-1], 1), 100.0)


def always(state: torch.Tensor) -> torch.Tensor:
    return torch.ones(state.shape[:-1], dtype=torch.bool)


def planners(env, actor, ensemble_env=None):
    value = TensorDictModule(ConstantValue(), in_keys=["observation"], out_keys=["state_value"])
    kw = {"num_candidates": 12, "horizon": H}
    fused = PolicyGuidedMPCPlanner(env, actor, **kw)
    step_loop = PolicyGuidedMPCPlanner(env, actor, **kw)
    step_loop.fused_rollout = False
    generic = PolicyGuidedMPCPlanner(env, actor, **kw)
    generic.fast_path = False
    out = {
        "fused": fused,
        "step_loop": step_loop,
        "generic": generic,
        "value": PolicyGuidedMPCPlanner(env, actor, value_module=value, **kw),
        "random": RandomShootingMPCPlanner(env, **kw),
        "cem": PolicyGuidedMPCPlanner(env, actor, refinement="cem", **kw),
        "mppi": PolicyGuidedMPCPlanner(env, actor, refinement="mppi", **kw),
    }
    if ensemble_env is not None:
        out["ensemble"] = EnsemblePolicyGuidedPlanner(ensemble_env, actor, **kw)
        out["ensemble_threshold"] = EnsemblePolicyGuidedPlanner(
            ensemble_env, actor, disagreement_threshold=1e9, **kw
        )
    return out


def test_every_step_terminates_score_is_the_first_reward(hopper, actor):
    env = LearnedDynamicsEnv(
        reward_of_first_action(DeltaDynamicsModel(12, 3, hidden_sizes=(4,))),
        hopper,
        termination_fn=always,
    )
    ens = reward_of_first_action(
        EnsembleDeltaDynamicsModel(12, 3, num_members=3, hidden_sizes=(4,))
    )
    ens_env = LearnedDynamicsEnv(ens, hopper, termination_fn=always)
    td = make_gym_state_env("Hopper-v5", num_envs=2, seed=1, **X_FIRST).reset()
    for name, planner in planners(env, actor, ens_env).items():
        torch.manual_seed(0)
        plan = planner.plan(td.clone())
        first_reward = plan.first_actions[..., 0].clamp(-1, 1).relu()
        # the first step terminates: its reward counts, the 5 later ones and the value do not
        torch.testing.assert_close(plan.returns, first_reward, msg=name)
        best = plan.returns.argmax(-1)
        assert torch.equal(plan.best, best), name  # all candidates end: still the best one


def hopper_model(hopper) -> DeltaDynamicsModel:
    """A random model whose scaling is fitted on real Hopper transitions (varied predictions)."""
    torch.manual_seed(3)
    data = make_gym_state_env("Hopper-v5", seed=2, **X_FIRST).rollout(
        300, break_when_any_done=False
    )
    model = DeltaDynamicsModel(12, 3, hidden_sizes=(32, 32))
    s, nxt = data["state"], data["next", "state"]
    model.fit_normalizer(s, data["action"], s + 3.0 * (nxt - s), data["next", "reward"])
    return model


def test_fused_step_loop_and_generic_agree_with_terminations(hopper, actor):
    env = LearnedDynamicsEnv(hopper_model(hopper), hopper)  # Hopper's own rule
    td = make_gym_state_env("Hopper-v5", num_envs=4, seed=5, **X_FIRST).reset()
    td["state"][:, 2] = torch.tensor([0.17, 0.18, 0.19, -0.19])  # torso leaning: near +-0.2
    td["observation"] = td["state"][:, 1:]
    plans = {}
    for name in ("fused", "step_loop", "generic"):
        planner = planners(env, actor)[name]
        torch.manual_seed(7)
        plans[name] = planner.plan(td.clone())
    # some candidates end early, some do not: the masks matter
    torch.manual_seed(7)
    out = planners(env, actor)["step_loop"].rollout(td["state"])
    ended = out.terminated.any(-1)
    assert 0 < ended.float().mean() < 1
    no_mask = out.rewards.sum(-1)
    assert not torch.allclose(no_mask, plans["fused"].returns)
    for name in ("step_loop", "generic"):
        torch.testing.assert_close(plans[name].first_actions, plans["fused"].first_actions)
        torch.testing.assert_close(
            plans[name].returns, plans["fused"].returns, atol=1e-4, rtol=1e-4
        )
        assert torch.equal(plans[name].best, plans["fused"].best)
    # bit for bit between the fused loop and the step loop
    assert torch.equal(plans["step_loop"].returns, plans["fused"].returns)


def test_hopper_about_to_fall(hopper, actor):
    """Real Hopper states one step before a real fall: the candidates that fall end there."""
    real = make_gym_state_env("Hopper-v5", seed=4, **X_FIRST)
    data = real.rollout(400, break_when_any_done=False)
    fall = data["next", "terminated"][:, 0] & ~data["terminated"][:, 0]
    before = data[fall.nonzero()[:5, 0]]
    assert before.shape[0] > 0
    rule = termination_rule("Hopper-v5", **X_FIRST)
    assert not rule(before["state"]).any() and rule(before["next", "state"]).all()

    model = reward_of_first_action(DeltaDynamicsModel(12, 3, hidden_sizes=(4,)))
    with torch.no_grad():  # reward 1 whatever the action; delta = the real step's
        model.net[-1].weight.zero_()
        model.net[-1].bias[12] = 1.0
    env = LearnedDynamicsEnv(model, hopper)
    # imagined step: the real fall's next state (a constant delta per start state)
    deltas = before["next", "state"] - before["state"]
    for i in range(before.shape[0]):
        with torch.no_grad():
            model.net[-1].bias[:12] = deltas[i]
        planner = RandomShootingMPCPlanner(env, num_candidates=8, horizon=H)
        plan = planner.plan(before[i : i + 1].clone())
        # the Hopper falls at the first imagined step: every candidate scores its one reward
        torch.testing.assert_close(plan.returns, torch.ones(1, 8))
    # without the rule the same plan would count the whole horizon
    env_blind = LearnedDynamicsEnv(model, hopper, termination_fn=lambda s: rule(s) & False)
    plan = RandomShootingMPCPlanner(env_blind, num_candidates=8, horizon=H).plan(before[-1:])
    torch.testing.assert_close(plan.returns, torch.full((1, 8), float(H)))


def test_transformed_env_takes_the_generic_path(hopper, actor):
    env = LearnedDynamicsEnv(hopper_model(hopper), hopper)
    assert (
        PolicyGuidedMPCPlanner(env, actor, num_candidates=8, horizon=4)
        .plan(hopper.reset().expand(2).clone())
        .returns.abs()
        .max()
        > 1e-2
    )
    zero = TransformedEnv(env, RewardScaling(loc=0.0, scale=0.0))
    td = hopper.reset().expand(2).clone()
    for planner in (
        PolicyGuidedMPCPlanner(zero, actor, num_candidates=8, horizon=4),
        RandomShootingMPCPlanner(zero, num_candidates=8, horizon=4),
    ):
        assert not planner.fast_path
        plan = planner.plan(td.clone())
        # (RewardScaling floors its scale at 1e-6: rewards ~1e-6, not the model's ~1)
        torch.testing.assert_close(plan.returns, torch.zeros(2, 8), atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="refinement"):
        PolicyGuidedMPCPlanner(zero, actor, refinement="cem")


def test_overridden_step_takes_the_generic_path(hopper, actor):
    class DoubledReward(LearnedDynamicsEnv):
        def _step(self, tensordict):
            out = super()._step(tensordict)
            return out.set("reward", 2 * out.get("reward"))

    model = hopper_model(hopper)
    plain, doubled = LearnedDynamicsEnv(model, hopper), DoubledReward(model, hopper)
    td = hopper.reset().expand(2).clone()
    a, b = (PolicyGuidedMPCPlanner(e, actor, num_candidates=8, horizon=4) for e in (plain, doubled))
    assert a.fast_path and not b.fast_path
    torch.manual_seed(1)
    pa = a.plan(td.clone())
    torch.manual_seed(1)
    pb = b.plan(td.clone())
    # doubling every reward doubles every score (the terminal steps are the same)
    torch.testing.assert_close(pb.returns, 2 * pa.returns, atol=1e-4, rtol=1e-4)


def test_overridden_horizon_mask_is_honoured(hopper, actor):
    class FirstStepOnly(PolicyGuidedMPCPlanner):
        def horizon_mask(self):
            return _FirstStep()

    class _FirstStep(TrustedHorizon):
        def __init__(self):
            super().__init__(threshold=None)

        def finish(self, state, horizon):
            return self.trusted.fill_(1), state

    env = LearnedDynamicsEnv(hopper_model(hopper), hopper, termination_fn=lambda s: s[..., 0] > 1e9)
    td = hopper.reset().expand(2).clone()
    planner = FirstStepOnly(env, actor, num_candidates=8, horizon=4)
    torch.manual_seed(2)
    plan = planner.plan(td.clone())
    plain = PolicyGuidedMPCPlanner(env, actor, num_candidates=8, horizon=4)
    assert plain.policy_rollout is not None and planner.policy_rollout is None
    torch.manual_seed(2)
    out = plain.rollout(td["state"])
    torch.testing.assert_close(plan.returns, out.rewards[..., 0])  # first step only
    assert not torch.allclose(plan.returns, out.rewards.sum(-1))


def test_overridden_score_hook_sees_rewards_stop_at_termination(hopper, actor):
    class SumOfSquares(RandomShootingMPCPlanner):
        def score_candidates(self, rewards, final):
            return rewards.pow(2).sum(-1)

    model = reward_of_first_action(DeltaDynamicsModel(12, 3, hidden_sizes=(4,)))
    with torch.no_grad():
        model.net[-1].weight.zero_()
        model.net[-1].bias[12] = 2.0  # reward 2 at every step
    ends_at_step_1 = LearnedDynamicsEnv(model, hopper, termination_fn=always)
    plan = SumOfSquares(ends_at_step_1, num_candidates=4, horizon=H).plan(hopper.reset())
    torch.testing.assert_close(plan.returns, torch.full((4,), 4.0))  # one step: 2 ** 2
