"""The fused SAC update's per-member backward of the min-Q rows equals the whole-batch one."""

from __future__ import annotations

import itertools

import pytest
import torch

from torchrl_mbmf.objectives import fused_sac


@pytest.mark.parametrize(
    ("obs_dim", "action_dim", "batch", "hidden", "act"),
    [
        (17, 6, 256, 256, "relu"),
        (3, 1, 64, 32, "relu"),
        (11, 3, 64, 64, "tanh"),
        (5, 2, 48, 16, torch.nn.functional.elu),
    ],
)
def test_min_q_backward_equals_whole_batch_backward(obs_dim, action_dim, batch, hidden, act):
    gen = torch.Generator().manual_seed(obs_dim)
    sizes = [obs_dim + action_dim, hidden, hidden, 1]
    linear = []
    for fan_in, fan_out in itertools.pairwise(sizes):
        linear += [
            torch.randn(2, fan_out, fan_in, generator=gen) / fan_in**0.5,
            torch.randn(2, fan_out, generator=gen) * 0.1,
        ]
    acts = [act, act]
    x = torch.randn(2 * batch, sizes[0], generator=gen)
    q, outs, pres = fused_sac._mlp_forward(linear, acts, x)
    # which member each actor row's min picks (the backward takes it as given)
    argmin = (torch.randperm(batch, generator=gen) % 2).long()
    d = torch.zeros_like(q)
    d[:, :batch] = torch.randn(2, batch, 1, generator=gen)
    d[:, batch:].squeeze(-1).scatter_(0, argmin.unsqueeze(0), -1.0 / batch)
    whole, whole_actions = fused_sac._mlp_backward(linear, acts, x, outs, pres, d, batch, obs_dim)
    # each member holds enough rows for the per-member path (else it falls back to the whole)
    counts = torch.bincount(argmin, minlength=2)
    assert bool((counts >= fused_sac._MIN_MEMBER_ROWS).all())
    grads, actions = fused_sac._q_backward(linear, acts, x, outs, pres, d, argmin, obs_dim)
    assert torch.equal(actions, whole_actions)
    for ours, theirs in zip(grads, whole, strict=True):
        assert torch.equal(ours, theirs)
