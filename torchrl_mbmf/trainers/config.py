"""Validation of the training config: fail before any work starts, naming the key."""

from __future__ import annotations

from typing import Any

from torchrl_mbmf.envs.transforms.rewards import REWARDS

#: Methods of ``recipes/train.py``.
METHODS: tuple[str, ...] = ("ppo", "mpc", "ppo_mpc", "sac", "sac_mpc")
#: Methods that plan with a learned model.
MODEL_BASED: tuple[str, ...] = ("mpc", "ppo_mpc", "sac_mpc")
#: Methods trained with PPO.
PPO_METHODS: tuple[str, ...] = ("ppo", "mpc", "ppo_mpc")
SAC_UPDATES: tuple[str, ...] = ("fused", "stock")
LOGGERS: tuple[str, ...] = ("csv", "tensorboard", "wandb", "mlflow", "")


class ConfigError(ValueError):
    """A training config value is invalid; the message names the key and the allowed values."""


def _positive(cfg: Any, key: str) -> None:
    node = cfg
    for part in key.split("."):
        node = node[part]
    if not isinstance(node, int | float) or isinstance(node, bool) or node < 1:
        raise ConfigError(f"{key} must be a number >= 1, got {node!r}")


def validate_train_config(cfg: Any) -> None:
    """Checks a composed ``train`` config before anything is built.

    Args:
        cfg: the composed config (an OmegaConf ``DictConfig`` or a nested dict).

    Raises:
        ConfigError: naming the offending key and the allowed values.

    Examples:
        >>> from torchrl_mbmf.trainers.config import ConfigError, validate_train_config
        >>> try:
        ...     validate_train_config({"method": "dqn"})
        ... except ConfigError as err:
        ...     print(err)
        method='dqn' is not a method; allowed: ['ppo', 'mpc', 'ppo_mpc', 'sac', 'sac_mpc']
    """
    method = cfg["method"]
    if method not in METHODS:
        raise ConfigError(f"method={method!r} is not a method; allowed: {list(METHODS)}")
    reward = cfg["reward"]["name"]
    if reward not in REWARDS:
        raise ConfigError(f"reward.name={reward!r} is not a reward; allowed: {sorted(REWARDS)}")
    if cfg["logger"]["backend"] not in LOGGERS:
        raise ConfigError(
            f"logger.backend={cfg['logger']['backend']!r} is not supported; allowed: "
            f"{list(LOGGERS)}"
        )
    if cfg["sac"].get("update", "stock") not in SAC_UPDATES:
        raise ConfigError(
            f"sac.update={cfg['sac']['update']!r} is not supported; allowed: {list(SAC_UPDATES)}"
        )
    for key in (
        "total_steps",
        "env.num_envs",
        "planner.num_candidates",
        "planner.horizon",
        "world_model.random_steps",
        "world_model.refit_every",
        "world_model.max_epochs",
        "world_model.batch_size",
        "eval_every",
        "checkpoint.every_steps",
        "checkpoint.keep_last",
        "ppo.frames_per_batch",
        "ppo.minibatch_size",
        "ppo.epochs",
        "sac.frames_per_batch",
        "sac.batch_size",
        "sac.refit_every_steps",
    ):
        _positive(cfg, key)
    if not 0 < cfg["planner"]["discount"] <= 1:
        raise ConfigError(f"planner.discount must be in (0, 1], got {cfg['planner']['discount']}")
    n_envs = int(cfg["env"]["num_envs"])
    algo = "ppo" if method in PPO_METHODS else "sac"
    frames = int(cfg[algo]["frames_per_batch"])
    if frames % n_envs:
        raise ConfigError(
            f"{algo}.frames_per_batch={frames} must be a multiple of env.num_envs={n_envs}"
        )
    if method in PPO_METHODS and frames % int(cfg["ppo"]["minibatch_size"]):
        raise ConfigError(
            f"ppo.frames_per_batch={frames} must be a multiple of "
            f"ppo.minibatch_size={cfg['ppo']['minibatch_size']}"
        )
    total = int(cfg["total_steps"])
    if method in ("mpc", "ppo_mpc"):
        updates = int(cfg["planning_updates"])
        if updates < 0:
            raise ConfigError(f"planning_updates must be >= 0, got {updates}")
        needed = int(cfg["world_model"]["random_steps"]) + updates * frames
        if needed > total:
            raise ConfigError(
                f"planning_updates={updates} needs world_model.random_steps + planning_updates "
                f"x ppo.frames_per_batch = {needed} real steps, beyond total_steps={total}"
            )
    if method in MODEL_BASED and int(cfg["world_model"]["random_steps"]) >= total:
        raise ConfigError(
            f"world_model.random_steps={cfg['world_model']['random_steps']} leaves no steps "
            f"of total_steps={total} for training"
        )
