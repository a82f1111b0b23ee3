"""Open-loop multi-step prediction errors of a world model (thesis tables 8 and 9).

The model starts at a real state and is fed the real actions of the following steps; its
predicted states and rewards are compared with the real trajectory at every step ``1..h``. The
trainer logs these errors on the policy's own, not yet trained-on, transitions at every model
refit; :mod:`torchrl_mbmf.analysis.horizon` tabulates and plots them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Literal

import torch
from torch import nn

from torchrl_mbmf.envs.tasks import task_layout

if TYPE_CHECKING:
    from torchrl_mbmf.data.transitions import TransitionDataset

__all__ = [
    "HorizonError",
    "horizon_windows",
    "multistep_mse",
    "open_loop_rollout",
    "resolve_x_index",
]

#: ``x_index`` value meaning "where the dataset's task keeps its x position".
TASK_X = "task"


@dataclass
class HorizonError:
    """Prediction errors of ``h``-step open-loop rollouts from real start states.

    The model is started at a real state and fed the real actions; its predictions are compared
    with the real trajectory at every step ``1..h``.

    Attributes:
        horizon: rollout length ``h``.
        num_rollouts: number of start states.
        x_mse: MSE of the x position averaged over the ``h`` steps (thesis table 8), or
            ``None`` for a state without an x position.
        reward_mse: MSE of the reward averaged over the ``h`` steps (thesis table 9).
        x_mse_final: MSE of the x position at step ``h`` (``None`` without an x position).
        reward_mse_final: MSE of the reward at step ``h``.
        state_mse: per-state-dimension MSE averaged over the ``h`` steps.

    Examples:
        >>> from torchrl_mbmf.objectives.open_loop import HorizonError
        >>> HorizonError(5, 10, 0.1, 0.2, 0.3, 0.4, [0.1]).to_dict()["x_mse"]
        0.1
    """

    horizon: int
    num_rollouts: int
    x_mse: float | None
    reward_mse: float
    x_mse_final: float | None
    reward_mse_final: float
    state_mse: list[float]

    def to_dict(self) -> dict[str, object]:
        """JSON-serialisable form."""
        return asdict(self)


def horizon_windows(
    data: TransitionDataset,
    horizon: int,
    *,
    num_starts: int | None = None,
    seed: int = 0,
    start_from: int = 0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Real ``horizon``-step trajectories of a dataset, for open-loop comparisons.

    Args:
        data: real transitions.
        horizon: steps per trajectory.

    Keyword Args:
        num_starts: sample this many start rows (all when ``None``). Defaults to ``None``.
        seed: seed of that sampling (its own generator: no global random state is used).
        start_from: only trajectories starting at this row or later. Defaults to ``0``.

    Returns:
        Start states ``[S, d]``, actions ``[S, h, a]``, real next states ``[S, h, d]`` and
        real rewards ``[S, h]``.

    Raises:
        ValueError: no episode has ``horizon`` consecutive steps from ``start_from`` on.

    Examples:
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.objectives.open_loop import horizon_windows
        >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 250, seed=0)
        >>> [t.shape[0] for t in horizon_windows(data, 5, start_from=200)]
        [46, 46, 46, 46]
    """
    td = data.tensors()
    # Windows never cross a done, a truncation or an unflagged reset between two batches.
    windows = data.windows(horizon)  # [S, h] row indices of consecutive steps
    windows = windows[windows[:, 0] >= start_from]
    if not windows.shape[0]:
        raise ValueError(
            f"no episode in the data has {horizon} consecutive steps from row {start_from} on"
        )
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
    model: nn.Module, state0: torch.Tensor, actions: torch.Tensor
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
        >>> from torchrl_mbmf.objectives.open_loop import open_loop_rollout
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


def resolve_x_index(
    data: TransitionDataset, x_index: int | Literal["task"] | None = TASK_X
) -> int | None:
    """The state index of the x position in ``data``'s states.

    Args:
        data: real transitions (their ``metadata["env_id"]`` names the task).
        x_index: an index, ``None`` (the state has no x position), or ``"task"``: the x index
            of the task's layout (:func:`~torchrl_mbmf.envs.task_layout`: ``0`` for HalfCheetah,
            Hopper, Walker2d and Ant as :func:`~torchrl_mbmf.envs.make_env` builds them,
            ``None`` for Pendulum); ``None`` for a task without a known layout or states of
            another size than the layout's (for example Hopper's observation without its x
            position, from a plain ``GymEnv``). Defaults to ``"task"``.

    Returns:
        The index, or ``None``.

    Raises:
        ValueError: ``x_index`` is neither an index of the state nor ``None`` nor ``"task"``.

    Examples:
        >>> from torchrl_mbmf.data import TransitionDataset
        >>> from torchrl_mbmf.objectives.open_loop import resolve_x_index
        >>> hopper = TransitionDataset({"env_id": "Hopper-v5", "reward": {"name": "default"}})
        >>> resolve_x_index(hopper), resolve_x_index(hopper, None), resolve_x_index(hopper, 2)
        (0, None, 2)
    """
    if x_index == TASK_X:
        layout = task_layout(str(data.metadata.get("env_id")))
        if layout is None:
            return None
        if len(data) and data.tensors().get(data.state_key).shape[-1] != layout.state_dim:
            return None  # another layout (e.g. a plain GymEnv without the positions)
        return layout.x_index
    if x_index is None:
        return None
    if isinstance(x_index, bool) or not isinstance(x_index, int) or x_index < 0:
        raise ValueError(
            f"x_index must be a state index (an int >= 0), None or {TASK_X!r}, got {x_index!r}"
        )
    return x_index


def multistep_mse(
    model: nn.Module,
    data: TransitionDataset,
    *,
    horizons: Sequence[int] = (5, 10, 25),
    num_starts: int | None = 2000,
    seed: int = 0,
    x_index: int | Literal["task"] | None = TASK_X,
    start_from: int = 0,
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
        x_index: state index of the x position, ``None`` for a state without one (the x
            errors are then ``None``), or ``"task"``: the index of the dataset's task
            (:func:`resolve_x_index`; HalfCheetah's and Hopper's x is ``0``, Pendulum has none).
            Defaults to ``"task"``.
        start_from: only windows starting at this row or later (for example the transitions
            collected after the model's fit: held-out data of the policy's own episodes).
            Defaults to ``0``.

    Returns:
        One :class:`HorizonError` per horizon.

    Raises:
        ValueError: if a horizon is < 1, no episode is long enough, or ``x_index`` is not an
            index of the state.

    Examples:
        >>> from torchrl_mbmf.objectives.open_loop import multistep_mse
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 100, seed=0)
        >>> errors = multistep_mse(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), data,
        ...                        horizons=(1, 5))
        >>> [e.horizon for e in errors], errors[0].x_mse  # Pendulum's state has no x
        ([1, 5], None)
    """
    if not horizons or min(horizons) < 1:
        raise ValueError(f"horizons must be >= 1, got {tuple(horizons)}")
    x = resolve_x_index(data, x_index)
    h_max = max(horizons)
    state0, actions, real_states, real_rewards = horizon_windows(
        data, h_max, num_starts=num_starts, seed=seed, start_from=start_from
    )
    if x is not None and x >= state0.shape[-1]:
        raise ValueError(f"x_index={x} is not an index of the {state0.shape[-1]}-dim state")
    pred_states, pred_rewards = open_loop_rollout(model, state0, actions)
    state_err = (pred_states - real_states).pow(2)  # [S, H, d]
    reward_err = (pred_rewards - real_rewards).pow(2)  # [S, H]
    out = []
    for h in horizons:
        out.append(
            HorizonError(
                horizon=int(h),
                num_rollouts=int(state0.shape[0]),
                x_mse=None if x is None else float(state_err[:, :h, x].mean()),
                reward_mse=float(reward_err[:, :h].mean()),
                x_mse_final=None if x is None else float(state_err[:, h - 1, x].mean()),
                reward_mse_final=float(reward_err[:, h - 1].mean()),
                state_mse=state_err[:, :h].mean((0, 1)).tolist(),
            )
        )
    return out
