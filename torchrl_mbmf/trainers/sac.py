"""SAC updates: the stock ``SACLoss`` step and a fused, plain-tensor step with the same math."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import Tensor, nn
from torchrl.objectives import SACLoss, SoftUpdate

_LOG2 = float(torch.log(torch.tensor(2.0)))


def sac_update_step(
    loss: SACLoss, optimizer: torch.optim.Optimizer, target_updater: SoftUpdate
) -> Callable[[TensorDictBase], dict[str, Tensor]]:
    """The stock SAC update: ``SACLoss`` forward, one optimiser step, soft target update.

    Args:
        loss: the ``SACLoss`` (``version`` 2, no value network).
        optimizer: the optimiser over ``loss.parameters()``.
        target_updater: the ``SoftUpdate`` of ``loss``'s target Q-networks.

    Returns:
        ``step(batch) -> {"loss_actor", "loss_qvalue", "loss_alpha", "alpha"}`` (detached).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.objectives import SoftUpdate
        >>> from torchrl_mbmf.trainers.sac import make_test_sac_loss, sac_update_step
        >>> loss, batch = make_test_sac_loss(batch_size=8)
        >>> optim = torch.optim.Adam(loss.parameters(), lr=3e-4)
        >>> step = sac_update_step(loss, optim, SoftUpdate(loss, tau=0.005))
        >>> sorted(step(batch))
        ['alpha', 'loss_actor', 'loss_alpha', 'loss_qvalue']
    """

    def step(batch: TensorDictBase) -> dict[str, Tensor]:
        out = loss(batch)
        total = out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        optimizer.step()
        target_updater.step()
        return {k: out[k].detach() for k in ("loss_actor", "loss_qvalue", "loss_alpha", "alpha")}

    return step


class FusedSACUpdate:
    """The ``SACLoss`` update in plain tensor operations, the Q-ensemble as batched matmuls.

    Computes exactly the losses of the stock :class:`~torchrl.objectives.SACLoss` (version 2:
    clipped double-Q TD(0) target with the target Q-networks and the entropy term, smooth-L1 Q
    loss summed over the ensemble, reparameterised actor loss against the detached Q-networks,
    temperature loss on ``log_alpha``) on the very parameters the loss module holds, so the
    optimiser, the soft target update and checkpoints are shared with the stock path. It skips
    the tensordict plumbing and ``vmap`` of the stock loss and evaluates both Q-networks with one
    :func:`torch.baddbmm` per layer. The random draws follow the stock order (next-state action
    first, then the current-state action), so with one seed both paths give the same losses and
    gradients (tested against ``SACLoss``); ``SACLoss`` stays the reference implementation.

    Supports the networks of :func:`~torchrl_mbmf.modules.make_sac_actor_critic`: an actor
    ``MLP -> NormalParamExtractor`` with a ``TanhNormal`` (``tanh_loc=False``) and Q-networks
    that are ``MLP`` of ``Linear`` layers and parameter-free activations.

    Args:
        loss: the ``SACLoss`` (built with ``num_qvalue_nets`` Q-networks, no value network).
        optimizer: the optimiser over ``loss.parameters()``.
        target_updater: the ``SoftUpdate`` of ``loss``'s target Q-networks.

    Keyword Args:
        gamma: discount of the TD(0) target. Defaults to the loss' value estimator's gamma.
        observation_key: the observation entry. Defaults to ``"observation"``.
        action_key: the action entry. Defaults to ``"action"``.

    Examples:
        >>> import torch
        >>> from torchrl.objectives import SoftUpdate
        >>> from torchrl_mbmf.trainers.sac import FusedSACUpdate, make_test_sac_loss
        >>> loss, batch = make_test_sac_loss(batch_size=8)
        >>> optim = torch.optim.Adam(loss.parameters(), lr=3e-4)
        >>> step = FusedSACUpdate(loss, optim, SoftUpdate(loss, tau=0.005))
        >>> sorted(step(batch))
        ['alpha', 'loss_actor', 'loss_alpha', 'loss_qvalue']
    """

    def __init__(
        self,
        loss: SACLoss,
        optimizer: torch.optim.Optimizer,
        target_updater: SoftUpdate,
        *,
        gamma: float | None = None,
        observation_key: Any = "observation",
        action_key: Any = "action",
    ) -> None:
        if getattr(loss, "_version", 2) != 2:
            raise ValueError("FusedSACUpdate supports SACLoss without a value network (v2)")
        self.loss = loss
        self.optimizer = optimizer
        self.target_updater = target_updater
        self.observation_key = observation_key
        self.action_key = action_key
        self.gamma = float(loss.value_estimator.gamma if gamma is None else gamma)
        self._policy_net = _find_policy_net(loss.actor_network)
        layers = _q_layers(loss.qvalue_network)
        # Parameters are updated in place (optimiser, SoftUpdate, load_state_dict), so the
        # tensors can be looked up once.
        self._q_params = _stack(loss.qvalue_network_params, layers)
        self._q_detached = [t if callable(t) else t.detach() for t in self._q_params]
        self._q_target = _stack(loss.target_qvalue_network_params, layers)
        low, high = _action_bounds(loss.actor_network)
        self._affine_loc = (high + low) / 2
        self._affine_scale = (high - low) / 2
        self._log_affine = self._affine_scale.abs().log().sum()

    # ------------------------------------------------------------------ pieces
    @staticmethod
    def _q(params: list[Any], obs: Tensor, action: Tensor) -> Tensor:
        """Q-values of every ensemble member, ``[n_q, B]``."""
        x = torch.cat([obs, action], -1)
        n = params[0].shape[0]
        h = x.unsqueeze(0).expand(n, *x.shape)
        i = 0
        while i < len(params):
            if callable(params[i]):
                h = params[i](h)
                i += 1
            else:
                h = torch.baddbmm(params[i + 1].unsqueeze(1), h, params[i].transpose(1, 2))
                i += 2
        return h.squeeze(-1)

    def _sample(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        """Reparameterised TanhNormal action and its log-probability."""
        loc, scale = self._policy_net(obs)
        eps = torch.randn_like(loc)
        pre = loc + scale * eps
        log_prob = (-0.5 * eps.pow(2) - scale.log() - 0.5 * _LOG2PI).sum(-1)
        log_prob = log_prob - (2.0 * (_LOG2 - pre - F.softplus(-2.0 * pre))).sum(-1)
        action = pre.tanh() * self._affine_scale + self._affine_loc
        return action, log_prob - self._log_affine

    def losses(
        self, obs: Tensor, action: Tensor, reward: Tensor, next_obs: Tensor, terminated: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The SAC losses of one batch of tensors.

        Args:
            obs: observations ``[B, obs_dim]``.
            action: actions taken ``[B, action_dim]``.
            reward: rewards ``[B]``.
            next_obs: next observations ``[B, obs_dim]``.
            terminated: terminal flags ``[B]`` (bool).

        Returns:
            ``(loss_actor, loss_qvalue, loss_alpha, log_prob)`` (``log_prob`` detached, ``[B]``).
        """
        loss = self.loss
        alpha = loss.log_alpha.detach().exp()
        with torch.no_grad():
            next_action, next_log_prob = self._sample(next_obs)
            next_q = self._q(self._q_target, next_obs, next_action)
            next_value = (next_q - alpha * next_log_prob).min(0).values
            target = reward + self.gamma * (~terminated).to(reward.dtype) * next_value
        pred = self._q(self._q_params, obs, action)
        loss_qvalue = F.smooth_l1_loss(pred, target.expand_as(pred), reduction="none")
        loss_qvalue = loss_qvalue.sum(0).mean()
        new_action, log_prob = self._sample(obs)
        q_pi = self._q(self._q_detached, obs, new_action).min(0).values
        loss_actor = (alpha * log_prob - q_pi).mean()
        log_prob = log_prob.detach()
        loss_alpha = (-loss.log_alpha * (log_prob + loss.target_entropy)).mean()
        return loss_actor, loss_qvalue, loss_alpha, log_prob

    def __call__(self, batch: TensorDictBase) -> dict[str, Tensor]:
        """One update on a replay-buffer batch (``[B]``); returns the detached losses."""
        loss_actor, loss_qvalue, loss_alpha, _ = self.losses(
            batch.get(self.observation_key),
            batch.get(self.action_key),
            batch.get(("next", "reward")).squeeze(-1),
            batch.get(("next", self.observation_key)),
            batch.get(("next", "terminated")).squeeze(-1),
        )
        self.optimizer.zero_grad(set_to_none=True)
        (loss_actor + loss_qvalue + loss_alpha).backward()
        self.optimizer.step()
        self.target_updater.step()
        return {
            "loss_actor": loss_actor.detach(),
            "loss_qvalue": loss_qvalue.detach(),
            "loss_alpha": loss_alpha.detach(),
            "alpha": self.loss.log_alpha.detach().exp(),
        }


_LOG2PI = float(torch.log(torch.tensor(2.0 * torch.pi)))


def _find_policy_net(actor: nn.Module) -> nn.Module:
    for module in actor.modules():
        if isinstance(module, TensorDictModule) and list(module.out_keys) == ["loc", "scale"]:
            net = module.module
            if not any(isinstance(m, NormalParamExtractor) for m in net.modules()):
                break
            return net
    raise ValueError(
        "FusedSACUpdate expects an actor with a TensorDictModule writing ['loc', 'scale'] "
        "through a NormalParamExtractor (see make_sac_actor_critic)"
    )


def _stack(params: TensorDictBase, layers: list[tuple[str, Any]]) -> list[Any]:
    out: list[Any] = []
    for kind, key in layers:
        if kind == "linear":
            out += [params.get((*key, "weight")), params.get((*key, "bias"))]
        else:
            out.append(key)
    return out


def _q_layers(qvalue: nn.Module) -> list[tuple[str, Any]]:
    net = qvalue.module if isinstance(qvalue, TensorDictModule) else qvalue
    layers: list[tuple[str, Any]] = []
    for name, module in net.named_children():
        if isinstance(module, nn.Linear):
            layers.append(("linear", ("module", name)))
        elif next(module.parameters(), None) is None:
            layers.append(("fn", module))
        else:
            raise ValueError(f"FusedSACUpdate: unsupported Q-network layer {name}: {module}")
    if not layers or layers[0][0] != "linear":
        raise ValueError("FusedSACUpdate expects a Q-network MLP starting with nn.Linear")
    return layers


def _action_bounds(actor: nn.Module) -> tuple[Tensor, Tensor]:
    kwargs: dict[str, Any] = {}
    for module in actor.modules():
        if getattr(module, "distribution_kwargs", None) is not None:
            kwargs = module.distribution_kwargs
            break
    if kwargs.get("tanh_loc", False):
        raise ValueError("FusedSACUpdate expects TanhNormal with tanh_loc=False")
    low = torch.as_tensor(kwargs.get("low", -1.0), dtype=torch.float32)
    high = torch.as_tensor(kwargs.get("high", 1.0), dtype=torch.float32)
    return low, high


def make_test_sac_loss(
    batch_size: int = 8, obs_dim: int = 3, action_dim: int = 2, hidden: int = 16
) -> tuple[SACLoss, TensorDictBase]:
    """A small ``SACLoss`` and a random replay batch, for examples and tests.

    Args:
        batch_size: batch size. Defaults to 8.
        obs_dim: observation size. Defaults to 3.
        action_dim: action size. Defaults to 2.
        hidden: hidden width (two layers). Defaults to 16.

    Returns:
        ``(loss, batch)``.

    Examples:
        >>> from torchrl_mbmf.trainers.sac import make_test_sac_loss
        >>> loss, batch = make_test_sac_loss(batch_size=4)
        >>> batch.batch_size
        torch.Size([4])
    """
    from tensordict import TensorDict
    from torchrl.data import Bounded
    from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator

    spec = Bounded(-2.0, 2.0, (action_dim,))
    net = nn.Sequential(
        MLP(in_features=obs_dim, out_features=2 * action_dim, num_cells=[hidden, hidden]),
        NormalParamExtractor(scale_mapping="biased_softplus_1.0", scale_lb=1e-4),
    )
    actor = ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high, "tanh_loc": False},
        return_log_prob=True,
    )
    qvalue = ValueOperator(
        MLP(in_features=obs_dim + action_dim, out_features=1, num_cells=[hidden, hidden]),
        in_keys=["observation", "action"],
    )
    loss = SACLoss(actor, qvalue, num_qvalue_nets=2, action_spec=spec)
    loss.make_value_estimator(gamma=0.99)
    b = batch_size
    batch = TensorDict(
        {
            "observation": torch.randn(b, obs_dim),
            "action": torch.rand(b, action_dim) * 4 - 2,
            "next": {
                "observation": torch.randn(b, obs_dim),
                "reward": torch.randn(b, 1),
                "done": torch.rand(b, 1) < 0.2,
                "terminated": torch.rand(b, 1) < 0.2,
            },
        },
        batch_size=[b],
    )
    return loss, batch
