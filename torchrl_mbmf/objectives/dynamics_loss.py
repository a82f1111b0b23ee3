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

    def squared_errors(
        self,
        state: torch.Tensor,
        action: torch.Tensor,
        next_state: torch.Tensor,
        reward: torch.Tensor,
    ) -> torch.Tensor:
        """Per-output squared errors ``[..., state_dim + 1]`` in scaled units."""
        prediction = self.world_model.predict_scaled(state, action)
        target = self.world_model.scale_targets(state, next_state, reward)
        return (prediction - target).pow(2)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Computes the losses of a batch of transitions."""
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
