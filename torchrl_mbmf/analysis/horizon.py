"""Open-loop multi-step prediction error of the world model (thesis tables 8, 9, figures 9, 10)."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.objectives.open_loop import (
    HorizonError,
    horizon_windows,
    open_loop_rollout,
)


def horizon_predictions(
    model: DeltaDynamicsModel,
    data: TransitionDataset,
    horizon: int,
    *,
    num_rollouts: int = 1,
    seed: int = 0,
    x_index: int = 0,
) -> dict[str, torch.Tensor]:
    """Predicted and real x position and reward along ``h``-step rollouts, for plotting.

    Args:
        model: the world model.
        data: real transitions.
        horizon: rollout length.

    Keyword Args:
        num_rollouts: number of rollouts. Defaults to ``1``.
        seed: seed of the start-state sampling. Defaults to ``0``.
        x_index: state index of the x position. Defaults to ``0``.

    Returns:
        ``{"x_pred", "x_real", "reward_pred", "reward_real"}``, each ``[num_rollouts, h]``,
        plus ``"x_start"`` ``[num_rollouts]``.

    Examples:
        >>> from torchrl_mbmf.analysis import horizon_predictions
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 50, seed=0)
        >>> out = horizon_predictions(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), data, 5)
        >>> out["x_pred"].shape
        torch.Size([1, 5])
    """
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    state0, actions, real_states, real_rewards = horizon_windows(
        data, horizon, num_starts=num_rollouts, seed=seed
    )
    pred_states, pred_rewards = open_loop_rollout(model, state0, actions)
    return {
        "x_start": state0[:, x_index],
        "x_pred": pred_states[..., x_index],
        "x_real": real_states[..., x_index],
        "reward_pred": pred_rewards,
        "reward_real": real_rewards,
    }


def horizon_table(errors: Sequence[HorizonError]) -> str:
    """Markdown table of :func:`multistep_mse` results next to the thesis' tables 8 and 9.

    Args:
        errors: the errors.

    Returns:
        The table.

    Examples:
        >>> from torchrl_mbmf.analysis import HorizonError, horizon_table
        >>> print(horizon_table([HorizonError(5, 3, 1.0, 2.0, 3.0, 4.0, [])]).splitlines()[2])
        | 5 | 1 | 2 | 3 | 4 | 2.359 | 0.3856 |
    """
    thesis = {5: (2.359, 0.3856), 10: (2.489, 0.50635), 25: (3.0342, 0.6238)}
    lines = [
        "| h | x MSE (mean over 1..h) | reward MSE (mean over 1..h) | x MSE at h "
        "| reward MSE at h | thesis x MSE (table 8) | thesis reward MSE (table 9) |",
        "|---|---|---|---|---|---|---|",
    ]
    for e in errors:
        tx, tr = thesis.get(e.horizon, (float("nan"), float("nan")))
        lines.append(
            f"| {e.horizon} | {e.x_mse:.4g} | {e.reward_mse:.4g} | {e.x_mse_final:.4g} "
            f"| {e.reward_mse_final:.4g} | {tx:.4g} | {tr:.4g} |"
        )
    return "\n".join(lines)
