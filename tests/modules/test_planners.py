from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import AddStateIndependentNormalScale, NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import IndependentNormal, ProbabilisticActor, TanhNormal, ValueOperator

from torchrl_mbmf.envs import LearnedDynamicsEnv, make_gym_state_env, make_half_cheetah_env
from torchrl_mbmf.modules import (
    DeltaDynamicsModel,
    PolicyGuidedMPCPlanner,
    RandomShootingMPCPlanner,
    make_ppo_actor_critic,
    make_sac_actor_critic,
)
from torchrl_mbmf.modules.planners import ActorSampler, CachedModelStep

C = torch.tensor([1.0, -2.0, 0.5, 3.0, -1.0, 2.0])


def closed_form_env(real):
    """Learned env with s' = s + [0, a, 0...] and r = C . a, exactly (identity scaling)."""
    model = DeltaDynamicsModel(18, 6, hidden_sizes=())
    w = torch.zeros(19, 24)
    w[1:7, 18:24] = torch.eye(6)  # delta of state dims 1..6 = action
    w[18, 18:24] = C  # reward = C . a
    with torch.no_grad():
        model.net[0].weight.copy_(w)
        model.net[0].bias.zero_()
    return LearnedDynamicsEnv(model, real)


@pytest.fixture(scope="module")
def real():
    return make_half_cheetah_env(seed=0)


@pytest.fixture(scope="module")
def actor(real):
    torch.manual_seed(0)
    return make_ppo_actor_critic(real, init_log_std=-0.5)


def brute_force(planner, state, seed, sample):
    """Re-draw the same candidates and pick the best by the closed-form return."""
    torch.manual_seed(seed)
    s = state.unsqueeze(-2).expand(*state.shape[:-1], planner.num_candidates, 18)
    returns, first = 0.0, None
    for _ in range(planner.horizon):
        a = sample(s[..., 1:])
        first = a if first is None else first
        returns = returns + (a.clamp(-1, 1) * C).sum(-1)
        s = s.clone()
        s[..., 1:7] += a.clamp(-1, 1)
    best = returns.argmax(-1)
    return first.gather(-2, best[..., None, None].expand(*best.shape, 1, 6)).squeeze(-2)


@pytest.mark.parametrize("batch", [(), (4,)])
def test_random_shooting_picks_best_candidate(real, batch):
    env = closed_form_env(real)
    planner = RandomShootingMPCPlanner(env, num_candidates=15, horizon=10)
    td = real.reset().expand(*batch).clone() if batch else real.reset()
    torch.manual_seed(3)
    out = planner(td.clone())
    expected = brute_force(planner, td["state"], 3, lambda o: torch.rand(*o.shape[:-1], 6) * 2 - 1)
    torch.testing.assert_close(out["action"], expected)
    assert out["action"].shape == (*batch, 6)
    ret = out["planner", "best_return"]
    assert (ret >= out["planner", "mean_return"]).all()


@pytest.mark.parametrize("batch", [(), (3,)])
def test_policy_guided_picks_best_candidate(real, actor, batch):
    policy, _ = actor
    env = closed_form_env(real)
    planner = PolicyGuidedMPCPlanner(env, policy, num_candidates=15, horizon=5)
    td = real.reset().expand(*batch).clone() if batch else real.reset()
    torch.manual_seed(4)
    out = planner(td.clone())

    def sample(obs):
        return policy.get_dist(TensorDict(observation=obs, batch_size=obs.shape[:-1])).sample()

    torch.testing.assert_close(out["action"], brute_force(planner, td["state"], 4, sample))


def test_actions_in_spec_and_inputs_untouched(real, actor):
    policy, _ = actor
    model_env = LearnedDynamicsEnv(DeltaDynamicsModel(18, 6, hidden_sizes=(32,)), real)
    td = make_half_cheetah_env(num_envs=2, seed=1).rollout(3)[:, -1]
    for planner in (
        PolicyGuidedMPCPlanner(model_env, policy),
        RandomShootingMPCPlanner(model_env, actor=policy),
        RandomShootingMPCPlanner(model_env),
    ):
        before = td.clone()
        out = planner(td.clone())
        assert real.action_spec.is_in(out["action"][0])
        assert real.action_spec.is_in(out["action"][1])
        for key in before.keys(True, True):
            if key not in planner.out_keys:
                torch.testing.assert_close(out[key], before[key])


def test_log_prob_is_actor_log_prob_at_real_state(real, actor):
    policy, _ = actor
    model_env = LearnedDynamicsEnv(DeltaDynamicsModel(18, 6, hidden_sizes=(32,)), real)
    td = make_half_cheetah_env(num_envs=4, seed=2).reset()
    for planner in (
        PolicyGuidedMPCPlanner(model_env, policy),
        RandomShootingMPCPlanner(model_env, actor=policy),
    ):
        out = planner(td.clone())
        dist = policy.get_dist(td.clone())
        torch.testing.assert_close(out["action_log_prob"], dist.log_prob(out["action"]))
        params = policy.module[0](td.clone())
        torch.testing.assert_close(out["loc"], params["loc"])
        torch.testing.assert_close(out["scale"], params["scale"])
        assert out["action_log_prob"].shape == (4,)


def test_same_seed_same_actions_and_deterministic_mode_still_samples(real, actor):
    policy, _ = actor
    model_env = LearnedDynamicsEnv(DeltaDynamicsModel(18, 6, hidden_sizes=(32,)), real)
    planner = PolicyGuidedMPCPlanner(model_env, policy, num_candidates=8, horizon=3)
    td = real.reset()
    torch.manual_seed(0)
    a = planner(td.clone())["action"]
    torch.manual_seed(0)
    b = planner(td.clone())["action"]
    torch.testing.assert_close(a, b)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        plan = planner.plan(td.clone())
    # candidates differ: the policy is sampled even in deterministic mode
    assert plan.first_actions.std(0).min() > 0


@pytest.mark.parametrize("cls", ["policy", "random"])
def test_fast_and_generic_paths_agree(real, actor, cls):
    policy, _ = actor
    torch.manual_seed(0)
    model = DeltaDynamicsModel(18, 6, hidden_sizes=(32, 32))
    s = torch.randn(200, 18)
    model.fit_normalizer(s, torch.rand(200, 6) * 2 - 1, s + torch.randn(200, 18), torch.randn(200))
    model_env = LearnedDynamicsEnv(model, real)
    if cls == "policy":
        planner = PolicyGuidedMPCPlanner(model_env, policy, num_candidates=15, horizon=6)
    else:
        planner = RandomShootingMPCPlanner(model_env, num_candidates=15, horizon=6)
    td = make_half_cheetah_env(num_envs=3, seed=5).reset()
    torch.manual_seed(7)
    fast = planner.plan(td.clone())
    planner.fast_path = False
    torch.manual_seed(7)
    generic = planner.plan(td.clone())
    torch.testing.assert_close(fast.first_actions, generic.first_actions)
    torch.testing.assert_close(fast.returns, generic.returns, rtol=1e-4, atol=1e-4)
    assert torch.equal(fast.best, generic.best)


def test_terminal_value_and_discount_change_the_choice(real):
    env = closed_form_env(real)
    # value favours a low state[1] (= cumulative action 0); the reward favours a high one
    value = ValueOperator(_NegFirst(), in_keys=["observation"])
    td = real.reset()
    plain = RandomShootingMPCPlanner(env, num_candidates=15, horizon=2)
    valued = RandomShootingMPCPlanner(env, num_candidates=15, horizon=2, value_module=value)
    torch.manual_seed(1)
    p1 = plain.plan(td.clone())
    torch.manual_seed(1)
    p2 = valued.plan(td.clone())
    torch.testing.assert_close(p1.first_actions, p2.first_actions)
    final0 = td["state"][1] + 0  # start value of state[1]
    assert p1.action[0] > 0  # C[0] = 1 rewards a positive first action dim
    assert p2.action[0] < 0  # the value (100 * -state[1]) dominates
    assert not torch.equal(p1.best, p2.best)
    assert final0.ndim == 0
    discounted = RandomShootingMPCPlanner(env, num_candidates=15, horizon=2, discount=0.5)
    torch.manual_seed(1)
    p3 = discounted.plan(td.clone())
    manual = p1.returns.new_zeros(15)
    torch.manual_seed(1)
    draws = [torch.rand(15, 6) * 2 - 1 for _ in range(2)]
    manual = (draws[0] * C).sum(-1) + 0.5 * (draws[1] * C).sum(-1)
    torch.testing.assert_close(p3.returns, manual)


class _NegFirst(nn.Module):
    def forward(self, obs):
        return -100.0 * obs[..., :1]


def test_errors(real, actor):
    policy, _ = actor
    env = LearnedDynamicsEnv(DeltaDynamicsModel(18, 6, hidden_sizes=(8,)), real)
    with pytest.raises(ValueError, match="num_candidates must be an integer >= 1, got 0"):
        RandomShootingMPCPlanner(env, num_candidates=0)
    with pytest.raises(ValueError, match="horizon must be an integer >= 1, got 0"):
        PolicyGuidedMPCPlanner(env, policy, horizon=0)
    with pytest.raises(ValueError, match="discount"):
        PolicyGuidedMPCPlanner(env, policy, discount=0.0)
    wrong = ProbabilisticActor(
        TensorDictModule(
            nn.Sequential(nn.Linear(17, 4), AddStateIndependentNormalScale(4)),
            in_keys=["observation"],
            out_keys=["loc", "scale"],
        ),
        in_keys=["loc", "scale"],
        distribution_class=TanhNormal,
        return_log_prob=True,
    )
    with pytest.raises(ValueError, match="size 4, the env's action spec has size 6"):
        PolicyGuidedMPCPlanner(env, wrong)
    deterministic = TensorDictModule(nn.Linear(17, 6), in_keys=["observation"], out_keys=["action"])
    with pytest.raises(TypeError, match="stochastic TorchRL actor"):
        PolicyGuidedMPCPlanner(env, deterministic)
    with pytest.raises(TypeError, match="needs a stochastic actor"):
        PolicyGuidedMPCPlanner(env, None)
    pendulum_actor, _ = make_ppo_actor_critic(make_gym_state_env("Pendulum-v1"))
    with pytest.raises(ValueError, match="cannot read the env's 'observation'"):
        PolicyGuidedMPCPlanner(env, pendulum_actor)


def test_generic_path_with_value_module_agrees(real):
    """The terminal value reads the same entries on both paths (state and observation)."""
    torch.manual_seed(0)
    model_env = LearnedDynamicsEnv(DeltaDynamicsModel(18, 6, hidden_sizes=(16,)), real)
    value = ValueOperator(nn.Linear(17, 1), in_keys=["observation"])
    planner = RandomShootingMPCPlanner(
        model_env, num_candidates=7, horizon=3, value_module=value, discount=0.9
    )
    td = make_half_cheetah_env(num_envs=2, seed=3).reset()
    torch.manual_seed(2)
    fast = planner.plan(td.clone())
    planner.fast_path = False
    torch.manual_seed(2)
    generic = planner.plan(td.clone())
    torch.testing.assert_close(fast.returns, generic.returns, rtol=1e-4, atol=1e-4)
    assert torch.equal(fast.best, generic.best)


class _LinearModelEnv(ModelBasedEnvBase):
    """A non-LearnedDynamicsEnv model env: obs' = obs + [a, 0, 0], reward = a . 1 (closed form)."""

    def __init__(self, action_spec=None):
        module = TensorDictModule(
            lambda obs, a: (obs + torch.nn.functional.pad(a, (0, 2)), a.sum(-1, keepdim=True)),
            in_keys=["observation", "action"],
            out_keys=["observation", "reward"],
        )
        super().__init__(module)
        self.observation_spec = Composite(observation=Unbounded(shape=(3,)))
        self.action_spec = action_spec if action_spec is not None else Bounded(-2.0, 2.0, (1,))
        self.reward_spec = Unbounded(shape=(1,))

    def _reset(self, tensordict=None, **kwargs):
        return tensordict.select("observation").copy()


def test_generic_path_on_any_model_based_env():
    env = _LinearModelEnv()
    planner = RandomShootingMPCPlanner(env, num_candidates=9, horizon=4)
    assert not planner.fast_path
    td = TensorDict(observation=torch.randn(5, 3), batch_size=[5])
    before = td.clone()
    torch.manual_seed(11)
    out = planner(td)
    torch.manual_seed(11)
    draws = [torch.rand(5, 9, 1) * 4 - 2 for _ in range(4)]
    returns = sum(d[..., 0] for d in draws)
    expected = draws[0][torch.arange(5), returns.argmax(-1)]
    torch.testing.assert_close(out["action"], expected)
    torch.testing.assert_close(out["observation"], before["observation"])
    with pytest.raises(ValueError, match="must be bounded"):
        RandomShootingMPCPlanner(_LinearModelEnv(Unbounded(shape=(1,))))


def test_cached_model_step_matches_model_and_sees_refits():
    torch.manual_seed(0)
    model = DeltaDynamicsModel(18, 6, hidden_sizes=(300, 300))
    s, a = torch.randn(64, 18), torch.rand(64, 6) * 2 - 1
    model.fit_normalizer(s, a, s + 0.1 * torch.randn(64, 18), torch.randn(64))
    step = CachedModelStep(model)
    with torch.no_grad():
        first = step()
        assert step() is first  # cached while the weights do not change
        for got, want in zip(first(s[:15], a[:15]), model(s[:15], a[:15]), strict=True):
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    optim = torch.optim.SGD(model.parameters(), lr=0.1)
    model(s, a)[0].square().mean().backward()
    optim.step()  # an in-place update, as a refit inside a Collector loop
    with torch.no_grad():
        assert step() is not first
        torch.testing.assert_close(step()(s, a)[0], model(s, a)[0], rtol=1e-5, atol=1e-5)
        model.fit_normalizer(s, a, s + torch.randn(64, 18), torch.randn(64))
        torch.testing.assert_close(step()(s, a)[1], model(s, a)[1], rtol=1e-5, atol=1e-5)


def _fitted_env(real, hidden=(32, 32)):
    torch.manual_seed(0)
    model = DeltaDynamicsModel(18, 6, hidden_sizes=hidden)
    s = torch.randn(200, 18)
    model.fit_normalizer(s, torch.rand(200, 6) * 2 - 1, s + torch.randn(200, 18), torch.randn(200))
    return LearnedDynamicsEnv(model, real)


@pytest.mark.parametrize("batch", [(), (3,)])
@pytest.mark.parametrize("kind", ["ppo", "ppo_normal", "sac"])
def test_fused_rollout_is_bit_identical_to_step_by_step(real, batch, kind):
    """The fused loop runs the same operations on the same values: equal bit for bit."""
    torch.manual_seed(1)
    if kind == "sac":
        policy, _ = make_sac_actor_critic(real, hidden_sizes=(32, 32))
    else:
        dist = "normal" if kind == "ppo_normal" else "tanh_normal"
        policy, _ = make_ppo_actor_critic(real, distribution=dist, init_log_std=-0.5)
    # 300 x 300 is above CachedModelStep's packing threshold: the oneDNN layer is covered
    planner = PolicyGuidedMPCPlanner(_fitted_env(real, (300, 300)), policy, horizon=6)
    assert planner.policy_rollout is not None and planner.policy_rollout.available()
    td = real.reset().expand(*batch).clone() if batch else real.reset()
    td["state"] = td["state"] + torch.randn_like(td["state"])  # distinct real states
    td["observation"] = td["state"][..., 1:]
    outs = []
    for fused in (True, False):
        planner.fused_rollout = fused
        torch.manual_seed(7)
        plan = planner.plan(td.clone())
        outs.append((plan, planner(td.clone()), torch.rand(())))
    (p1, o1, r1), (p2, o2, r2) = outs
    assert torch.equal(p1.first_actions, p2.first_actions)
    assert torch.equal(p1.returns, p2.returns)
    assert torch.equal(p1.best, p2.best)
    assert torch.equal(r1, r2)  # the same number of random draws
    for key in planner.out_keys:
        assert torch.equal(o1[key], o2[key]), key


def test_fused_rollout_only_for_stock_policy_samples(real, actor):
    policy, _ = actor
    env = _fitted_env(real)

    class Uniform(PolicyGuidedMPCPlanner):
        def sample_candidate_actions(self, observation, step):
            return torch.rand(*observation.shape[:-1], 6) * 2 - 1

    assert Uniform(env, policy).policy_rollout is None
    assert PolicyGuidedMPCPlanner(env, policy, refinement="cem").policy_rollout is None
    assert RandomShootingMPCPlanner(env, actor=policy).policy_rollout is None


def test_tight_actor_params_follow_weight_updates(real, actor):
    policy, _ = make_ppo_actor_critic(real, init_log_std=-0.5)
    sampler = ActorSampler(policy)
    obs = torch.randn(15, 17)
    fn, scale = sampler.tight_params()
    assert sampler.tight_params()[0] is fn  # cached while nothing changes
    loc, want_scale = sampler.params(obs)
    assert torch.equal(fn(obs)[0], loc)
    assert torch.equal(scale.expand_as(want_scale), want_scale)
    optim = torch.optim.SGD(policy.parameters(), lr=0.1)
    dist = policy.get_dist(TensorDict(observation=obs, batch_size=[15]))
    dist.log_prob(torch.zeros(15, 6)).sum().backward()
    optim.step()
    fn, scale = sampler.tight_params()
    loc, want_scale = sampler.params(obs)
    assert torch.equal(fn(obs)[0], loc)
    assert torch.equal(scale.expand_as(want_scale), want_scale)
    net = policy.module[0].module[0]
    net[0].weight = nn.Parameter(torch.zeros_like(net[0].weight))  # a replaced tensor
    assert torch.equal(sampler.tight_params()[0](obs)[0], sampler.params(obs)[0])


def test_tight_params_of_the_tanh_loc_actor_unroll_its_network(real):
    """The recipes' actor (``distribution="normal"``: tanh of the MLP's output as the mean)."""
    torch.manual_seed(0)
    policy, _ = make_ppo_actor_critic(real, distribution="normal", init_log_std=-0.5)
    sampler = ActorSampler(policy)
    obs = torch.randn(15, 17)
    fn, scale = sampler.tight_params()
    td = policy.module[0](TensorDict(observation=obs, batch_size=[15]))
    assert torch.equal(fn(obs)[0], td["loc"])  # the same values as the module, bit for bit
    assert torch.equal(scale.expand_as(td["scale"]), td["scale"])
    # every layer is unrolled: no module of the network is called by the tight chain
    calls = []
    hooks = [m.register_forward_hook(lambda *a: calls.append(1)) for m in policy.modules()]
    fn(obs)
    for h in hooks:
        h.remove()
    assert calls == []


@pytest.mark.parametrize("distribution", ["normal", "tanh_normal"])
@pytest.mark.parametrize("shape", [(), (5,), (2, 3)])
def test_sampler_draws_what_the_stock_actor_draws(real, distribution, shape):
    """The collectors' and step loops' draws (the tight chain) equal the actor's, bit for bit."""
    torch.manual_seed(0)
    policy, _ = make_ppo_actor_critic(real, distribution=distribution, init_log_std=-0.5)
    sampler = ActorSampler(policy)
    obs = torch.randn(*shape, 17)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        torch.manual_seed(1)
        td = policy(TensorDict(observation=obs, batch_size=shape))
        torch.manual_seed(1)
        action, (loc, scale) = sampler.sample_with_params(obs)
    assert torch.equal(loc, td["loc"]) and torch.equal(scale, td["scale"])
    assert torch.equal(action, td["action"])
    # with autograd on, the module path (gradients reach the parameters)
    _, (loc, _) = sampler.sample_with_params(obs)
    assert loc.requires_grad


@pytest.mark.parametrize("distribution", ["normal", "tanh_normal"])
def test_sampler_follows_a_loss_load_state_dict(real, distribution):
    """A torchrl loss loads parameters in place without bumping their version counters (a
    resumed run): the tight chain's constant scale follows them all the same."""
    from torchrl.objectives import ClipPPOLoss

    torch.manual_seed(0)
    policy, critic = make_ppo_actor_critic(real, distribution=distribution)
    loss = ClipPPOLoss(policy, critic)
    sampler = ActorSampler(policy)
    obs = torch.randn(17)
    state = {k: v + 0.25 if v.is_floating_point() else v for k, v in loss.state_dict().items()}
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        sampler.sample_with_params(obs)  # the chain and its constant scale are built
        loss.load_state_dict(state)
        torch.manual_seed(1)
        td = policy(TensorDict(observation=obs))
        torch.manual_seed(1)
        action, (loc, scale) = sampler.sample_with_params(obs)
    assert torch.equal(scale, td["scale"]) and torch.equal(loc, td["loc"])
    assert torch.equal(action, td["action"])
    assert torch.equal(scale, torch.full_like(scale, 0.25).exp())


@pytest.mark.parametrize("bounds", [(-1.0, 1.0), (-2.0, 0.5)])
def test_closed_form_log_prob_matches_distribution(bounds):
    torch.manual_seed(0)
    low, high = torch.full((6,), bounds[0]), torch.full((6,), bounds[1])
    loc, scale = torch.randn(20, 6), torch.rand(20, 6) + 0.05
    action = low + (high - low) * torch.rand(20, 6)
    for cls, kwargs in ((TanhNormal, {"low": low, "high": high}), (IndependentNormal, {})):
        policy = ProbabilisticActor(
            TensorDictModule(
                NormalParamExtractor(), in_keys=["observation"], out_keys=["loc", "scale"]
            ),
            in_keys=["loc", "scale"],
            distribution_class=cls,
            distribution_kwargs=kwargs,
        )
        sampler = ActorSampler(policy)
        assert sampler.closed_form_log_prob
        want = cls(loc, scale, **kwargs).log_prob(action)
        torch.testing.assert_close(sampler.log_prob_params(action, loc, scale), want)


def test_cached_model_step_sees_a_replaced_parameter():
    model = DeltaDynamicsModel(3, 1, hidden_sizes=(8,))
    step = CachedModelStep(model)
    s, a = torch.randn(5, 3), torch.randn(5, 1)
    with torch.no_grad():
        first = step()
        model.net[0].weight = nn.Parameter(torch.randn(8, 4))
        assert step() is not first
        torch.testing.assert_close(step()(s, a)[0], model(s, a)[0], rtol=1e-5, atol=1e-5)


def test_planner_writes_the_actors_log_prob_key_for_stock_ppo():
    from tensordict.nn import NormalParamExtractor
    from torchrl.objectives import ClipPPOLoss
    from torchrl.objectives.value import GAE

    real = make_gym_state_env("Pendulum-v1", seed=0)
    torch.manual_seed(0)
    net = TensorDictModule(
        nn.Sequential(nn.Linear(3, 16), nn.Tanh(), nn.Linear(16, 2), NormalParamExtractor()),
        in_keys=["observation"],
        out_keys=["loc", "scale"],
    )
    actor = ProbabilisticActor(
        net,
        in_keys=["loc", "scale"],
        spec=real.action_spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -2.0, "high": 2.0},
        return_log_prob=True,
        log_prob_key="sample_log_prob",
    )
    critic = ValueOperator(nn.Linear(3, 1), in_keys=["observation"])
    model_env = LearnedDynamicsEnv(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), real)
    planner = PolicyGuidedMPCPlanner(model_env, actor, num_candidates=4, horizon=2)
    assert planner.log_prob_key == "sample_log_prob"
    assert RandomShootingMPCPlanner(model_env).log_prob_key == "action_log_prob"
    assert PolicyGuidedMPCPlanner(model_env, actor, log_prob_key="lp").log_prob_key == "lp"
    batch = real.rollout(6, planner)
    keys = set(batch.keys())
    assert "sample_log_prob" in keys and "action_log_prob" not in keys
    # the written log-prob is the actor's own at the real state
    dist = actor.get_dist(batch.select("observation").clone())
    torch.testing.assert_close(
        batch["sample_log_prob"], dist.log_prob(batch["action"]), atol=1e-4, rtol=1e-4
    )
    loss = ClipPPOLoss(actor, critic)
    GAE(gamma=0.99, lmbda=0.95, value_network=critic)(batch)
    losses = loss(batch)  # reads "sample_log_prob": no KeyError
    assert torch.isfinite(losses["loss_objective"])
