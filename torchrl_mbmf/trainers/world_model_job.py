"""The fit-world-model job: random data, fit, horizon evaluation, plots."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import torch

from torchrl_mbmf.analysis.horizon import horizon_predictions, horizon_table, multistep_mse
from torchrl_mbmf.data.transitions import TransitionDataset, collect_random_transitions
from torchrl_mbmf.envs.factory import env_metadata, make_env
from torchrl_mbmf.envs.keys import STATE_KEY
from torchrl_mbmf.modules.dynamics import DeltaDynamicsModel
from torchrl_mbmf.trainers.dynamics import fit_dynamics

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
        The written files (``horizon_x.png``, ``horizon_reward.png``).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.data import collect_random_transitions
        >>> from torchrl_mbmf.envs import make_gym_state_env
        >>> from torchrl_mbmf.modules import DeltaDynamicsModel
        >>> from torchrl_mbmf.trainers.world_model_job import plot_horizon_predictions
        >>> data = collect_random_transitions(make_gym_state_env("Pendulum-v1"), 60, seed=0)
        >>> with tempfile.TemporaryDirectory() as d:
        ...     files = plot_horizon_predictions(DeltaDynamicsModel(3, 1), data, [5], Path(d))
        >>> [f.name for f in files]
        ['horizon_x.png', 'horizon_reward.png']
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    for quantity, label in (("x", "x position (m)"), ("reward", "reward per step")):
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


def run_fit_world_model(cfg: Any, out_dir: Path) -> dict[str, Any]:
    """Runs the job described by the ``fit_world_model`` Hydra config, writing into ``out_dir``.

    Writes ``dataset/`` (the random transitions), ``world_model.pt`` (state dict and
    constructor config), ``fit_history.json``, ``horizon_mse.json`` and ``horizon_mse.md``, and
    ``horizon_x.png`` / ``horizon_reward.png``.

    Args:
        cfg: the composed config (``env``, ``reward``, ``world_model``, ``seed``,
            ``eval_steps``, ``horizons``, ``eval_starts``, ``plot_rollouts``, ``dataset``,
            ``progress``).
        out_dir: the run folder.

    Returns:
        A summary dict (also written to ``summary.json``).

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from omegaconf import OmegaConf
        >>> from torchrl_mbmf.trainers.world_model_job import run_fit_world_model
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
    model = DeltaDynamicsModel(state_dim, action_dim, hidden_sizes=tuple(wm.hidden_sizes))
    history = fit_dynamics(
        model,
        data,
        lr=float(wm.lr),
        batch_size=int(wm.batch_size),
        max_epochs=int(wm.max_epochs),
        val_fraction=float(wm.val_fraction),
        patience=int(wm.patience),
        seed=cfg.seed,
        progress=cfg.progress,
    )
    torch.save(
        {"config": model.config, "state_dict": model.state_dict(), "metadata": expect},
        out_dir / "world_model.pt",
    )
    (out_dir / "fit_history.json").write_text(json.dumps(history.to_dict(), indent=2))
    errors = multistep_mse(
        model, eval_data, horizons=horizons, num_starts=cfg.eval_starts, seed=cfg.seed
    )
    table = horizon_table(errors)
    (out_dir / "horizon_mse.json").write_text(json.dumps([e.to_dict() for e in errors], indent=2))
    (out_dir / "horizon_mse.md").write_text(table + "\n")
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
        "horizon_table": table,
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
