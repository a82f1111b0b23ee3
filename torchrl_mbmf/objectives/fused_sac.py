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

from torchrl_mbmf.modules.mlp import activate, affine, plain_layers

__all__ = ["FusedSACUpdate", "sac_update_step"]

_LOG2 = float(torch.log(torch.tensor(2.0)))
#: ``SACLoss(loss_function=...)`` values the fused update reproduces: each distance (as
#: torchrl's ``distance_loss`` computes it) and its derivative in the prediction error.
_Q_DISTANCES: dict[str, Callable[..., Tensor]] = {
    "smooth_l1": F.smooth_l1_loss,
    "l2": F.mse_loss,
    "l1": F.l1_loss,
}
_Q_DISTANCE_GRADS: dict[str, Callable[[Tensor], Tensor]] = {
    "smooth_l1": lambda d: d.clamp(-1.0, 1.0),  # beta = 1: the clipped difference
    "l2": lambda d: 2.0 * d,
    "l1": torch.sign,
}


def _q_distance(name: str) -> tuple[Callable[..., Tensor], Callable[[Tensor], Tensor]]:
    """The distance ``SACLoss(loss_function=name)`` computes and its derivative."""
    if name not in _Q_DISTANCES:
        raise ValueError(
            f"FusedSACUpdate supports SACLoss(loss_function=...) in {sorted(_Q_DISTANCES)}; "
            f"got {name!r} (use the stock update for it)"
        )
    return _Q_DISTANCES[name], _Q_DISTANCE_GRADS[name]


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
        >>> from torchrl.objectives import SACLoss, SoftUpdate
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.modules import make_sac_actor_critic
        >>> from torchrl_mbmf.objectives.fused_sac import sac_update_step
        >>> env = make_env("Pendulum-v1", seed=0)
        >>> actor, qvalue = make_sac_actor_critic(env, hidden_sizes=(16, 16))
        >>> loss = SACLoss(actor, qvalue, action_spec=env.action_spec_unbatched)
        >>> loss.make_value_estimator(gamma=0.99)
        >>> with torch.no_grad():
        ...     batch = env.rollout(8, actor)
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

    The losses of the stock :class:`~torchrl.objectives.SACLoss` (version 2, its Q distance
    ``smooth_l1``, ``l2`` or ``l1``) on the loss's own parameters, so the optimiser, the soft
    target update and checkpoints are shared with the stock path. :meth:`update` writes both
    networks' backward by hand; :meth:`losses` is the same math through autograd; random
    draws follow the stock order; tested equal to ``SACLoss`` on the networks of
    :func:`~torchrl_mbmf.modules.make_sac_actor_critic`. See ``docs/design/fused_updates.md``.

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
        >>> from torchrl.objectives import SACLoss, SoftUpdate
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.modules import make_sac_actor_critic
        >>> env = make_env("Pendulum-v1", seed=0)
        >>> actor, qvalue = make_sac_actor_critic(env, hidden_sizes=(16, 16))
        >>> loss = SACLoss(actor, qvalue, action_spec=env.action_spec_unbatched)
        >>> loss.make_value_estimator(gamma=0.99)
        >>> optim = torch.optim.Adam(loss.parameters(), lr=3e-4)
        >>> step = FusedSACUpdate(loss, optim, SoftUpdate(loss, tau=0.005))
        >>> with torch.no_grad():
        ...     batch = env.rollout(8, actor)
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
        self._distance, self._distance_grad = _q_distance(loss.loss_function)
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
        self._q_linear = [t for t in self._q_params if not callable(t)]
        self._q_target_linear = [t for t in self._q_target if not callable(t)]
        self._q_acts = _activations(layers)
        # The actor's MLP by hand as well when it is Sequential(MLP, NormalParamExtractor)
        # (autograd then only runs through the head and the TanhNormal sample).
        self._actor = _split_policy(self._policy_net)
        # With both networks by hand every parameter's gradient is assigned afresh each update;
        # when the optimiser holds exactly those, its zero_grad (freeing them) can be skipped.
        assigned = [loss.log_alpha, *self._q_linear]
        if self._actor is not None:
            assigned += self._actor[0]
        held = [p for group in optimizer.param_groups for p in group["params"]]
        self._assigns_all_grads = self._actor is not None and {id(p) for p in held} == {
            id(p) for p in assigned
        }
        self._lerp_weight = _soft_update_weight(target_updater, loss)

    def _sample(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        """Reparameterised TanhNormal action and its log-probability."""
        return self._tanh_normal(*self._policy_net(obs))

    def _tanh_normal(self, loc: Tensor, scale: Tensor) -> tuple[Tensor, Tensor]:
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
            next_q = _q_ensemble(self._q_target, next_obs, next_action)
            next_value = (next_q - alpha * next_log_prob).min(0).values
            target = reward + self.gamma * (~terminated).to(reward.dtype) * next_value
        pred = _q_ensemble(self._q_params, obs, action)
        loss_qvalue = self._distance(pred, target.expand_as(pred), reduction="none")
        loss_qvalue = loss_qvalue.sum(0).mean()
        new_action, log_prob = self._sample(obs)
        q_pi = _q_ensemble(self._q_detached, obs, new_action).min(0).values
        loss_actor = (alpha * log_prob - q_pi).mean()
        log_prob = log_prob.detach()
        loss_alpha = (-loss.log_alpha * (log_prob + loss.target_entropy)).mean()
        return loss_actor, loss_qvalue, loss_alpha, log_prob

    def update(
        self, obs: Tensor, action: Tensor, reward: Tensor, next_obs: Tensor, terminated: Tensor
    ) -> dict[str, Tensor]:
        """One update on a batch of tensors: the losses, their gradients, the step, the targets.

        Args:
            obs: observations ``[B, obs_dim]``.
            action: actions taken ``[B, action_dim]``.
            reward: rewards ``[B]`` or ``[B, 1]``.
            next_obs: next observations ``[B, obs_dim]``.
            terminated: terminal flags ``[B]`` or ``[B, 1]`` (bool).

        Returns:
            ``{"loss_actor", "loss_qvalue", "loss_alpha", "alpha"}``: 0-dim detached tensors
            (no host synchronisation; average them when logging).

        Examples:
            >>> import torch
            >>> from torchrl.objectives import SACLoss, SoftUpdate
            >>> from torchrl_mbmf.envs import make_env
            >>> from torchrl_mbmf.modules import make_sac_actor_critic
            >>> env = make_env("Pendulum-v1", seed=1)
            >>> actor, qvalue = make_sac_actor_critic(env, hidden_sizes=(16, 16))
            >>> loss = SACLoss(actor, qvalue, action_spec=env.action_spec_unbatched)
            >>> loss.make_value_estimator(gamma=0.99)
            >>> optim = torch.optim.Adam(loss.parameters())
            >>> step = FusedSACUpdate(loss, optim, SoftUpdate(loss, tau=0.005))
            >>> with torch.no_grad():
            ...     batch = env.rollout(8, actor)
            >>> out = step.update(*(batch.get(k) for k in step.batch_keys))
            >>> out["loss_qvalue"].shape
            torch.Size([])
        """
        loss = self.loss
        log_alpha = loss.log_alpha
        batch = obs.shape[0]
        reward = reward.reshape(batch)
        terminated = terminated.reshape(batch)
        acts = self._q_acts
        with torch.no_grad():
            alpha = log_alpha.exp()
            if self._actor is None:
                next_action, next_log_prob = self._sample(next_obs)
            else:
                # the actor's trunk on both batches at once (its rows are independent)
                a_params, a_lin, a_acts, head = self._actor
                a_out, a_outs, a_pres = _mlp_forward(a_lin, a_acts, torch.cat([obs, next_obs]))
                next_action, next_log_prob = self._tanh_normal(*head(a_out[0, batch:]))
            next_x = torch.cat([next_obs, next_action], -1)
            next_q = _mlp_forward(self._q_target_linear, acts, next_x)[0].squeeze(-1)
            next_value = (next_q - alpha * next_log_prob).min(0).values
            target = reward + self.gamma * (~terminated).to(reward.dtype) * next_value
        if self._actor is None:
            new_action, log_prob = self._sample(obs)
        else:
            policy_out = a_out[0, :batch].detach().requires_grad_()
            new_action, log_prob = self._tanh_normal(*head(policy_out))
        with torch.no_grad():
            x = torch.cat(
                [torch.cat([obs, action], -1), torch.cat([obs, new_action.detach()], -1)], 0
            )
            q, outs, pres = _mlp_forward(self._q_linear, acts, x)
            q = q.squeeze(-1)
            diff = q[:, :batch] - target
            loss_qvalue = self._distance(diff, torch.zeros_like(diff), reduction="none")
            loss_qvalue = loss_qvalue.sum(0).mean()
            q_pi, argmin = q[:, batch:].min(0)
            scale = 1.0 / batch
            grad = torch.zeros_like(q)
            grad[:, :batch] = self._distance_grad(diff).mul_(scale)
            grad[:, batch:].scatter_(0, argmin.unsqueeze(0), -scale)
            q_grads, action_grad = _q_backward(
                self._q_linear, acts, x, outs, pres, grad.unsqueeze(-1), argmin, obs.shape[-1]
            )
            log_prob_d = log_prob.detach()
            loss_actor = (alpha * log_prob_d - q_pi).mean()
            loss_alpha = (-log_alpha * (log_prob_d + loss.target_entropy)).mean()
            alpha_grad = -(log_prob_d + loss.target_entropy).mean()
        if not self._assigns_all_grads:
            self.optimizer.zero_grad(set_to_none=True)
        torch.autograd.backward(
            [log_prob, new_action],
            [(alpha * scale).expand_as(log_prob), action_grad],
        )
        if self._actor is not None:
            with torch.no_grad():
                a_outs = [t[:, :batch] for t in a_outs]
                a_pres = [None if t is None else t[:, :batch] for t in a_pres]
                a_grads, _ = _mlp_backward(
                    a_lin, a_acts, obs, a_outs, a_pres, policy_out.grad.unsqueeze(0), batch
                )
            for param, g in zip(a_params, a_grads, strict=True):
                param.grad = g.view_as(param)
        for param, g in zip(self._q_linear, q_grads, strict=True):
            param.grad = g.view_as(param)
        log_alpha.grad = alpha_grad.reshape(log_alpha.shape).to(log_alpha.dtype)
        self.optimizer.step()
        self._target_step()
        return {
            "loss_actor": loss_actor,
            "loss_qvalue": loss_qvalue,
            "loss_alpha": loss_alpha,
            "alpha": log_alpha.detach().exp(),
        }

    def _target_step(self) -> None:
        if self._lerp_weight is None or not self.target_updater.initialized:
            self.target_updater.step()
            return
        with torch.no_grad():
            torch._foreach_lerp_(self._q_target_linear, self._q_linear, self._lerp_weight)

    @property
    def batch_keys(self) -> tuple[Any, ...]:
        """The batch entries :meth:`update` takes, in its argument order."""
        obs, action = self.observation_key, self.action_key
        obs_next = ("next", *obs) if isinstance(obs, tuple) else ("next", obs)
        return obs, action, ("next", "reward"), obs_next, ("next", "terminated")

    def __call__(self, batch: TensorDictBase) -> dict[str, Tensor]:
        """One update on a replay-buffer batch (``[B]``); see :meth:`update`."""
        return self.update(*(batch.get(key) for key in self.batch_keys))


def _q_ensemble(params: list[Any], obs: Tensor, action: Tensor) -> Tensor:
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
            h = affine(h, params[i].transpose(1, 2), params[i + 1].unsqueeze(1))
            i += 2
    return h.squeeze(-1)


def _soft_update_weight(target_updater: SoftUpdate, loss: SACLoss) -> float | None:
    """The lerp weight of a stock ``SoftUpdate`` of the Q-networks only, else ``None``.

    The soft target update then runs as plain in-place lerps (what ``SoftUpdate.step`` does,
    without the tensordict traversal).
    """
    if (
        type(target_updater) is SoftUpdate
        and target_updater.loss_module is loss
        and not getattr(loss, "delay_actor", False)
        and getattr(loss, "delay_qvalue", True)
    ):
        return 1.0 - float(target_updater.eps)
    return None


def _mlp_forward(
    linear: list[Tensor], acts: list[Any], x: Tensor
) -> tuple[Tensor, list[Tensor], list[Tensor | None]]:
    """An ensemble MLP ``[n, N, out]`` on shared inputs ``x`` ``[N, in]``; weights ``[n, o, i]``.

    Also returns the hidden outputs and, for generic activations, their inputs (what
    :func:`_mlp_backward` needs).
    """
    n = linear[0].shape[0]
    h = x.unsqueeze(0).expand(n, *x.shape)
    outs: list[Tensor] = []
    pres: list[Tensor | None] = []
    for i, act in enumerate(acts):
        z = affine(h, linear[2 * i].transpose(1, 2), linear[2 * i + 1].unsqueeze(1))
        # relu and tanh in place on the fresh output (their backward reads the output only)
        h = activate(z, act, inplace=True)
        outs.append(h)
        pres.append(None if act in ("relu", "tanh") else z)
    out = affine(h, linear[-2].transpose(1, 2), linear[-1].unsqueeze(1))
    return out, outs, pres


def _mlp_backward(
    linear: list[Tensor],
    acts: list[Any],
    x: Tensor,
    outs: list[Tensor],
    pres: list[Tensor | None],
    d: Tensor,
    rows: int,
    skip: int = 0,
) -> tuple[list[Tensor], Tensor | None]:
    """Backward of :func:`_mlp_forward` for the output gradient ``d`` ``[n, N, out]``.

    The parameter gradients take the first ``rows`` rows only; the gradient of the inputs past
    column ``skip``, summed over the members, is returned for the remaining rows (``None``
    when there are none).
    """
    grads: list[Tensor] = list(linear)
    for i in range(len(acts), -1, -1):
        weight = linear[2 * i]
        top = d[:, :rows]
        grads[2 * i + 1] = top.sum(1)
        if i == 0:
            # Both products have a narrow side (the input width, the action width); MKL runs
            # them several times faster with it as the output's rows.
            inp = x[:rows].t().expand(weight.shape[0], -1, -1)
            grads[0] = torch.bmm(inp, top).transpose(1, 2).contiguous()
            if rows == d.shape[1]:
                return grads, None
            part = weight[:, :, skip:].transpose(1, 2)
            return grads, torch.bmm(part, d[:, rows:].transpose(1, 2)).sum(0).t()
        grads[2 * i] = torch.bmm(top.transpose(1, 2), outs[i - 1][:, :rows])
        d = d * weight if d.shape[-1] == 1 else torch.bmm(d, weight)
        d = _activation_backward(acts[i - 1], d, outs[i - 1], pres[i - 1])
    raise AssertionError("unreachable")


def _activation_backward(
    act: Any, d: Tensor, out: Tensor, pre: Tensor | None, *index: Any
) -> Tensor:
    """``d`` through an activation, from its output ``out`` (or its input ``pre[index]``)."""
    if act == "relu":
        return torch.ops.aten.threshold_backward(d, out, 0)
    if act == "tanh":
        return torch.ops.aten.tanh_backward(d, out)
    with torch.enable_grad():
        z = pre[index].detach().requires_grad_()
        (d,) = torch.autograd.grad(act(z), z, d)
    return d


#: Fewest rows a member's share of the actor rows may have for :func:`_q_backward` to run it
#: alone: below this, MKL's single-thread GEMM takes another kernel path for the narrow side and
#: rounds differently from the whole-batch product (measured: 3 rows, 11 columns).
_MIN_MEMBER_ROWS = 16


def _q_backward(
    linear: list[Tensor],
    acts: list[Any],
    x: Tensor,
    outs: list[Tensor],
    pres: list[Tensor | None],
    d: Tensor,
    argmin: Tensor,
    skip: int,
) -> tuple[list[Tensor], Tensor | None]:
    """:func:`_mlp_backward` of the Q-ensemble's critic rows and min-Q actor rows.

    The first ``rows = len(argmin)`` rows of ``d`` ``[n, 2 * rows, 1]`` are the critic loss'
    gradients (every member), the last ``rows`` the actor loss' (non-zero in the member
    ``argmin`` of each row only). The critic rows run through every member; each actor row
    runs through its ``argmin`` member alone (its other members' rows are exact zeros), which
    halves that part's products. Same numbers as :func:`_mlp_backward` on all ``2 * rows``
    rows (a row of a product does not depend on the others); where a member would get fewer
    than :data:`_MIN_MEMBER_ROWS` rows, that whole-batch backward runs instead.
    """
    rows = argmin.shape[0]
    n = linear[0].shape[0]
    members = [(argmin == k).nonzero().squeeze(1) for k in range(n)]
    if any(0 < len(m) < _MIN_MEMBER_ROWS for m in members):
        return _mlp_backward(linear, acts, x, outs, pres, d, rows, skip)
    critic = [t[:, :rows] for t in outs], [None if t is None else t[:, :rows] for t in pres]
    grads, _ = _mlp_backward(linear, acts, x[:rows], *critic, d[:, :rows], rows)
    # the first layer's input gradient as the whole-batch product, on exact zeros elsewhere
    first = outs[0].new_zeros(n, rows, outs[0].shape[-1])
    for k, index in enumerate(members):
        if len(index):
            at = index + rows
            g = d[k, at]
            for i in range(len(acts), 0, -1):
                weight = linear[2 * i][k]
                g = g * weight if g.shape[-1] == 1 else torch.mm(g, weight)
                g = _activation_backward(acts[i - 1], g, outs[i - 1][k, at], pres[i - 1], k, at)
            first[k, index] = g
    part = linear[0][:, :, skip:].transpose(1, 2)
    return grads, torch.bmm(part, first.transpose(1, 2)).sum(0).t()


def _split_policy(
    net: nn.Module,
) -> tuple[list[Tensor], list[Tensor], list[Any], nn.Module] | None:
    """``(params, params as [1, ...] views, activations, head)`` of ``Sequential(MLP, head)``.

    ``None`` when ``net`` is not an MLP of biased ``Linear`` layers and one parameter-free
    activation between them, followed by parameter-free modules.
    """
    children = list(net.children()) if isinstance(net, nn.Sequential) else []
    if not children or not isinstance(children[0], nn.Sequential):
        return None
    layers: list[tuple[str, Any]] = []
    for module in children[0].children():
        if isinstance(module, nn.Linear) and module.bias is not None:
            layers.append(("linear", module))
        elif next(module.parameters(), None) is None:
            layers.append(("fn", module))
        else:
            return None
    head = nn.Sequential(*children[1:])
    if any(True for _ in head.parameters()):
        return None
    try:
        acts = _activations(layers)
    except ValueError:
        return None
    params = [t for _, m in layers[::2] for t in (m.weight, m.bias)]
    with torch.no_grad():
        linear = [t.unsqueeze(0) for t in params]
    return params, linear, acts, head


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


def _activations(layers: list[tuple[str, Any]]) -> list[Any]:
    """The activation between consecutive linear layers: ``"relu"``, ``"tanh"`` or the module."""
    kinds = [kind for kind, _ in layers]
    expected = ["linear"] + ["fn", "linear"] * ((len(layers) - 1) // 2)
    if kinds != expected:
        raise ValueError(
            f"FusedSACUpdate expects a Q-network of Linear layers with one activation between "
            f"consecutive ones, got layers {kinds}"
        )
    return list(plain_layers([module for _, module in layers[1::2]]))


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
