"""The fused SAC update computes what the stock SACLoss computes."""

from __future__ import annotations

import pytest
import torch
from torchrl.objectives import SoftUpdate

from torchrl_mbmf.trainers.sac import FusedSACUpdate, make_test_sac_loss, sac_update_step


def _fused_losses(fused: FusedSACUpdate, batch):
    return fused.losses(
        batch["observation"],
        batch["action"],
        batch["next", "reward"].squeeze(-1),
        batch["next", "observation"],
        batch["next", "terminated"].squeeze(-1),
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_fused_losses_and_grads_match_sacloss(seed):
    torch.manual_seed(seed)
    loss, batch = make_test_sac_loss(batch_size=64, obs_dim=5, action_dim=3, hidden=32)
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


def test_fused_rejects_unsupported_q_network():
    loss, _ = make_test_sac_loss()
    loss.qvalue_network.module = torch.nn.Sequential(torch.nn.BatchNorm1d(4))
    with pytest.raises(ValueError, match="unsupported Q-network layer"):
        FusedSACUpdate(loss, torch.optim.Adam(loss.parameters()), SoftUpdate(loss, tau=0.1))
