"""One-step world-model loss (thesis eq. 17) as a TorchRL loss module."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel


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

        Both in the model's scaled units, with its current scaler. A fit whose scaler stays
        fixed scales the data once with this and trains with :meth:`scaled_loss` on index
        slices of the result, instead of rescaling every minibatch.

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
        wm._check(state, action)
        inputs = torch.cat(
            [
                (state - wm.state_loc) / wm.state_scale,
                (wm.clip_action(action) - wm.action_loc) / wm.action_scale,
            ],
            -1,
        )
        return inputs, wm.scale_targets(state, next_state, reward)

    def scaled_loss(self, inputs: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
        """Eq. 17 on pre-scaled data from :meth:`scaled_pairs` (the mean over all outputs).

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
        return torch.nn.functional.mse_loss(self.world_model.net(inputs), targets)

    def squared_errors(
        self,
        state: torch.Tensor,
        action: torch.Tensor,
        next_state: torch.Tensor,
        reward: torch.Tensor,
    ) -> torch.Tensor:
        """Per-output squared errors ``[..., state_dim + 1]`` in scaled units.

        Args:
            state: states ``[..., state_dim]``.
            action: actions ``[..., action_dim]``.
            next_state: real next states ``[..., state_dim]``.
            reward: real rewards ``[...]`` or ``[..., 1]``.

        Returns:
            The squared errors, scaled delta first and scaled reward last.

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
