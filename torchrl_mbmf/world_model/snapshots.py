"""What a run records of its world-model fits: a weight snapshot per fit, held-out errors.

Each fit's weights go to ``<run_dir>/world_models/fit-<transitions>/`` (raw tensors and an
integrity record, never unpickled); before each refit, :func:`heldout_open_loop_errors` scores
the model being replaced on the transitions it never trained on. Why:
``docs/design/world_model_fit.md``.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Literal

import torch
from tensordict import TensorDict
from torch import nn

from torchrl_mbmf.data.memmap import load_tensor_folder
from torchrl_mbmf.data.transitions import TransitionDataset
from torchrl_mbmf.objectives.open_loop import multistep_mse
from torchrl_mbmf.runs.layout import FITS
from torchrl_mbmf.runs.storage import verify_checkpoint, write_integrity_record

__all__ = [
    "FIT_FOLDER",
    "HELDOUT_HORIZONS",
    "fit_snapshots",
    "heldout_open_loop_errors",
    "load_fit_snapshot",
    "save_fit_snapshot",
]

#: Folder of a run that holds one snapshot per world-model fit.
FIT_FOLDER = FITS
#: Horizons of the held-out open-loop errors (thesis experiment 1).
HELDOUT_HORIZONS = (5, 10, 25)


def save_fit_snapshot(model: nn.Module, run_dir: str | os.PathLike, transitions: int) -> Path:
    """Writes the fitted model's parameters and buffers to ``world_models/fit-<transitions>``.

    The folder is written beside its final place and renamed into it once complete (with an
    integrity record), so a killed process leaves no half-written snapshot; a snapshot of the
    same fit (a resumed run refits at the same step, bit-identically) is replaced.

    Args:
        model: the world model (any module: its ``TensorDict.from_module`` state is saved).
        run_dir: the run folder.
        transitions: real transitions the model was fitted on (names the snapshot).

    Returns:
        The snapshot folder.

    Examples:
        >>> import tempfile, torch
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.world_model.snapshots import load_fit_snapshot, save_fit_snapshot
        >>> model = DeltaDynamicsModel(3, 1, hidden_sizes=(8,))
        >>> folder = save_fit_snapshot(model, tempfile.mkdtemp(), 200)
        >>> folder.name
        'fit-000000200'
        >>> copy = load_fit_snapshot(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), folder)
        >>> s, a = torch.zeros(2, 3), torch.zeros(2, 1)
        >>> all(torch.equal(x, y) for x, y in zip(copy(s, a), model(s, a)))
        True
    """
    if transitions < 0:
        raise ValueError(f"transitions={transitions} must be >= 0")
    root = Path(run_dir) / FIT_FOLDER
    root.mkdir(parents=True, exist_ok=True)
    folder = root / f"fit-{transitions:09d}"
    staging = root / f".{folder.name}.staging"
    if staging.exists():
        shutil.rmtree(staging)
    state = TensorDict.from_module(model, as_module=False).detach().clone()
    state.memmap_(staging / "state")
    write_integrity_record(staging)
    if folder.exists():
        shutil.rmtree(folder)
    staging.rename(folder)
    return folder


def load_fit_snapshot(model: nn.Module, folder: str | os.PathLike) -> nn.Module:
    """Loads a snapshot written by :func:`save_fit_snapshot` into ``model`` (same architecture).

    Args:
        model: a module of the snapshot's architecture (its values are overwritten).
        folder: the snapshot folder.

    Returns:
        ``model``, holding the snapshot's values.

    Raises:
        CheckpointIntegrityError: a file is missing, truncated or altered.

    Examples:
        >>> import tempfile
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.world_model.snapshots import load_fit_snapshot, save_fit_snapshot
        >>> net = DeltaDynamicsModel(3, 1, hidden_sizes=(8,))
        >>> folder = save_fit_snapshot(net, tempfile.mkdtemp(), 5)
        >>> model = load_fit_snapshot(DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), folder)
        >>> bool(model.normalizer_fitted)
        False
    """
    verify_checkpoint(folder)
    load_tensor_folder(Path(folder) / "state").to_module(model)
    return model


def fit_snapshots(run_dir: str | os.PathLike) -> list[tuple[int, Path]]:
    """The snapshots of a run as ``(transitions, folder)``, oldest first.

    Args:
        run_dir: the run folder.

    Examples:
        >>> import tempfile
        >>> from torchrl_mbmf.world_model.snapshots import fit_snapshots
        >>> fit_snapshots(tempfile.mkdtemp())
        []
    """
    root = Path(run_dir) / FIT_FOLDER
    if not root.is_dir():
        return []
    found = [(int(p.name.removeprefix("fit-")), p) for p in root.glob("fit-*") if p.is_dir()]
    return sorted(found)


@torch.no_grad()
def heldout_open_loop_errors(
    model: nn.Module,
    dataset: TransitionDataset,
    *,
    since: int,
    horizons: tuple[int, ...] = HELDOUT_HORIZONS,
    num_starts: int = 2000,
    seed: int = 0,
    x_index: int | Literal["task"] | None = "task",
) -> dict[str, float]:
    """Open-loop x-position and reward MSE on the dataset's rows from ``since`` on.

    The x position is the task's by default
    (:func:`~torchrl_mbmf.objectives.open_loop.resolve_x_index`); a task without one
    (Pendulum) records the reward errors only.

    Uses its own random generator (the run's random state is untouched, so recording these
    errors changes no training number).

    Args:
        model: the world model, called as ``model(state, action) -> (next_state, reward)``.
        dataset: the run's real transitions, in collection order.

    Keyword Args:
        since: first row the model was not fitted on (the dataset's length at the fit).
        horizons: rollout lengths. Defaults to :data:`HELDOUT_HORIZONS`.
        num_starts: start states sampled (all if fewer). Defaults to ``2000``.
        seed: seed of the sampling. Defaults to ``0``.
        x_index: the x position's state index, ``None`` or ``"task"`` (as
            :func:`~torchrl_mbmf.objectives.open_loop.multistep_mse`). Defaults to ``"task"``.

    Returns:
        ``{"model/heldout_x_mse_h<h>": ..., "model/heldout_reward_mse_h<h>": ...,
        "model/heldout_starts": ...}`` (no x entries for a task without an x position), or
        ``{}`` when no episode has ``max(horizons)`` steps after ``since``.

    Examples:
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.world_model.snapshots import heldout_open_loop_errors
        >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 400, seed=0)
        >>> errors = heldout_open_loop_errors(
        ...     DeltaDynamicsModel(3, 1, hidden_sizes=(8,)), data, since=200, horizons=(1, 5))
        >>> sorted(errors)[:2], errors["model/heldout_starts"]
        (['model/heldout_reward_mse_h1', 'model/heldout_reward_mse_h5'], 196.0)
    """
    if len(dataset) <= since:
        return {}
    try:
        errors = multistep_mse(
            model,
            dataset,
            horizons=horizons,
            num_starts=num_starts,
            seed=seed,
            x_index=x_index,
            start_from=since,
        )
    except ValueError:  # no episode long enough after `since`
        return {}
    out = {"model/heldout_starts": float(errors[0].num_rollouts)}
    for e in errors:
        if e.x_mse is not None:  # the task's state has an x position
            out[f"model/heldout_x_mse_h{e.horizon}"] = e.x_mse
        out[f"model/heldout_reward_mse_h{e.horizon}"] = e.reward_mse
    return out
