"""The fused SAC update computes what the stock SACLoss computes."""

from __future__ import annotations

import pytest
import torch
from rl_helpers import make_test_sac_loss
from torchrl.objectives import SoftUpdate

from torchrl_mbmf.modules.log_std import ClampedLogStdExtractor
from torchrl_mbmf.objectives.fused_sac import FusedSACUpdate, sac_update_step


def _fused_losses(fused: FusedSACUpdate, batch):
    return fused.losses(
        batch["observation"],
        batch["action"],
        batch["next", "reward"].squeeze(-1),
        batch["next", "observation"],
        batch["next", "terminated"].squeeze(-1),
    )


@pytest.mark.parametrize("loss_function", ["smooth_l1", "l2", "l1"])
@pytest.mark.parametrize("seed", [0, 1])
def test_fused_losses_and_grads_match_sacloss(seed, loss_function):
    torch.manual_seed(seed)
    loss, batch = make_test_sac_loss(
        batch_size=64, obs_dim=5, action_dim=3, hidden=32, loss_function=loss_function
    )
    batch["next", "reward"] *= 3.0  # TD errors on both sides of smooth_l1's kink
    with torch.no_grad():
        loss.log_alpha.fill_(-0.7)
    fused = FusedSACUpdate(loss, torch.optim.Adam(loss.parameters()), SoftUpdate(loss, tau=0.1))
    params = list(loss.parameters())
    torch.manual_seed(100 + seed)
    out = loss(batch.clone())
    stock = [out["loss_actor"], out["loss_qvalue"], out["loss_alpha"]]
    stock_grads = torch.autograd.grad(sum(stock), params)
    torch.manual_seed(100 + seed)
    actor, qvalue, alpha, _ = _fused_losses(fused, batch)
    fused_grads = torch.autograd.grad(actor + qvalue + alpha, params)
    for a, b in zip(stock, (actor, qvalue, alpha), strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    for a, b in zip(stock_grads, fused_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-6)


def test_fused_updates_track_stock_updates():
    def run(fused: bool):
        torch.manual_seed(0)
        loss, batch = make_test_sac_loss(batch_size=32, hidden=16)
        optim = torch.optim.Adam(loss.parameters(), lr=1e-3)
        updater = SoftUpdate(loss, tau=0.05)
        step = (FusedSACUpdate if fused else sac_update_step)(loss, optim, updater)
        for _ in range(5):
            step(batch)
        return loss.state_dict()

    stock, fused = run(False), run(True)
    assert stock.keys() == fused.keys()
    for key in stock:
        torch.testing.assert_close(stock[key], fused[key], rtol=1e-4, atol=1e-5)


def test_fused_rejects_an_unsupported_q_distance():
    loss, _ = make_test_sac_loss()
    loss.loss_function = "huber"
    with pytest.raises(ValueError, match=r"loss_function.*'huber'"):
        FusedSACUpdate(loss, torch.optim.Adam(loss.parameters()), SoftUpdate(loss, tau=0.1))


def test_fused_rejects_unsupported_q_network():
    loss, _ = make_test_sac_loss()
    loss.qvalue_network.module = torch.nn.Sequential(torch.nn.BatchNorm1d(4))
    with pytest.raises(ValueError, match="unsupported Q-network layer"):
        FusedSACUpdate(loss, torch.optim.Adam(loss.parameters()), SoftUpdate(loss, tau=0.1))


def _batch_args(batch):
    return (
        batch["observation"],
        batch["action"],
        batch["next", "reward"],
        batch["next", "observation"],
        batch["next", "terminated"],
    )


def assert_fused_update_matches_sacloss(loss, batch, seed: int) -> None:
    """One fused update (lr=0) gives SACLoss' losses, temperature and gradients, same draws."""
    params = list(loss.parameters())
    torch.manual_seed(seed)
    out = loss(batch.clone())
    stock = [out["loss_actor"], out["loss_qvalue"], out["loss_alpha"]]
    stock_grads = torch.autograd.grad(sum(stock), params)
    # lr=0: the step leaves the parameters as they are and their gradients in place
    fused = FusedSACUpdate(loss, torch.optim.SGD(params, lr=0.0), SoftUpdate(loss, tau=0.1))
    torch.manual_seed(seed)
    got = fused.update(*_batch_args(batch))
    for key, value in zip(("loss_actor", "loss_qvalue", "loss_alpha"), stock, strict=True):
        torch.testing.assert_close(got[key], value.detach(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got["alpha"], loss.log_alpha.detach().exp())
    for (name, p), g in zip(loss.named_parameters(), stock_grads, strict=True):
        assert p.grad is not None, name
        torch.testing.assert_close(p.grad, g, rtol=1e-4, atol=1e-6, msg=name)


@pytest.mark.parametrize("loss_function", ["smooth_l1", "l2", "l1"])
@pytest.mark.parametrize("activation", [torch.nn.ReLU, torch.nn.Tanh, torch.nn.ELU])
@pytest.mark.parametrize("seed", [0, 1])
def test_fused_update_gradients_match_sacloss(activation, seed, loss_function):
    """The hand-written Q backward + autograd actor give SACLoss' losses and gradients."""
    torch.manual_seed(seed)
    loss, batch = make_test_sac_loss(
        batch_size=64,
        obs_dim=5,
        action_dim=3,
        hidden=32,
        activation=activation,
        loss_function=loss_function,
    )
    batch["next", "reward"] *= 3.0  # TD errors on both sides of smooth_l1's kink
    with torch.no_grad():
        loss.log_alpha.fill_(-0.7)
    assert_fused_update_matches_sacloss(loss, batch, seed=100 + seed)


@pytest.mark.parametrize("seed", [0, 1])
def test_fused_update_with_the_clamped_log_std_head_matches_sacloss(seed):
    """SB3's scale (exp of a log-std clamped to [-20, 2]) goes through the fused path unchanged:
    same losses and gradients as SACLoss, with log-stds on both sides of the clamp."""
    torch.manual_seed(seed)
    loss, batch = make_test_sac_loss(
        batch_size=64, obs_dim=5, action_dim=3, hidden=32, head=ClampedLogStdExtractor()
    )
    with torch.no_grad():  # push part of the log-std head above the upper bound
        last = loss.actor_network_params["module", "0", "module", "0", "4", "bias"]
        last[3:].fill_(2.5)
    assert_fused_update_matches_sacloss(loss, batch, seed=100 + seed)


def test_fused_update_consumes_the_stock_random_stream():
    """After an update, the global RNG is where the stock update leaves it."""
    loss, batch = make_test_sac_loss(batch_size=16)
    optim = torch.optim.Adam(loss.parameters())
    torch.manual_seed(3)
    sac_update_step(loss, optim, SoftUpdate(loss, tau=0.1))(batch)
    stock = torch.rand(4)
    torch.manual_seed(3)
    FusedSACUpdate(loss, optim, SoftUpdate(loss, tau=0.1))(batch)
    torch.testing.assert_close(torch.rand(4), stock, rtol=0, atol=0)


def test_fused_target_update_is_soft_update():
    """The fused lerp of the target Q-parameters is bit-identical to SoftUpdate.step."""
    torch.manual_seed(0)
    loss, _ = make_test_sac_loss()
    updater = SoftUpdate(loss, tau=0.05)
    fused = FusedSACUpdate(loss, torch.optim.Adam(loss.parameters()), updater)
    with torch.no_grad():
        for p in loss.qvalue_network_params.values(True, True):
            p.add_(torch.randn_like(p))
    before = loss.target_qvalue_network_params.clone()
    updater.step()
    stock = loss.target_qvalue_network_params.clone()
    loss.target_qvalue_network_params.update_(before)
    fused._target_step()
    for key in stock.keys(True, True):
        assert torch.equal(loss.target_qvalue_network_params[key], stock[key]), key


@pytest.mark.parametrize("adam", [{}, {"fused": True}, {"foreach": True}])
def test_fused_updates_track_stock_updates_relu(adam):
    """Ten updates (ReLU nets; default, fused or foreach Adam) stay on the stock trajectory."""

    def run(use_fused: bool, **kwargs):
        torch.manual_seed(0)
        loss, batch = make_test_sac_loss(batch_size=32, hidden=16, activation=torch.nn.ReLU)
        optim = torch.optim.Adam(loss.parameters(), lr=1e-3, **kwargs)
        updater = SoftUpdate(loss, tau=0.05)
        step = (FusedSACUpdate if use_fused else sac_update_step)(loss, optim, updater)
        for _ in range(10):
            step(batch)
        return loss.state_dict()

    stock, fused = run(False), run(True, **adam)
    for key in stock:
        torch.testing.assert_close(stock[key], fused[key], rtol=1e-4, atol=1e-5, msg=key)


def _filled_buffer(n: int = 50, capacity: int = 1000, batch_size: int = 8):
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity), batch_size=batch_size)
    _, batch = make_test_sac_loss(batch_size=n)
    buffer.extend(batch)
    assert isinstance(batch, TensorDict)
    return buffer, batch


def test_replay_sampler_draws_the_stock_rows():
    from torchrl_mbmf.data import ReplaySampler

    buffer, _ = _filled_buffer()
    loss, _ = make_test_sac_loss()
    keys = FusedSACUpdate(loss, torch.optim.Adam(loss.parameters()), SoftUpdate(loss, tau=0.1))
    sampler = ReplaySampler(buffer, keys.batch_keys)
    for step in range(3):
        torch.manual_seed(step)
        stock = buffer.sample()
        torch.manual_seed(step)
        fast = sampler()
        for key, value in zip(keys.batch_keys, fast, strict=True):
            assert torch.equal(value, stock.get(key)), key
        # the buffer grows between draws (the storage views stay valid)
        _, more = make_test_sac_loss(batch_size=5)
        buffer.extend(more)


def test_replay_sampler_follows_a_reloaded_buffer():
    """Emptying and refilling (what the replay checkpoint adapter does) is picked up."""
    from torchrl_mbmf.data import ReplaySampler

    buffer, _ = _filled_buffer(n=40)
    sampler = ReplaySampler(buffer, ["observation"], batch_size=64)
    sampler()
    saved = buffer.storage[:20].clone()
    buffer.empty()
    buffer.extend(saved)
    torch.manual_seed(0)
    (obs,) = sampler()
    torch.manual_seed(0)
    assert torch.equal(obs, buffer.sample(64)["observation"])
    assert obs.shape == (64, 3)


def test_replay_sampler_rejects_bad_input():
    from torchrl.data import LazyTensorStorage, SamplerWithoutReplacement, TensorDictReplayBuffer

    from torchrl_mbmf.data import ReplaySampler

    buffer, _ = _filled_buffer()
    with pytest.raises(ValueError, match="positive batch_size"):
        ReplaySampler(buffer, ["observation"], batch_size=0)
    other = TensorDictReplayBuffer(
        storage=LazyTensorStorage(10), sampler=SamplerWithoutReplacement(), batch_size=2
    )
    with pytest.raises(ValueError, match="RandomSampler"):
        ReplaySampler(other, ["observation"])
    with pytest.raises(RuntimeError, match="empty"):
        ReplaySampler(TensorDictReplayBuffer(storage=LazyTensorStorage(10)), ["x"], batch_size=2)()


def test_fused_update_autograd_actor_fallback_matches_sacloss(monkeypatch):
    """An actor the update cannot split into MLP + head goes through autograd, same gradients."""
    monkeypatch.setattr("torchrl_mbmf.objectives.fused_sac._split_policy", lambda net: None)
    torch.manual_seed(0)
    loss, batch = make_test_sac_loss(batch_size=32, hidden=16, activation=torch.nn.ReLU)
    params = list(loss.parameters())
    torch.manual_seed(5)
    out = loss(batch.clone())
    stock_grads = torch.autograd.grad(
        out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"], params
    )
    fused = FusedSACUpdate(loss, torch.optim.SGD(params, lr=0.0), SoftUpdate(loss, tau=0.1))
    torch.manual_seed(5)
    fused.update(*_batch_args(batch))
    for (name, p), g in zip(loss.named_parameters(), stock_grads, strict=True):
        torch.testing.assert_close(p.grad, g, rtol=1e-4, atol=1e-6, msg=name)


def test_keep_freed_memory():
    import platform

    from torchrl_mbmf.device import keep_freed_memory

    applied = keep_freed_memory()
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert applied
    with pytest.raises(ValueError, match="positive"):
        keep_freed_memory(0)
