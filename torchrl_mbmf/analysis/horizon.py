"""Open-loop multi-step prediction error of the world model (thesis tables 8, 9, figures 9, 10)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import torch

from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.envs.factory import action_bounds, make_env
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.objectives.open_loop import (
    HorizonError,
    horizon_windows,
    multistep_mse,
    open_loop_rollout,
    resolve_x_index,
)
from torchrl_mbmf.runs.layout import RunFolder
from torchrl_mbmf.world_model.snapshots import fit_snapshots, load_fit_snapshot

# The thesis' tables 8 and 9: h -> (x-position MSE, reward MSE), each the mean over steps 1..h.
THESIS_HORIZON_MSE = {5: (2.359, 0.3856), 10: (2.489, 0.50635), 25: (3.0342, 0.6238)}


def horizon_predictions(
    model: DeltaDynamicsModel,
    data: TransitionDataset,
    horizon: int,
    *,
    num_rollouts: int = 1,
    seed: int = 0,
    x_index: int | Literal["task"] | None = "task",
) -> dict[str, torch.Tensor]:
    """Predicted and real x position and reward along ``h``-step rollouts, for plotting.

    Args:
        model: the world model.
        data: real transitions.
        horizon: rollout length.

    Keyword Args:
        num_rollouts: number of rollouts. Defaults to ``1``.
        seed: seed of the start-state sampling. Defaults to ``0``.
        x_index: state index of the x position, ``None`` (none), or ``"task"``: the x index
            of the dataset's task (:func:`~torchrl_mbmf.objectives.open_loop.resolve_x_index`).
            Defaults to ``"task"``.

    Returns:
        ``{"x_pred", "x_real", "reward_pred", "reward_real"}``, each ``[num_rollouts, h]``,
        plus ``"x_start"`` ``[num_rollouts]``; the x entries only where the state has an x
        position.

    Examples:
        >>> from torchrl_mbmf.analysis import horizon_predictions
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> data = collect_random_transitions(make_env("Hopper-v5"), 50, seed=0)
        >>> out = horizon_predictions(DeltaDynamicsModel(12, 3, hidden_sizes=(8,)), data, 5)
        >>> out["x_pred"].shape
        torch.Size([1, 5])

    Raises:
        ValueError: ``horizon < 1``.
    """
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    x = resolve_x_index(data, x_index)
    state0, actions, real_states, real_rewards = horizon_windows(
        data, horizon, num_starts=num_rollouts, seed=seed
    )
    pred_states, pred_rewards = open_loop_rollout(model, state0, actions)
    out = {"reward_pred": pred_rewards, "reward_real": real_rewards}
    if x is not None:
        out.update(x_start=state0[:, x], x_pred=pred_states[..., x], x_real=real_states[..., x])
    return out


def _fmt(value: float | None) -> str:
    """A table cell: 4 significant digits, or ``n/a`` (a state without an x position)."""
    return "n/a" if value is None else f"{value:.4g}"


def horizon_table(errors: Sequence[HorizonError]) -> str:
    """Markdown table of :func:`multistep_mse` results next to the thesis' tables 8 and 9.

    The x columns read ``n/a`` for a state without an x position.

    Args:
        errors: the errors.

    Returns:
        The table.

    Examples:
        >>> from torchrl_mbmf.analysis import HorizonError, horizon_table
        >>> print(horizon_table([HorizonError(5, 3, 1.0, 2.0, 3.0, 4.0, [])]).splitlines()[2])
        | 5 | 1 | 2 | 3 | 4 | 2.359 | 0.3856 |
    """
    thesis = THESIS_HORIZON_MSE
    lines = [
        "| h | x MSE (mean over 1..h) | reward MSE (mean over 1..h) | x MSE at h "
        "| reward MSE at h | thesis x MSE (table 8) | thesis reward MSE (table 9) |",
        "|---|---|---|---|---|---|---|",
    ]
    for e in errors:
        tx, tr = thesis.get(e.horizon, (float("nan"), float("nan")))
        lines.append(
            f"| {e.horizon} | {_fmt(e.x_mse)} | {e.reward_mse:.4g} | {_fmt(e.x_mse_final)} "
            f"| {e.reward_mse_final:.4g} | {tx:.4g} | {tr:.4g} |"
        )
    return "\n".join(lines)


def snapshot_open_loop_errors(
    run_dir: str | Path,
    data: TransitionDataset,
    *,
    horizons: Sequence[int] = (5, 10, 25),
    num_starts: int | None = 2000,
    seed: int = 0,
) -> list[dict[str, object]]:
    """Open-loop errors of every world-model fit a training run recorded, on the same data.

    Each snapshot under ``run_dir/world_models/`` (written at every fit, see
    :mod:`torchrl_mbmf.world_model.snapshots`) is loaded into a model of the run's
    ``world_model.hidden_sizes`` and its env's action range, and evaluated with
    :func:`multistep_mse` on the same start states, so the rows compare the refits (thesis
    tables 8 and 9 at each refit).

    Args:
        run_dir: a training run folder (``config.yaml`` and ``world_models/``).
        data: held-out real transitions (for example fresh random-policy episodes).

    Keyword Args:
        horizons: rollout lengths. Defaults to ``(5, 10, 25)``.
        num_starts: start states sampled. Defaults to ``2000``.
        seed: seed of the sampling. Defaults to ``0``.

    Returns:
        One dict per snapshot, oldest first: ``transitions`` (the data it was fitted on) and
        ``errors`` (one :meth:`HorizonError.to_dict` per horizon).

    Raises:
        FileNotFoundError: the run has no ``config.yaml``.
        ValueError: the run recorded no fit, or it planned with an ensemble.

    Examples:
        >>> import tempfile, pathlib, yaml
        >>> from torchrl_mbmf.analysis.horizon import snapshot_open_loop_errors
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.world_model.snapshots import save_fit_snapshot
        >>> run = pathlib.Path(tempfile.mkdtemp())
        >>> _ = (run / "config.yaml").write_text(yaml.safe_dump(
        ...     {"world_model": {"hidden_sizes": [8], "ensemble_size": 1}}))
        >>> _ = save_fit_snapshot(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), run, 100)
        >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 200, seed=0)
        >>> rows = snapshot_open_loop_errors(run, data, horizons=(1, 5), num_starts=20)
        >>> rows[0]["transitions"], [e["horizon"] for e in rows[0]["errors"]]
        (100, [1, 5])
    """
    run_dir = Path(run_dir)
    config = RunFolder(run_dir).read_config()
    wm = config.get("world_model", {})
    if int(wm.get("ensemble_size", 1) or 1) > 1:
        raise ValueError(f"{run_dir} planned with an ensemble; expected a single world model")
    snapshots = fit_snapshots(run_dir)
    if not snapshots:
        raise ValueError(f"{run_dir} recorded no world-model fit (no world_models/fit-*)")
    td = data.tensors()
    state_dim = td.get(data.state_key).shape[-1]
    action_dim = td.get(data.action_key).shape[-1]
    # the run's model had its env's action range (recipes build it from the action spec)
    env_id = config.get("env", {}).get("id", data.metadata["env_id"])
    low, high = action_bounds(make_env(env_id))
    rows = []
    for transitions, folder in snapshots:
        model = DeltaDynamicsModel(
            state_dim,
            action_dim,
            hidden_sizes=tuple(int(h) for h in wm["hidden_sizes"]),
            action_low=low,
            action_high=high,
        )
        load_fit_snapshot(model, folder)
        errors = multistep_mse(model, data, horizons=horizons, num_starts=num_starts, seed=seed)
        rows.append({"transitions": transitions, "errors": [e.to_dict() for e in errors]})
    return rows
