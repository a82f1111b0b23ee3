"""The fit-world-model job: random data, fit, horizon evaluation, plots."""

from __future__ import annotations

import copy
import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from torchrl_mbmf.analysis.horizon import horizon_predictions, horizon_table
from torchrl_mbmf.checks import check_multi_step, check_number
from torchrl_mbmf.data.transitions import TransitionDataset, collect_random_transitions
from torchrl_mbmf.envs.factory import action_bounds, env_metadata, make_env
from torchrl_mbmf.envs.keys import STATE_KEY
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.objectives.open_loop import HorizonError, multistep_mse, resolve_x_index
from torchrl_mbmf.world_model.fit import fit_dynamics, fit_dynamics_kwargs

logger = logging.getLogger(__name__)


def plot_horizon_predictions(
    model: DeltaDynamicsModel,
    data: TransitionDataset,
    horizons: list[int],
    out_dir: Path,
    *,
    num_rollouts: int = 3,
    seed: int = 0,
) -> list[Path]:
    """Plots predicted vs real x position and reward along h-step rollouts (figures 9, 10).

    Args:
        model: the world model.
        data: held-out real transitions.
        horizons: one plot column per horizon.
        out_dir: folder of the PNG files.

    Keyword Args:
        num_rollouts: rollouts per panel. Defaults to ``3``.
        seed: seed of the start-state sampling. Defaults to ``0``.

    Returns:
        The written files (``horizon_x.png``, ``horizon_reward.png``; the x plot only where
        the dataset's task has an x position,
        :func:`~torchrl_mbmf.objectives.open_loop.resolve_x_index`).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.analysis.world_model_job import plot_horizon_predictions
        >>> data = collect_random_transitions(make_env("Hopper-v5"), 60, seed=0)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     files = plot_horizon_predictions(DeltaDynamicsModel(12, 3), data, [5], Path(d))
        >>> [f.name for f in files]
        ['horizon_x.png', 'horizon_reward.png']
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    quantities = [("x", "x position (m)"), ("reward", "reward per step")]
    if resolve_x_index(data) is None:  # the task's state has no x position (Pendulum)
        quantities = quantities[1:]
    for quantity, label in quantities:
        fig, axes = plt.subplots(1, len(horizons), figsize=(4.2 * len(horizons), 3.4))
        axes = [axes] if len(horizons) == 1 else list(axes)
        for ax, h in zip(axes, horizons, strict=True):
            out = horizon_predictions(model, data, h, num_rollouts=num_rollouts, seed=seed)
            steps = torch.arange(1, h + 1)
            for i in range(out[f"{quantity}_pred"].shape[0]):
                (line,) = ax.plot(
                    steps, out[f"{quantity}_real"][i], label="real" if i == 0 else None
                )
                ax.plot(
                    steps,
                    out[f"{quantity}_pred"][i],
                    "--",
                    color=line.get_color(),
                    label="predicted" if i == 0 else None,
                )
            ax.set_title(f"h = {h}")
            ax.set_xlabel("step of the open-loop rollout (0.05 s)")
            ax.set_ylabel(label)
        axes[0].legend()
        fig.tight_layout()
        path = out_dir / f"horizon_{quantity}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        files.append(path)
    return files


def horizon_comparison_table(
    errors: Sequence[HorizonError],
    other: Sequence[HorizonError],
    *,
    label: str = "k=1",
    other_label: str = "k=5",
) -> str:
    """Markdown table of two models' open-loop errors per horizon, side by side.

    Both lists must come from :func:`~torchrl_mbmf.analysis.multistep_mse` on the same data,
    start states and horizons. The ratio columns are ``other / errors`` (below 1: ``other``
    predicts better).

    Args:
        errors: the first model's errors (the reference).
        other: the second model's errors.

    Keyword Args:
        label: name of the first model. Defaults to ``"k=1"``.
        other_label: name of the second model. Defaults to ``"k=5"``.

    Returns:
        The table: x MSE and reward MSE (means over steps ``1..h``) of both models.

    Raises:
        ValueError: if the horizons differ.

    Examples:
        >>> from torchrl_mbmf.analysis import HorizonError
        >>> from torchrl_mbmf.analysis.world_model_job import horizon_comparison_table
        >>> a, b = HorizonError(5, 3, 2.0, 0.4, 3, 1, []), HorizonError(5, 3, 1.0, 0.5, 2, 1, [])
        >>> print(horizon_comparison_table([a], [b]).splitlines()[2])
        | 5 | 2 | 1 | 0.5 | 0.4 | 0.5 | 1.25 |
    """
    if [e.horizon for e in errors] != [e.horizon for e in other]:
        raise ValueError(
            f"horizons differ: {[e.horizon for e in errors]} vs {[e.horizon for e in other]}"
        )
    lines = [
        f"| h | x MSE, {label} | x MSE, {other_label} | x ratio | reward MSE, {label} "
        f"| reward MSE, {other_label} | reward ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for a, b in zip(errors, other, strict=True):
        r_ratio = b.reward_mse / a.reward_mse if a.reward_mse else float("nan")
        if a.x_mse is None or b.x_mse is None:  # a state without an x position
            x_cells = "n/a | n/a | n/a"
        else:
            x_ratio = b.x_mse / a.x_mse if a.x_mse else float("nan")
            x_cells = f"{a.x_mse:.4g} | {b.x_mse:.4g} | {x_ratio:.3g}"
        lines.append(
            f"| {a.horizon} | {x_cells} | {a.reward_mse:.4g} | {b.reward_mse:.4g} | {r_ratio:.3g} |"
        )
    return "\n".join(lines)


def run_fit_world_model(cfg: Any, out_dir: Path) -> dict[str, Any]:
    """Runs the job described by the ``fit_world_model`` Hydra config, writing into ``out_dir``.

    Writes ``dataset/`` (the random transitions), ``world_model.pt`` (state dict and
    constructor config), ``fit_history.json``, ``horizon_mse.json`` and ``horizon_mse.md``, and
    ``horizon_x.png`` / ``horizon_reward.png``. The model is fitted with the settings of
    ``world_model`` (:func:`~torchrl_mbmf.world_model.fit.fit_dynamics_kwargs`, including
    ``world_model.multi_step``).

    With ``compare_multi_step: k`` a second model is fitted with ``multi_step=k`` on the same
    data, from the same initial weights, with the same seed (so the same split and one-step
    minibatch order) and evaluated on the same start states; it writes
    ``world_model_multistep.pt``, ``fit_history_multistep.json``,
    ``horizon_mse_multistep.json`` / ``.md`` and ``horizon_compare.md`` (both models' x and
    reward MSE per horizon, also in the summary as ``horizon_compare_table``).

    Args:
        cfg: the composed config (``env``, ``reward``, ``world_model``, ``seed``,
            ``eval_steps``, ``horizons``, ``eval_starts``, ``plot_rollouts``, ``dataset``,
            ``progress`` and optionally ``compare_multi_step``).
        out_dir: the run folder.

    Returns:
        A summary dict (also written to ``summary.json``).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from omegaconf import OmegaConf
        >>> from torchrl_mbmf.analysis.world_model_job import run_fit_world_model
        >>> cfg = OmegaConf.create({
        ...     "env": {"id": "Pendulum-v1", "num_envs": 1, "device": "cpu"},
        ...     "reward": {"name": "default", "kwargs": {}},
        ...     "world_model": {"hidden_sizes": [8], "lr": 1e-3, "batch_size": 32,
        ...                     "max_epochs": 2, "val_fraction": 0.1, "patience": 5,
        ...                     "random_steps": 100},
        ...     "seed": 0, "eval_steps": 50, "horizons": [1, 5], "eval_starts": 10,
        ...     "plot_rollouts": 1, "dataset": None, "progress": False})
        >>> with tempfile.TemporaryDirectory() as d:
        ...     summary = run_fit_world_model(cfg, Path(d))
        >>> summary["real_steps"]
        150
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    wm = cfg.world_model
    horizons = [int(h) for h in cfg.horizons]
    if not horizons or min(horizons) < 1:
        raise ValueError(f"horizons must all be >= 1, got {horizons}")
    if int(wm.random_steps) < 1:
        raise ValueError(f"world_model.random_steps must be >= 1, got {wm.random_steps}")
    check_number(cfg.eval_steps, "eval_steps", minimum=1, integer=True)
    check_number(cfg.plot_rollouts, "plot_rollouts", minimum=0, integer=True)
    if cfg.eval_starts is not None:
        check_number(cfg.eval_starts, "eval_starts", minimum=1, integer=True, note=" or null")
    fit_kwargs = fit_dynamics_kwargs(wm)
    compare = cfg.get("compare_multi_step")
    if compare is not None:
        compare = check_multi_step(compare, key="compare_multi_step")
        if compare == fit_kwargs["multi_step"]:
            raise ValueError(
                f"compare_multi_step={compare} equals world_model.multi_step; nothing to compare"
            )

    def build(seed: int):
        return make_env(
            cfg.env.id,
            reward=cfg.reward.name,
            reward_kwargs=dict(cfg.reward.kwargs or {}),
            num_envs=int(cfg.env.num_envs),
            seed=seed,
            device=cfg.env.device,
        )

    env = build(cfg.seed)
    expect = env_metadata(env)
    if cfg.dataset:
        data = TransitionDataset.load(cfg.dataset, expect=expect)
    else:
        data = collect_random_transitions(
            env, int(wm.random_steps), seed=cfg.seed, progress=cfg.progress
        )
        data.save(out_dir / "dataset")
    # held-out episodes from another seed of the env
    eval_data = collect_random_transitions(
        build(cfg.seed + 10_000),
        int(cfg.eval_steps),
        seed=cfg.seed + 10_000,
        progress=cfg.progress,
    )
    state_dim = env.full_observation_spec_unbatched[STATE_KEY].shape[-1]
    action_dim = env.full_action_spec_unbatched[env.action_key].shape[-1]
    # the env's action range (no clip to another: Pendulum's is [-2, 2])
    bounds = dict(zip(("action_low", "action_high"), action_bounds(env), strict=True))
    model = DeltaDynamicsModel(state_dim, action_dim, hidden_sizes=tuple(wm.hidden_sizes), **bounds)
    initial_weights = copy.deepcopy(model.state_dict()) if compare is not None else None

    def fit_and_evaluate(
        model: DeltaDynamicsModel, multi_step: int, suffix: str
    ) -> tuple[Any, list[HorizonError], str]:
        history = fit_dynamics(
            model,
            data,
            **{**fit_kwargs, "multi_step": multi_step},
            seed=cfg.seed,
            progress=cfg.progress,
        )
        torch.save(
            {"config": model.config, "state_dict": model.state_dict(), "metadata": expect},
            out_dir / f"world_model{suffix}.pt",
        )
        (out_dir / f"fit_history{suffix}.json").write_text(json.dumps(history.to_dict(), indent=2))
        errors = multistep_mse(
            model, eval_data, horizons=horizons, num_starts=cfg.eval_starts, seed=cfg.seed
        )
        table = horizon_table(errors)
        (out_dir / f"horizon_mse{suffix}.json").write_text(
            json.dumps([e.to_dict() for e in errors], indent=2)
        )
        (out_dir / f"horizon_mse{suffix}.md").write_text(table + "\n")
        return history, errors, table

    history, errors, table = fit_and_evaluate(model, fit_kwargs["multi_step"], "")
    plot_horizon_predictions(
        model, eval_data, horizons, out_dir, num_rollouts=int(cfg.plot_rollouts), seed=cfg.seed
    )
    summary = {
        **expect,
        "seed": int(cfg.seed),
        "random_steps": len(data),
        "eval_steps": len(eval_data),
        "real_steps": len(data) + len(eval_data),
        "epochs": history.epochs,
        "best_epoch": history.best_epoch,
        "best_val_loss": history.best_val_loss,
        "fit_seconds": history.seconds,
        "multi_step": fit_kwargs["multi_step"],
        "multi_step_weight": fit_kwargs["multi_step_weight"],
        "horizon_table": table,
    }
    if compare is not None:
        other = DeltaDynamicsModel(
            state_dim, action_dim, hidden_sizes=tuple(wm.hidden_sizes), **bounds
        )
        other.load_state_dict(initial_weights)
        other_history, other_errors, other_table = fit_and_evaluate(other, compare, "_multistep")
        labels = {"label": f"k={fit_kwargs['multi_step']}", "other_label": f"k={compare}"}
        comparison = horizon_comparison_table(errors, other_errors, **labels)
        fits = "\n".join(
            f"- {label}: {h.epochs} epochs, kept epoch {h.best_epoch}, held-out one-step loss "
            f"{h.best_val_loss:.5g}"
            + (
                f", held-out {h.multi_step}-step loss {h.best_val_multi_step_loss:.5g} "
                f"(early stopping on {h.early_stopping})"
                if h.multi_step > 1
                else ""
            )
            + f", {h.seconds:.0f} s"
            for label, h in zip(labels.values(), (history, other_history), strict=True)
        )
        (out_dir / "horizon_compare.md").write_text(
            f"Open-loop MSE on {errors[0].num_rollouts} held-out start states "
            f"(multi_step_weight={fit_kwargs['multi_step_weight']:g}):\n\n"
            f"{comparison}\n\n{fits}\n"
        )
        logger.info("open-loop errors, %s vs %s:\n%s", *labels.values(), comparison)
        summary.update(
            {
                "compare_multi_step": compare,
                "epochs_multistep": other_history.epochs,
                "best_epoch_multistep": other_history.best_epoch,
                "best_val_loss_multistep": other_history.best_val_loss,
                "best_val_multi_step_loss_multistep": other_history.best_val_multi_step_loss,
                "fit_seconds_multistep": other_history.seconds,
                "horizon_table_multistep": other_table,
                "horizon_compare_table": comparison,
            }
        )
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
