"""World-model losses as TorchRL loss modules: one-step (thesis eq. 17) and multi-step."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from torchrl_mbmf.checks import check_multi_step, check_multi_step_weight
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.modules.mlp import mlp_forward


class DynamicsLoss(LossModule):
    """MSE between predicted and real scaled state delta and reward (thesis eq. 17).

    The targets are the real ``s' - s`` and ``r``, standard-scaled with the model's buffers
    (:meth:`~torchrl_mbmf.modules.DeltaDynamicsModel.scale_targets`); the prediction is the
    network output for ``(s, a)``. ``loss_dynamics`` is the mean over all ``state_dim + 1``
    outputs; ``loss_delta`` and ``loss_reward`` split it for logging.

    Args:
        world_model: the model to train.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.objectives import DynamicsLoss
        >>> loss = DynamicsLoss(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)))
        >>> td = TensorDict(state=torch.randn(4, 3), action=torch.rand(4, 1),
        ...                 next=TensorDict(state=torch.randn(4, 3), reward=torch.randn(4, 1),
        ...                                 batch_size=[4]), batch_size=[4])
        >>> sorted(loss(td).keys())
        ['loss_delta', 'loss_dynamics', 'loss_reward']
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (``loss.set_keys(state=...)``).

        Attributes:
            state: the state. Defaults to ``"state"``.
            action: the action. Defaults to ``"action"``.
            next_state: the real next state. Defaults to ``("next", "state")``.
            reward: the real reward. Defaults to ``("next", "reward")``.
        """

        state: NestedKey = "state"
        action: NestedKey = "action"
        next_state: NestedKey = ("next", "state")
        reward: NestedKey = ("next", "reward")

    def __init__(self, world_model: DeltaDynamicsModel) -> None:
        super().__init__()
        self.world_model = world_model

    def _forward_value_estimator_keys(self, **kwargs: object) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        """Keys read by :meth:`forward`."""
        k = self.tensor_keys
        return [k.state, k.action, k.next_state, k.reward]

    @property
    def out_keys(self) -> list[str]:
        """Keys written by :meth:`forward`."""
        return ["loss_dynamics", "loss_delta", "loss_reward"]

    def scaled_pairs(
        self,
        state: torch.Tensor,
        action: torch.Tensor,
        next_state: torch.Tensor,
        reward: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Network inputs ``[..., state_dim + action_dim]`` and targets ``[..., state_dim + 1]``.

        Both in the model's scaled units, with its current scaler (a fit scales its data
        once with this and trains with :meth:`scaled_loss` on slices of the result).

        Args:
            state: states ``[..., state_dim]``.
            action: actions ``[..., action_dim]`` (clipped to the model's bounds).
            next_state: real next states ``[..., state_dim]``.
            reward: real rewards ``[...]`` or ``[..., 1]``.

        Returns:
            ``(inputs, targets)``; ``world_model.net(inputs)`` equals
            ``world_model.predict_scaled(state, action)``.

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.modules import DeltaDynamicsModel
            >>> from torchrl_mbmf.objectives import DynamicsLoss
            >>> loss = DynamicsLoss(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)))
            >>> x, y = loss.scaled_pairs(torch.zeros(5, 3), torch.zeros(5, 1), torch.ones(5, 3),
            ...                          torch.zeros(5))
            >>> x.shape, y.shape
            (torch.Size([5, 4]), torch.Size([5, 4]))
        """
        wm = self.world_model
        return wm.scaled_inputs(state, action), wm.scale_targets(state, next_state, reward)

    def scaled_loss(self, inputs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """Eq. 17 on pre-scaled data from :meth:`scaled_pairs` (the mean over all outputs).

        The network runs through :func:`~torchrl_mbmf.modules.mlp.mlp_forward` (in-place
        ReLUs for the thesis network, bit for bit the same values and gradients).

        Args:
            inputs: scaled network inputs.
            targets: scaled targets.

        Returns:
            The scalar loss.

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.modules import DeltaDynamicsModel
            >>> from torchrl_mbmf.objectives import DynamicsLoss
            >>> loss = DynamicsLoss(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)))
            >>> loss.scaled_loss(torch.zeros(5, 4), torch.zeros(5, 4)).shape
            torch.Size([])
        """
        return torch.nn.functional.mse_loss(mlp_forward(self.world_model.net, inputs), targets)

    def squared_errors(
        self,
        state: torch.Tensor,
        action: torch.Tensor,
        next_state: torch.Tensor,
        reward: torch.Tensor,
    ) -> torch.Tensor:
        """Per-output squared errors ``[..., state_dim + 1]`` in scaled units (delta, reward).

        Args:
            state: states ``[..., state_dim]``.
            action: actions ``[..., action_dim]``.
            next_state: real next states ``[..., state_dim]``.
            reward: real rewards ``[...]`` or ``[..., 1]``.

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.modules import DeltaDynamicsModel
            >>> from torchrl_mbmf.objectives import DynamicsLoss
            >>> loss = DynamicsLoss(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)))
            >>> loss.squared_errors(torch.zeros(5, 3), torch.zeros(5, 1), torch.ones(5, 3),
            ...                     torch.zeros(5)).shape
            torch.Size([5, 4])
        """
        prediction = self.world_model.predict_scaled(state, action)
        target = self.world_model.scale_targets(state, next_state, reward)
        return (prediction - target).pow(2)

    def rollout_squared_errors(
        self,
        state: torch.Tensor,
        actions: torch.Tensor,
        next_states: torch.Tensor,
        rewards: torch.Tensor,
    ) -> torch.Tensor:
        """Squared errors ``[..., k, state_dim + 1]`` (delta, reward) of a ``k``-step rollout.

        From the real ``state``, fed the real ``actions``, the model steps on its own
        predictions (gradients flow through the rollout). Step ``t``'s state error is
        ``(ŝ_t - s_t) / delta_scale``, its reward error that of the reward predicted from
        ``ŝ_{t-1}`` in scaled units; step 1 is :meth:`squared_errors`. Details:
        ``docs/design/dynamics_model.md``.

        Args:
            state: real start states ``[..., state_dim]``.
            actions: real actions ``[..., k, action_dim]``.
            next_states: real next states ``[..., k, state_dim]``.
            rewards: real rewards ``[..., k]`` or ``[..., k, 1]``.

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.modules import DeltaDynamicsModel
            >>> from torchrl_mbmf.objectives import DynamicsLoss
            >>> loss = DynamicsLoss(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)))
            >>> loss.rollout_squared_errors(torch.zeros(5, 3), torch.zeros(5, 4, 1),
            ...                             torch.ones(5, 4, 3), torch.zeros(5, 4)).shape
            torch.Size([5, 4, 4])
        """
        wm = self.world_model
        k = actions.shape[-2]
        if next_states.shape[:-1] != actions.shape[:-1]:
            raise ValueError(
                f"next_states batch {tuple(next_states.shape[:-1])} and actions batch "
                f"{tuple(actions.shape[:-1])} differ"
            )
        rewards = rewards.reshape(*actions.shape[:-1], 1)
        errors = []
        predicted = state
        for t in range(k):
            output = wm.predict_scaled(predicted, actions[..., t, :])
            predicted, _ = wm.unscale(predicted, output)
            state_err = (predicted - next_states[..., t, :]) / wm.delta_scale
            reward_err = output[..., -1:] - (rewards[..., t, :] - wm.reward_loc) / wm.reward_scale
            errors.append(torch.cat([state_err, reward_err], -1).pow(2))
        return torch.stack(errors, -2)

    def multi_step_loss(
        self,
        state: torch.Tensor,
        actions: torch.Tensor,
        next_states: torch.Tensor,
        rewards: torch.Tensor,
    ) -> torch.Tensor:
        """Mean over the ``k`` steps and all outputs of :meth:`rollout_squared_errors`.

        With ``k == 1`` this is the one-step loss (eq. 17) of the same transitions.

        Args:
            state: real start states ``[..., state_dim]``.
            actions: real actions ``[..., k, action_dim]``.
            next_states: real next states ``[..., k, state_dim]``.
            rewards: real rewards ``[..., k]`` or ``[..., k, 1]``.

        Examples:
            >>> import torch
            >>> from torchrl_mbmf.modules import DeltaDynamicsModel
            >>> from torchrl_mbmf.objectives import DynamicsLoss
            >>> loss = DynamicsLoss(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)))
            >>> loss.multi_step_loss(torch.zeros(5, 3), torch.zeros(5, 4, 1),
            ...                      torch.ones(5, 4, 3), torch.zeros(5, 4)).shape
            torch.Size([])
        """
        return self.rollout_squared_errors(state, actions, next_states, rewards).mean()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes the losses of a batch of transitions.

        Args:
            tensordict: transitions with the keys of :attr:`in_keys`.

        Returns:
            ``loss_dynamics`` (differentiable), ``loss_delta`` and ``loss_reward`` (detached).
        """
        k = self.tensor_keys
        err = self.squared_errors(
            tensordict.get(k.state),
            tensordict.get(k.action),
            tensordict.get(k.next_state),
            tensordict.get(k.reward),
        )
        return TensorDict(
            loss_dynamics=err.mean(),
            loss_delta=err[..., :-1].mean().detach(),
            loss_reward=err[..., -1].mean().detach(),
        )


class MultiStepDynamicsLoss(DynamicsLoss):
    """One-step loss plus a ``k``-step open-loop rollout loss on windows of real transitions.

    ``loss_dynamics = loss_one_step + multi_step_weight * loss_multi_step`` on a ``[B, k]``
    TensorDict of windows of consecutive transitions (time last, such as
    ``dataset.tensors()[dataset.windows(k)]``), the multi-step term being
    :meth:`DynamicsLoss.multi_step_loss` from each window's first state. Why and references:
    ``docs/design/dynamics_model.md``.

    Args:
        world_model: the model to train.

    Keyword Args:
        multi_step_weight: weight of the multi-step term (``>= 0``). Defaults to ``1.0``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.objectives import MultiStepDynamicsLoss
        >>> loss = MultiStepDynamicsLoss(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)))
        >>> windows = TensorDict(state=torch.randn(4, 5, 3), action=torch.rand(4, 5, 1),
        ...                      next=TensorDict(state=torch.randn(4, 5, 3),
        ...                                      reward=torch.randn(4, 5, 1),
        ...                                      batch_size=[4, 5]), batch_size=[4, 5])
        >>> sorted(loss(windows).keys())
        ['loss_delta', 'loss_dynamics', 'loss_multi_step', 'loss_one_step', 'loss_reward']
    """

    def __init__(self, world_model: DeltaDynamicsModel, *, multi_step_weight: float = 1.0) -> None:
        super().__init__(world_model)
        self.multi_step_weight = check_multi_step_weight(multi_step_weight)

    @property
    def out_keys(self) -> list[str]:
        """Keys written by :meth:`forward`."""
        return ["loss_dynamics", "loss_one_step", "loss_multi_step", "loss_delta", "loss_reward"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes the losses of a batch of windows.

        Args:
            tensordict: ``[B, k]`` windows of consecutive transitions with the keys of
                :attr:`in_keys`.

        Returns:
            ``loss_dynamics`` (differentiable); ``loss_one_step`` and ``loss_multi_step``
            (detached) are its two terms, ``loss_delta`` and ``loss_reward`` (detached)
            split the multi-step term.
        """
        if tensordict.batch_dims < 2:
            raise ValueError(
                f"expects [..., k] windows of transitions, got batch {tuple(tensordict.batch_size)}"
            )
        k = self.tensor_keys
        state = tensordict.get(k.state)
        action = tensordict.get(k.action)
        next_state = tensordict.get(k.next_state)
        reward = tensordict.get(k.reward)
        one_step = self.squared_errors(state, action, next_state, reward).mean()
        err = self.rollout_squared_errors(state[..., 0, :], action, next_state, reward)
        multi_step = err.mean()
        return TensorDict(
            loss_dynamics=one_step + self.multi_step_weight * multi_step,
            loss_one_step=one_step.detach(),
            loss_multi_step=multi_step.detach(),
            loss_delta=err[..., :-1].mean().detach(),
            loss_reward=err[..., -1].mean().detach(),
        )


__all__ = [
    "DynamicsLoss",
    "MultiStepDynamicsLoss",
    "check_multi_step",
    "check_multi_step_weight",
]
