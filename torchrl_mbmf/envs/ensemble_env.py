"""The ensemble world model as a TorchRL environment that reports the members' disagreement."""

from __future__ import annotations

from typing import Any, Literal

from tensordict.utils import NestedKey
from torchrl.envs import EnvBase

from torchrl_mbmf.envs.model_based import MEMBER_ASSIGNMENTS, LearnedDynamicsEnv
from torchrl_mbmf.modules.ensemble import EnsembleDeltaDynamicsModel, check_ensemble


class EnsembleLearnedDynamicsEnv(LearnedDynamicsEnv):
    """:class:`~torchrl_mbmf.envs.LearnedDynamicsEnv` on an ensemble, members and disagreement on.

    The learned env with ``member_assignment="cycle"`` (element ``i`` of the last batch dim
    stepped by member ``i mod K``, the convention of
    :class:`~torchrl_mbmf.modules.planners.EnsemblePolicyGuidedPlanner`: ``[*B, m]``
    candidates rolled out here follow the same members as in the planner; ``"mean"`` steps
    the members' mean) and ``disagreement_key="disagreement"``: every step writes
    ``("next", disagreement_key)`` ``[*B, 1]``, the members' disagreement at the step's
    ``(state, action)``, and ``reset`` writes 0. All members are evaluated at every step (one
    batched op), which the disagreement needs. Everything else is ``LearnedDynamicsEnv``'s.

    Args:
        world_model: the fitted ensemble.
        env: the real env whose specs are copied (batched or not).

    Keyword Args:
        member_assignment: ``"cycle"`` or ``"mean"``. Defaults to ``"cycle"``.
        disagreement_key: key of the disagreement. Defaults to ``"disagreement"``.
        **kwargs: the other keyword arguments of :class:`~torchrl_mbmf.envs.LearnedDynamicsEnv`
            (``batch_size``, ``state_key``, ``observation_key``, ``action_key``,
            ``reward_key``, ``observation_fn``, ``device``, ``termination_fn``).

    Examples:
        >>> import torch
        >>> from torchrl.envs.utils import check_env_specs
        >>> from torchrl_mbmf.envs import EnsembleLearnedDynamicsEnv, make_gym_state_env
        >>> from torchrl_mbmf.modules import EnsembleDeltaDynamicsModel
        >>> real = make_gym_state_env("Pendulum-v1", seed=0)
        >>> model = EnsembleDeltaDynamicsModel(3, 1, num_members=3, hidden_sizes=(16,))
        >>> env = EnsembleLearnedDynamicsEnv(model, real)
        >>> check_env_specs(env)
        >>> start = real.reset().expand(6)  # 6 candidates: members 0, 1, 2, 0, 1, 2
        >>> rollout = env.rollout(4, tensordict=env.reset(start), auto_reset=False)
        >>> rollout["next", "disagreement"].shape
        torch.Size([6, 4, 1])
    """

    def __init__(
        self,
        world_model: EnsembleDeltaDynamicsModel,
        env: EnvBase,
        *,
        member_assignment: Literal["cycle", "mean"] = "cycle",
        disagreement_key: NestedKey = "disagreement",
        **kwargs: Any,
    ) -> None:
        check_ensemble(world_model)  # a single model: LearnedDynamicsEnv
        super().__init__(
            world_model,
            env,
            member_assignment=member_assignment,
            disagreement_key=disagreement_key,
            **kwargs,
        )


__all__ = ["MEMBER_ASSIGNMENTS", "EnsembleLearnedDynamicsEnv"]
