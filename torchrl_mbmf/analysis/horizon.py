"""Open-loop multi-step prediction error of the world model (thesis tables 8, 9, figures 9, 10)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import torch

from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel


@dataclass
class HorizonError:
    """Prediction errors of ``h``-step open-loop rollouts from real start states.

    The model is started at a real state and fed the real actions; its predictions are compared
    with the real trajectory at every step ``1..h``.

    Attributes:
        horizon: rollout length ``h``.
        num_rollouts: number of start states.
        x_mse: MSE of the x position averaged over the ``h`` steps (thesis table 8).
        reward_mse: MSE of the reward averaged over the ``h`` steps (thesis table 9).
        x_mse_final: MSE of the x position at step ``h``.
        reward_mse_final: MSE of the reward at step ``h``.
        state_mse: per-state-dimension MSE averaged over the ``h`` steps.

    Examples:
        >>> from torchrl_mbmf.analysis import HorizonError
        >>> HorizonError(5, 10, 0.1, 0.2, 0.3, 0.4, [0.1]).to_dict()["x_mse"]
        0.1
    """

    horizon: int
    num_rollouts: int
    x_mse: float
    reward_mse: float
    x_mse_final: float
    reward_mse_final: float
    state_mse: list[float]

    def to_dict(self) -> dict[str, object]:
        """JSON-serialisable form."""
        return asdict(self)


def _windows(
    data: TransitionDataset, horizon: int, num_starts: int | None, seed: int
) -> tuple[torch.Tensor, ...]:
    td = data.tensors()
    # Windows never cross a done, a truncation or an unflagged reset between two batches.
    windows = data.windows(horizon)  # [S, h] row indices of consecutive steps
    if not windows.shape[0]:
        raise ValueError(f"no episode in the data has {horizon} consecutive steps")
    if num_starts is not None and num_starts < windows.shape[0]:
        g = torch.Generator().manual_seed(seed)
        windows = windows[torch.randperm(windows.shape[0], generator=g)[:num_starts]]
    state0 = td.get(data.state_key)[windows[:, 0]].float()
    actions = td.get(data.action_key)[windows].float()
    real_states = td.get(("next", data.state_key))[windows].float()
    real_rewards = td.get(("next", data.reward_key))[windows].float().reshape(*windows.shape)
    return state0, actions, real_states, real_rewards


@torch.no_grad()
def open_loop_rollout(
    model: DeltaDynamicsModel, state0: torch.Tensor, actions: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rolls the model from ``state0 [S, d]`` through ``actions [S, h, a]``.

    Args:
        model: the world model.
        state0: start states.
        actions: action sequences.

    Returns:
        Predicted next states ``[S, h, d]`` and rewards ``[S, h]``.

    Examples:
        >>> import torch
        >>> from torchrl_mbmf.analysis import open_loop_rollout
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> s, r = open_loop_rollout(DeltaDynamicsModel(3, 1, hidden_sizes=(4,)),
        ...                          torch.zeros(2, 3), torch.zeros(2, 5, 1))
        >>> s.shape, r.shape
        (torch.Size([2, 5, 3]), torch.Size([2, 5]))
    """
    states, rewards = [], []
    s = state0
    for t in range(actions.shape[1]):
        s, r = model(s, actions[:, t])
        states.append(s)
        rewards.append(r[..., 0])
    return torch.stack(states, 1), torch.stack(rewards, 1)


def multistep_mse(
    model: DeltaDynamicsModel,
    data: TransitionDataset,
    *,
    horizons: Sequence[int] = (5, 10, 25),
    num_starts: int | None = 2000,
    seed: int = 0,
    x_index: int = 0,
) -> list[HorizonError]:
    """Open-loop ``h``-step prediction error from real start states, for each horizon.

    Every start state of every episode with enough following steps is a candidate; the same
    start states are used for all horizons (those with ``max(horizons)`` steps ahead), so the
    horizons are comparable. ``num_starts`` samples a subset.

    Args:
        model: the world model.
        data: real transitions (held-out data, to measure generalisation).

    Keyword Args:
        horizons: rollout lengths. Defaults to ``(5, 10, 25)`` (thesis experiment 1).
        num_starts: number of start states sampled, or ``None`` for all. Defaults to ``2000``.
        seed: seed of the sampling. Defaults to ``0``.
        x_index: state index of the x position. Defaults to ``0``.

    Returns:
        One :class:`HorizonError` per horizon.

    Raises:
        ValueError: if a horizon is < 1 or no episode is long enough.

    Examples:
        >>> from torchrl_mbmf.analysis import multistep_mse
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 100, seed=0)
        >>> errors = multistep_mse(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), data,
        ...                        horizons=(1, 5))
        >>> [e.horizon for e in errors]
        [1, 5]
    """
    if not horizons or min(horizons) < 1:
        raise ValueError(f"horizons must be >= 1, got {tuple(horizons)}")
    h_max = max(horizons)
    state0, actions, real_states, real_rewards = _windows(data, h_max, num_starts, seed)
    pred_states, pred_rewards = open_loop_rollout(model, state0, actions)
    state_err = (pred_states - real_states).pow(2)  # [S, H, d]
    reward_err = (pred_rewards - real_rewards).pow(2)  # [S, H]
    out = []
    for h in horizons:
        out.append(
            HorizonError(
                horizon=int(h),
                num_rollouts=int(state0.shape[0]),
                x_mse=float(state_err[:, :h, x_index].mean()),
                reward_mse=float(reward_err[:, :h].mean()),
                x_mse_final=float(state_err[:, h - 1, x_index].mean()),
                reward_mse_final=float(reward_err[:, h - 1].mean()),
                state_mse=state_err[:, :h].mean((0, 1)).tolist(),
            )
        )
    return out


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
    state0, actions, real_states, real_rewards = _windows(data, horizon, num_rollouts, seed)
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
