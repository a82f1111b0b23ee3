"""The fused PPO update takes the steps the stock ppo_update (ClipPPOLoss + GAE) takes."""

from __future__ import annotations

import copy

import pytest
import torch
from rl_helpers import make_test_ppo
from tensordict import TensorDict
from torchrl.objectives.value import GAE
from torchrl.objectives.value.functional import generalized_advantage_estimate

from torchrl_mbmf.objectives.fused_ppo import PPO_STATS, FusedPPOUpdate, gae_recursion, ppo_update


def _pair(distribution: str, num_envs: int | None, frames: int = 64):
    """Two identical (loss, gae, optimiser) triples and one batch."""
    out = []
    for _ in range(2):
        torch.manual_seed(0)
        loss, gae, batch = make_test_ppo(
            frames=frames, num_envs=num_envs, obs_dim=5, action_dim=3, distribution=distribution
        )
        out.append((loss, gae, torch.optim.Adam(loss.parameters(), lr=1e-3)))
    return out[0], out[1], batch


@pytest.mark.parametrize("num_envs", [None, 2])
@pytest.mark.parametrize("distribution", ["tanh_normal", "normal"])
def test_gae_matches_torchrl(distribution, num_envs):
    (loss, gae, optim), _, batch = _pair(distribution, num_envs)
    assert batch["next", "terminated"].any() and batch["next", "truncated"].any()
    fused = FusedPPOUpdate(loss, gae, optim)
    advantage, value_target = fused.advantage(batch)
    stock = gae(batch.clone())
    torch.testing.assert_close(advantage, stock["advantage"], rtol=0, atol=0)
    torch.testing.assert_close(value_target, stock["value_target"], rtol=0, atol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(("shape", "time_dim"), [((300, 1), 0), ((3, 200, 1), 1), ((40, 2, 2), 0)])
def test_gae_recursion_is_torchrls_gae(shape, time_dim, dtype):
    """The NumPy recursion gives torchrl's loop's advantages and targets bit for bit."""
    g = torch.Generator().manual_seed(0)
    value, next_value = 30 * torch.randn(2, *shape, generator=g, dtype=dtype)
    reward = torch.randn(shape, generator=g, dtype=dtype)
    done = torch.rand(shape, generator=g) < 0.05
    terminated = done & (torch.rand(shape, generator=g) < 0.5)
    assert done.any() and terminated.any() and (done & ~terminated).any()
    gamma, lmbda = torch.tensor(0.99), torch.tensor(0.95)
    args = (gamma, lmbda, value, next_value, reward, done, terminated)
    stock = generalized_advantage_estimate(*args, time_dim=time_dim)
    ours = gae_recursion(*args, time_dim=time_dim)
    for a, b in zip(ours, stock, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert torch.equal(a, b)


def test_gae_recursion_refuses_what_it_does_not_run():
    g = torch.tensor(0.9)
    with pytest.raises(ValueError, match="one shape"):
        gae_recursion(
            g,
            g,
            torch.zeros(4, 1),
            torch.zeros(4, 1),
            torch.zeros(3, 1),
            torch.zeros(4, 1, dtype=torch.bool),
            torch.zeros(4, 1, dtype=torch.bool),
        )
    flags = torch.zeros(4, 1, dtype=torch.bool)
    with pytest.raises(ValueError, match="CPU float"):
        ints = torch.zeros(4, 1, dtype=torch.int64)
        gae_recursion(g, g, ints, ints, ints, flags, flags)


def test_hooked_actor_modules_keep_their_calls():
    """A module with a hook is called as it is (the unrolled ops would skip the hook)."""
    (loss, gae, optim), _, batch = _pair("normal", None)
    assert FusedPPOUpdate(loss, gae, optim).nets._loc_run is not None  # unrolled, unhooked
    calls = []
    relu = next(m for m in loss.actor_network.modules() if isinstance(m, torch.nn.ReLU))
    relu.register_forward_hook(lambda *args: calls.append(1))
    fused = FusedPPOUpdate(loss, gae, optim, epochs=1, minibatch_size=16)
    fused(batch.clone())
    assert len(calls) == 64 // 16


@pytest.mark.parametrize("num_envs", [None, 2])
@pytest.mark.parametrize("distribution", ["tanh_normal", "normal"])
def test_fused_iteration_is_bit_identical_to_ppo_update(distribution, num_envs):
    (loss_a, gae_a, optim_a), (loss_b, gae_b, optim_b), batch = _pair(distribution, num_envs)
    fused = FusedPPOUpdate(
        loss_b, gae_b, optim_b, epochs=2, minibatch_size=16, gradients="autograd"
    )
    for seed in (1, 2):  # the second iteration starts from a non-empty Adam state
        torch.manual_seed(seed)
        stock_stats = ppo_update(loss_a, gae_a, optim_a, batch.clone(), epochs=2, minibatch_size=16)
        torch.manual_seed(seed)
        fused_stats = fused(batch.clone())
        assert list(fused_stats) == list(PPO_STATS)
        assert fused_stats == stock_stats
    for a, b in zip(loss_a.parameters(), loss_b.parameters(), strict=True):
        assert torch.equal(a, b)
    state_a, state_b = optim_a.state_dict()["state"], optim_b.state_dict()["state"]
    for i in state_a:
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(state_a[i][key], state_b[i][key])


@pytest.mark.parametrize("gradients", ["autograd", "manual"])
def test_rng_consumption_matches(gradients):
    (loss_a, gae_a, optim_a), (loss_b, gae_b, optim_b), batch = _pair("tanh_normal", None)
    torch.manual_seed(3)
    ppo_update(loss_a, gae_a, optim_a, batch.clone(), epochs=1, minibatch_size=16)
    after_stock = torch.rand(3)
    torch.manual_seed(3)
    fused = FusedPPOUpdate(loss_b, gae_b, optim_b, epochs=1, minibatch_size=16, gradients=gradients)
    fused(batch.clone())
    assert torch.equal(torch.rand(3), after_stock)


def test_stock_and_fused_steps_can_alternate():
    """The optimiser state stays the optimiser's: stock steps after fused ones still match."""
    (loss_a, gae_a, optim_a), (loss_b, gae_b, optim_b), batch = _pair("tanh_normal", None)
    fused = FusedPPOUpdate(
        loss_b, gae_b, optim_b, epochs=1, minibatch_size=16, gradients="autograd"
    )
    for seed, use_fused in ((1, True), (2, False), (3, True)):
        torch.manual_seed(seed)
        ppo_update(loss_a, gae_a, optim_a, batch.clone(), epochs=1, minibatch_size=16)
        torch.manual_seed(seed)
        if use_fused:
            fused(batch.clone())
        else:
            ppo_update(loss_b, gae_b, optim_b, batch.clone(), epochs=1, minibatch_size=16)
    for a, b in zip(loss_a.parameters(), loss_b.parameters(), strict=True):
        assert torch.equal(a, b)
    # a reloaded optimiser state is picked up again
    optim_b.load_state_dict(copy.deepcopy(optim_a.state_dict()))
    torch.manual_seed(4)
    ppo_update(loss_a, gae_a, optim_a, batch.clone(), epochs=1, minibatch_size=16)
    torch.manual_seed(4)
    fused(batch.clone())
    for a, b in zip(loss_a.parameters(), loss_b.parameters(), strict=True):
        assert torch.equal(a, b)


def test_rejects_unsupported_settings():
    loss, gae, _ = make_test_ppo(frames=8)
    optim = torch.optim.Adam(loss.parameters())
    with pytest.raises(ValueError, match="ClipPPOLoss"):
        FusedPPOUpdate(gae, gae, optim)
    loss.clip_value = torch.tensor(0.2)
    with pytest.raises(ValueError, match="clip_value"):
        FusedPPOUpdate(loss, gae, optim)
    loss, gae, _ = make_test_ppo(frames=8)
    shifted = GAE(gamma=0.99, lmbda=0.95, value_network=loss.critic_network, shifted=True)
    with pytest.raises(ValueError, match="shifted"):
        FusedPPOUpdate(loss, shifted, optim)
    with pytest.raises(ValueError, match="minibatch_size"):
        FusedPPOUpdate(loss, gae, optim, minibatch_size=0)


def _manual_vs_autograd(dtype: torch.dtype, distribution: str = "tanh_normal"):
    default = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        (loss_a, gae_a, optim_a), (loss_b, gae_b, optim_b), batch = _pair(distribution, 2)
        exact = FusedPPOUpdate(loss_a, gae_a, optim_a, gradients="autograd", minibatch_size=16)
        manual = FusedPPOUpdate(loss_b, gae_b, optim_b, minibatch_size=16)
        torch.manual_seed(1)
        stats_a = exact(batch.clone())
        torch.manual_seed(1)
        stats_b = manual(batch.clone())
        return manual, stats_a, stats_b, list(loss_a.parameters()), list(loss_b.parameters())
    finally:
        torch.set_default_dtype(default)


def test_manual_gradients_equal_autograd_in_float64():
    """The hand-written derivatives are the autograd ones: 4 epochs agree to 1e-12 in float64."""
    manual, stats_a, stats_b, params_a, params_b = _manual_vs_autograd(torch.float64)
    assert manual.manual
    for a, b in zip(params_a, params_b, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    for key in PPO_STATS:
        assert stats_a[key] == pytest.approx(stats_b[key], rel=1e-10, abs=1e-12)


def test_manual_gradients_track_stock_in_float32():
    """In float32 the two differ by rounding only: one iteration (32 steps) stays within 1e-5."""
    manual, stats_a, stats_b, params_a, params_b = _manual_vs_autograd(torch.float32)
    assert manual.manual
    for a, b in zip(params_a, params_b, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    for key in PPO_STATS:
        assert stats_a[key] == pytest.approx(stats_b[key], rel=1e-3, abs=1e-6)


def test_manual_falls_back_to_autograd_for_opaque_loc_networks():
    """The ``normal`` actor squashes its mean in a wrapper module: autograd runs it, exactly."""
    (loss_a, gae_a, optim_a), (loss_b, gae_b, optim_b), batch = _pair("normal", None)
    fused = FusedPPOUpdate(loss_b, gae_b, optim_b, epochs=1, minibatch_size=16)
    assert not fused.manual
    torch.manual_seed(1)
    ppo_update(loss_a, gae_a, optim_a, batch.clone(), epochs=1, minibatch_size=16)
    torch.manual_seed(1)
    fused(batch.clone())
    for a, b in zip(loss_a.parameters(), loss_b.parameters(), strict=True):
        assert torch.equal(a, b)


def test_minibatch_remainder_and_non_adam_optimiser():
    """A batch not divisible by the minibatch size, and an optimiser run as it is (SGD)."""
    for gradients in ("autograd", "manual"):  # "manual" needs a plain Adam: autograd runs
        (loss_a, gae_a, _), (loss_b, gae_b, _), batch = _pair("tanh_normal", None, frames=40)
        optim_a = torch.optim.SGD(loss_a.parameters(), lr=1e-2)
        optim_b = torch.optim.SGD(loss_b.parameters(), lr=1e-2)
        fused = FusedPPOUpdate(
            loss_b, gae_b, optim_b, epochs=2, minibatch_size=16, gradients=gradients
        )
        assert not fused.manual
        torch.manual_seed(1)
        stock = ppo_update(loss_a, gae_a, optim_a, batch.clone(), epochs=2, minibatch_size=16)
        torch.manual_seed(1)
        assert fused(batch.clone()) == stock
        for a, b in zip(loss_a.parameters(), loss_b.parameters(), strict=True):
            assert torch.equal(a, b)


def test_env_rollout_with_truncation_matches_stock():
    """A real rollout (Pendulum truncates at 200 steps) through the real actor builders."""
    from torchrl.objectives import ClipPPOLoss

    from torchrl_mbmf.envs import make_gym_state_env
    from torchrl_mbmf.modules import make_ppo_actor_critic

    def build():
        torch.manual_seed(0)
        env = make_gym_state_env("Pendulum-v1")
        env.set_seed(0)
        actor, critic = make_ppo_actor_critic(env, hidden_sizes=(16, 16))
        loss = ClipPPOLoss(
            actor, critic, entropy_coeff=1e-4, critic_coeff=0.5, normalize_advantage=True
        )
        gae = GAE(gamma=0.99, lmbda=0.95, value_network=critic, average_gae=False)
        with torch.no_grad():
            batch = env.rollout(256, actor, break_when_any_done=False)
        return loss, gae, torch.optim.Adam(loss.parameters(), lr=3e-4), batch

    (loss_a, gae_a, optim_a, batch), (loss_b, gae_b, optim_b, _) = build(), build()
    assert batch["next", "truncated"].any()
    fused = FusedPPOUpdate(loss_b, gae_b, optim_b, epochs=1, gradients="autograd")
    torch.manual_seed(1)
    stock = ppo_update(loss_a, gae_a, optim_a, batch.clone(), epochs=1)
    torch.manual_seed(1)
    assert fused(batch.clone()) == stock
    for a, b in zip(loss_a.parameters(), loss_b.parameters(), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("gradients", ["manual", "autograd"])
def test_samplers_see_the_updated_policy(gradients):
    """Caches keyed on parameter versions (the planner's and collector's actor path) follow."""
    from torchrl_mbmf.modules.planners.sampling import ActorSampler

    torch.manual_seed(0)
    loss, gae, batch = make_test_ppo(frames=64)
    optim = torch.optim.Adam(loss.parameters(), lr=1e-2)
    update = FusedPPOUpdate(loss, gae, optim, epochs=2, minibatch_size=16, gradients=gradients)
    actor = loss.actor_network
    sampler = ActorSampler(actor)
    obs = torch.randn(4, batch["observation"].shape[-1])
    for _ in range(3):
        update(batch.clone())
        with torch.no_grad():
            td = actor.module[0](TensorDict(observation=obs, batch_size=[4]))
            fn, _ = sampler.tight_params()
            loc, scale = fn(obs)
        torch.testing.assert_close(loc, td["loc"], rtol=0, atol=0)
        torch.testing.assert_close(scale.expand_as(td["scale"]), td["scale"], rtol=0, atol=0)
