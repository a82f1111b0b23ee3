"""The thesis PPO update: GAE once per batch, several epochs of shuffled minibatches."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

#: Loss entries averaged into the logged statistics.
PPO_STATS: tuple[str, ...] = ("loss_objective", "loss_critic", "loss_entropy", "kl_approx")


def ppo_update(
    loss: ClipPPOLoss,
    gae: GAE,
    optimizer: torch.optim.Optimizer,
    batch: TensorDictBase,
    *,
    epochs: int = 4,
    minibatch_size: int = 32,
    max_grad_norm: float | None = 0.5,
) -> dict[str, float]:
    """One PPO iteration on a collected batch (thesis table 6 defaults).

    GAE is computed once on the whole batch (its time structure intact), then the flattened
    batch is shuffled every epoch and cut into minibatches; each minibatch takes one step of
    ``optimizer`` on ``loss_objective + loss_critic + loss_entropy`` with gradient clipping.

    Args:
        loss: the stock ``ClipPPOLoss``.
        gae: the advantage module (writes ``advantage`` and ``value_target``).
        optimizer: the optimiser over ``loss.parameters()``.
        batch: a collector batch ``[*B, T]`` with ``action_log_prob``.

    Keyword Args:
        epochs: passes over the batch. Defaults to 4.
        minibatch_size: transitions per gradient step. Defaults to 32.
        max_grad_norm: gradient-norm clip, ``None`` for none. Defaults to 0.5.

    Returns:
        The mean of each of :data:`PPO_STATS` over the iteration.

    Examples:
        >>> import torch
        >>> from torchrl.collectors import Collector
        >>> from torchrl.objectives import ClipPPOLoss
        >>> from torchrl.objectives.value import GAE
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import make_ppo_actor_critic
        >>> from torchrl_mbmf.trainers.ppo import ppo_update
        >>> env = make_gym_state_env("Pendulum-v1")
        >>> actor, critic = make_ppo_actor_critic(env, hidden_sizes=(16, 16))
        >>> loss = ClipPPOLoss(actor, critic)
        >>> gae = GAE(gamma=0.99, lmbda=0.95, value_network=critic)
        >>> optim = torch.optim.Adam(loss.parameters(), lr=3e-4)
        >>> with torch.no_grad():
        ...     batch = env.rollout(64, actor)
        >>> stats = ppo_update(loss, gae, optim, batch, epochs=1, minibatch_size=32)
        >>> sorted(stats)
        ['kl_approx', 'loss_critic', 'loss_entropy', 'loss_objective']
    """
    with torch.no_grad():
        gae(batch)
    flat = batch.reshape(-1)
    n = flat.shape[0]
    sums: dict[str, float] = {}
    steps = 0
    params = list(loss.parameters())
    for _ in range(epochs):
        perm = torch.randperm(n)
        for i in range(0, n, minibatch_size):
            out = loss(flat[perm[i : i + minibatch_size]])
            total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
            optimizer.zero_grad(set_to_none=True)
            total.backward()
            if max_grad_norm is not None:
                torch.nn.utils.clip_grad_norm_(params, max_grad_norm)
            optimizer.step()
            steps += 1
            for key in PPO_STATS:
                value = out.get(key, None)
                if value is not None:
                    sums[key] = sums.get(key, 0.0) + float(value.detach())
    return {key: value / steps for key, value in sums.items()}
