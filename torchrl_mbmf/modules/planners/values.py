"""Terminal values for the planners' scores: the SAC min-Q of the policy's action.

For PPO-MPC the terminal value is the PPO critic ``V(s_h)`` itself (a ``ValueOperator`` writing
``"state_value"``); for SAC-MPC it is ``min_i Q_i(s_h, pi(s_h))`` over the loss' Q-networks,
which :class:`MinQValue` computes with the very parameters ``SACLoss`` trains.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.envs.utils import ExplorationType, set_exploration_type


class MinQValue(TensorDictModuleBase):
    """``min_i Q_i(s, a)`` with ``a`` the actor's action at ``s``, written as a state value.

    ``SACLoss`` keeps its Q-networks' parameters stacked in ``loss.qvalue_network_params``
    (the ``qvalue`` module handed to it is only a template); this module evaluates the template
    with each stacked parameter set and keeps the minimum, as SAC's clipped double-Q target does.

    Args:
        actor: the SAC actor (writes ``action_key`` from its observation entries).
        qvalue: the Q-network template (reads observation and action, writes
            ``"state_action_value"``).
        qvalue_params: the stacked parameters ``[num_qvalue_nets, ...]``, for example
            ``loss.qvalue_network_params``.

    Keyword Args:
        value_key: output key. Defaults to ``"state_value"``.
        action_key: the actor's action key. Defaults to ``"action"``.
        deterministic: evaluate at the actor's deterministic action (its mode) rather than a
            sample. Defaults to ``True``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.objectives import SACLoss
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import make_sac_actor_critic
        >>> from torchrl_mbmf.modules.planners import MinQValue
        >>> env = make_gym_state_env("Pendulum-v1", seed=0)
        >>> actor, qvalue = make_sac_actor_critic(env, hidden_sizes=(8, 8))
        >>> loss = SACLoss(actor, qvalue, num_qvalue_nets=2)
        >>> value = MinQValue(actor, qvalue, loss.qvalue_network_params)
        >>> value(env.reset())["state_value"].shape
        torch.Size([1])
    """

    def __init__(
        self,
        actor: TensorDictModuleBase,
        qvalue: TensorDictModuleBase,
        qvalue_params: TensorDictBase,
        *,
        value_key: NestedKey = "state_value",
        action_key: NestedKey = "action",
        deterministic: bool = True,
    ) -> None:
        super().__init__()
        if qvalue_params.batch_dims < 1 or qvalue_params.batch_size[0] < 1:
            raise ValueError(
                "qvalue_params must be stacked parameters [num_qvalue_nets, ...] (for example "
                f"SACLoss.qvalue_network_params), got batch size {tuple(qvalue_params.batch_size)}"
            )
        self.actor = actor
        self.qvalue = qvalue
        # Not registered as parameters here: they belong to the loss module.
        self._qvalue_params = [qvalue_params]
        self.value_key = value_key
        self.action_key = action_key
        self.deterministic = bool(deterministic)
        self.in_keys = list(actor.in_keys)
        self.out_keys = [value_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes ``value_key`` (``[*B, 1]``) into ``tensordict``.

        Args:
            tensordict: observation entries the actor reads, batch ``[*B]``.
        """
        mode = ExplorationType.DETERMINISTIC if self.deterministic else ExplorationType.RANDOM
        td = tensordict.copy()
        with set_exploration_type(mode):
            td = self.actor(td)
        values = []
        for params in self._qvalue_params[0].unbind(0):
            with params.to_module(self.qvalue):
                values.append(self.qvalue(td.copy()).get("state_action_value"))
        tensordict.set(self.value_key, torch.stack(values).amin(0))
        return tensordict


__all__ = ["MinQValue"]
