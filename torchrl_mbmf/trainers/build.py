"""Building a run's parts from its config: envs, collectors, hooks, the evaluation rollout."""

from __future__ import annotations

import random
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger, get_logger

from torchrl_mbmf.checks import choice
from torchrl_mbmf.envs.factory import make_env
from torchrl_mbmf.moved import moved_attribute
from torchrl_mbmf.runs.layout import LOGS
from torchrl_mbmf.trainers.hooks import (
    EpisodeLog,
    Evaluation,
    HookFn,
    Hooks,
    ModelData,
    ModelRefit,
    ModelRollouts,
    ProgressBar,
    SaveCheckpoint,
    StepTiming,
)
from torchrl_mbmf.trainers.progress import RunPlan
from torchrl_mbmf.trainers.settings import EnvSettings, RewardSettings, TrainConfig

__all__ = [
    "LOGGERS",
    "make_hooks",
    "make_logger",
    "make_settings_env",
    "make_train_env",
    "seed_everything",
]

#: Names that moved to another module (kept here for one release, with a warning).
MOVED_NAMES: dict[str, str] = {
    "evaluate_policy": "torchrl_mbmf.collectors.factory",
    "make_collector": "torchrl_mbmf.collectors.factory",
}

#: Logger backends of the ``logger`` group (``""``: no logger).
LOGGERS: tuple[str, ...] = ("csv", "tensorboard", "wandb", "mlflow", "")


def seed_everything(seed: int) -> None:
    """Seeds Python, NumPy and torch.

    Args:
        seed: the seed.

    Examples:
        >>> from torchrl_mbmf.trainers.build import seed_everything
        >>> seed_everything(0)
    """
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def make_train_env(cfg: DictConfig, seed: int, num_envs: int | None = None) -> EnvBase:
    """The env of the ``env`` and ``reward`` config groups.

    Args:
        cfg: the training config.
        seed: the env seed.
        num_envs: batched envs; ``env.num_envs`` by default.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"env": {"id": "Pendulum-v1", "num_envs": 2, "device": "cpu"},
        ...                         "reward": {"name": "default", "kwargs": {}}})
        >>> make_train_env(cfg, seed=0).batch_size
        torch.Size([2])
    """
    env = EnvSettings(str(cfg.env.id), int(cfg.env.num_envs), str(cfg.env.device))
    return make_settings_env(
        env, RewardSettings(cfg.reward.name, cfg.reward.kwargs or {}), seed, num_envs
    )


def make_settings_env(
    env: EnvSettings, reward: RewardSettings, seed: int, num_envs: int | None = None
) -> EnvBase:
    """The env of parsed ``env`` and ``reward`` settings.

    Args:
        env: the ``env`` group's settings.
        reward: the ``reward`` group's settings.
        seed: the env seed.
        num_envs: batched envs; ``env.num_envs`` by default.

    Examples:
        >>> from torchrl_mbmf.trainers.settings import EnvSettings, RewardSettings
        >>> env = EnvSettings("Pendulum-v1", 2, "cpu")
        >>> make_settings_env(env, RewardSettings("default"), seed=0).batch_size
        torch.Size([2])
    """
    return make_env(
        env.id,
        reward=reward.name,
        reward_kwargs=dict(reward.kwargs or {}),
        num_envs=int(env.num_envs if num_envs is None else num_envs),
        seed=seed,
        device=env.device,
    )


def make_logger(run_dir: str | Path, *, backend: str) -> Logger | None:
    """The run's logger: the ``logger`` config group's builder (its ``_target_``).

    Args:
        run_dir: the run folder (the logs go to ``run_dir/logs``).

    Keyword Args:
        backend: a :data:`LOGGERS` entry, passed to :func:`torchrl.record.loggers.get_logger`
            (``""``: no logger).

    Examples:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     type(make_logger(d, backend="csv")).__name__
        'CSVLogger'
    """
    choice(*LOGGERS).check("backend", backend)
    return get_logger(backend, logger_name=str(run_dir), experiment_name=LOGS)


def make_hooks(config: TrainConfig, model_based: bool) -> tuple[Hooks, dict[str, HookFn]]:
    """The loop's hooks of a parsed config, and the ones the loop also calls by name.

    Args:
        config: the parsed training config.
        model_based: whether the run has a world model (data and refit hooks).

    Returns:
        ``(hooks, named)`` with ``named`` holding ``bar``, ``timing``, ``checkpoints`` and
        ``evaluation``.

    Examples:
        >>> from hydra import compose, initialize_config_dir
        >>> from pathlib import Path
        >>> from torchrl_mbmf.trainers.settings import TrainConfig
        >>> with initialize_config_dir(str(Path("configs").resolve()), version_base="1.3"):
        ...     cfg = compose("train", overrides=["method=ppo", "env=pendulum", "progress=false"])
        >>> hooks, named = make_hooks(TrainConfig.from_config(cfg), model_based=False)
        >>> [type(h).__name__ for h in hooks.stages["updated"]]
        ['StepTiming', 'Evaluation']
    """
    named = {
        "bar": ProgressBar(
            config.total_steps,
            config.method,
            config.progress,
            RunPlan.from_config(config) if config.progress else None,
        ),
        "timing": StepTiming(),
        "checkpoints": SaveCheckpoint(config.checkpoint.every_steps),
        "evaluation": Evaluation(config.eval_every, config.eval_episodes),
    }
    hooks = Hooks()
    hooks.register("collected", named["bar"])
    hooks.register("collected", EpisodeLog())
    if model_based:
        hooks.register("collected", ModelData())
        if config.method == "sac_mbpo":
            hooks.register("collected", ModelRollouts())
        hooks.register("updated", ModelRefit())
    hooks.register("updated", named["timing"])
    hooks.register("updated", named["evaluation"])
    hooks.register("round_end", named["checkpoints"])
    return hooks, named


def __getattr__(name: str) -> object:
    return moved_attribute(__name__, name, MOVED_NAMES)
