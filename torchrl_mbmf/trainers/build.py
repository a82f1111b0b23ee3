"""Building a run's parts from its config: envs, collectors, hooks, the evaluation rollout."""

from __future__ import annotations

import copy
import random
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.record.loggers import Logger, get_logger

from torchrl_mbmf.checks import check_finite, choice
from torchrl_mbmf.collectors import LeanCollector
from torchrl_mbmf.envs.factory import make_env
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
    "evaluate_policy",
    "make_collector",
    "make_hooks",
    "make_logger",
    "make_settings_env",
    "make_train_env",
    "seed_everything",
]

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


def make_collector(
    env: EnvBase,
    policy: TensorDictModuleBase | Callable[[TensorDictBase], TensorDictBase],
    frames: int,
    total: int,
    device: torch.device,
    kind: str = "lean",
) -> Collector | LeanCollector:
    """The lean collector where the env supports it (``kind="lean"``), else the stock one.

    Args:
        env: the (CPU) env.
        policy: the acting policy.
        frames: frames per batch.
        total: total frames (``-1``: unbounded).
        device: the policy's device.
        kind: ``"lean"`` or ``"stock"`` (``collector`` setting).

    Examples:
        >>> from torchrl.envs.utils import RandomPolicy
        >>> from torchrl_mbmf.envs import make_env
        >>> env = make_env("Pendulum-v1", seed=0)
        >>> c = make_collector(env, RandomPolicy(env.full_action_spec), 8, 8, torch.device("cpu"))
        >>> next(iter(c)).numel()
        8
    """
    if kind == "lean" and LeanCollector.supports(env):
        return LeanCollector(
            env, policy, frames_per_batch=frames, total_frames=total, policy_device=device
        )
    devices = {}
    if device.type != "cpu":
        devices = {"policy_device": device, "env_device": "cpu", "storing_device": "cpu"}
    return Collector(
        env,
        policy,
        frames_per_batch=frames,
        total_frames=total,
        auto_register_policy_transforms=False,
        **devices,
    )


def evaluate_policy(
    env: EnvBase,
    actor: TensorDictModuleBase,
    episodes: int,
    device: torch.device,
    kind: str = "lean",
    step: int = 0,
) -> float:
    """Mean return of ``actor`` alone, deterministic, over ``episodes`` episodes of ``env``.

    Args:
        env: the evaluation env (one env; seeded by the caller).
        actor: the policy.
        episodes: episodes to average.
        device: the actor's device.
        kind: the collection path (``"lean"``: the same episode as ``env.rollout``, tested).
        step: the real-step count named if the return is not finite.

    Examples:
        >>> from torchrl_mbmf.envs import make_env
        >>> from torchrl_mbmf.modules import make_ppo_actor_critic
        >>> env = make_env("Pendulum-v1", seed=0)
        >>> actor, _ = make_ppo_actor_critic(env, hidden_sizes=(8,))
        >>> evaluate_policy(env, actor, 1, torch.device("cpu")) < 0
        True
    """
    returns = []
    lean = kind == "lean" and LeanCollector.supports(env)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        for _ in range(int(episodes)):
            if lean:
                td = LeanCollector(
                    env,
                    actor,
                    frames_per_batch=1,
                    exploration_type=ExplorationType.DETERMINISTIC,
                    policy_device=device,
                ).episode()
            elif device.type != "cpu":
                # the stock env rollout runs the policy where the env is: a CPU copy
                td = env.rollout(100_000, copy.deepcopy(actor).to("cpu"))
            else:
                td = env.rollout(100_000, actor)
            returns.append(float(td.get(("next", "reward")).sum()))
    mean = float(np.mean(returns))
    check_finite({"eval/return": mean}, step)
    return mean


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
