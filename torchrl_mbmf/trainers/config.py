"""Validation of the training config: the trainer's own settings and the checks across keys.

How the config is checked and parsed: ``docs/design/config.md``.
"""

from __future__ import annotations

import difflib
import inspect
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from torchrl_mbmf.checks import ConfigError, Setting, check_number
from torchrl_mbmf.device import DeviceError, resolve_device
from torchrl_mbmf.envs.transforms.rewards import REWARDS
from torchrl_mbmf.methods import GUIDED, METHODS, MODEL_BASED, PPO_METHODS
from torchrl_mbmf.runs.resume import (
    DEFAULT_TARGETS,
    OPTIONAL_GROUPS,
    RESUME_SAFE_SETTINGS,
    flatten_settings,
    resume_changes,
)
from torchrl_mbmf.trainers.components import group_keys, group_target
from torchrl_mbmf.world_model.branched_rollouts import check_mbpo_config

__all__ = [
    "METHODS",
    "MODEL_BASED",
    "PPO_METHODS",
    "RESUME_SAFE_SETTINGS",
    "TRAIN_SETTINGS",
    "ConfigError",
    "TrainSettings",
    "flatten_config",
    "resume_changes",
    "train_setting_keys",
    "validate_train_config",
]

COLLECTORS: tuple[str, ...] = ("lean", "stock")
#: Largest seed NumPy accepts (``np.random.seed``).
MAX_SEED = 2**32 - 1


def _int(low: int | None = None, **kw: Any) -> Setting:
    return Setting("int", low, **kw)


_OPTIONAL = {"required": False}

#: The trainer's own settings (flattened keys), with their type and range; any other key that
#: is not a component group's is refused as unknown.
TRAIN_SETTINGS: dict[str, Setting] = {
    "method": Setting("choice", choices=METHODS),
    "seed": _int(0, high=MAX_SEED),
    "total_steps": _int(1),
    "planning_updates": _int(0),
    "eval_every": _int(1),
    "eval_episodes": _int(0),  # 0: no evaluation (final_eval_return is null)
    "checkpoint.every_steps": _int(1),
    "checkpoint.keep_last": _int(1),
    "progress": Setting("bool"),
    "threads": _int(1, nullable=True, **_OPTIONAL),
    "run_name": Setting("str", **_OPTIONAL),
    "run_dir": Setting("str", **_OPTIONAL),
    "restart": Setting("bool", **_OPTIONAL),
    "budget.name": Setting("str", **_OPTIONAL),
    "env.id": Setting("str"),
    "env.num_envs": _int(1),
    "env.device": Setting("str"),
    "reward.name": Setting("choice", choices=tuple(sorted(REWARDS))),
    "reward.kwargs": Setting("dict", nullable=True, **_OPTIONAL),
    "collector": Setting("choice", choices=COLLECTORS, **_OPTIONAL),
    "device": Setting("str", **_OPTIONAL),
}
#: Subtrees whose keys are not fixed (``experiment``: a preset's name and budgets).
FREE_FORM: tuple[str, ...] = ("experiment",)
#: Top-level nodes that are not train settings (Hydra's own): neither checked nor compared.
NOT_SETTINGS: tuple[str, ...] = ("hydra",)


def _resolved(cfg: Any) -> dict[str, Any]:
    """``cfg`` as plain, resolved containers, without :data:`NOT_SETTINGS`."""
    if not isinstance(cfg, DictConfig):
        return {k: v for k, v in cfg.items() if k not in NOT_SETTINGS}
    out: dict[str, Any] = {}
    for key in cfg:
        if key in NOT_SETTINGS:
            continue
        value = cfg[key]
        if isinstance(value, DictConfig | ListConfig):
            value = OmegaConf.to_container(value, resolve=True)
        out[key] = value
    return out


def flatten_config(cfg: Any, prefix: str = "") -> dict[str, Any]:
    """Flattens a (resolved) config into ``{"a.b.c": value}``; lists and empty dicts are leaves.

    Args:
        cfg: a ``DictConfig`` (its ``hydra`` node left out) or a nested mapping.
        prefix: prepended to every key. Defaults to ``""``.

    Returns:
        The flat mapping, values as plain Python objects.

    Examples:
        >>> from torchrl_mbmf.trainers.config import flatten_config
        >>> flatten_config({"ppo": {"lr": 3e-4, "hidden_sizes": [64, 64]}, "kw": {}})
        {'ppo.lr': 0.0003, 'ppo.hidden_sizes': [64, 64], 'kw': {}}
    """
    if isinstance(cfg, DictConfig):
        cfg = _resolved(cfg)
    return flatten_settings(cfg, prefix)


def train_setting_keys(cfg: Any) -> dict[str, bool]:
    """Every key the train config may hold, with whether it is required.

    Args:
        cfg: the config (its ``_target_`` entries name the builders, whose keyword-only
            parameters are their group's keys).

    Examples:
        >>> from torchrl_mbmf.trainers.config import train_setting_keys
        >>> cfg = {g: {} for g in ("ppo", "sac", "world_model", "planner", "logger")}
        >>> keys = train_setting_keys(cfg)
        >>> keys["planner.horizon"], keys["planner.discount"], keys["ppo.gamma"]
        (True, False, True)
    """
    keys = {key: setting.required for key, setting in TRAIN_SETTINGS.items()}
    for group in DEFAULT_TARGETS:
        if group not in cfg and group in OPTIONAL_GROUPS:
            continue
        if group not in cfg:
            raise ConfigError(f"the {group} group is missing from the train config")
        names, required = group_keys(group_target(cfg, group))
        keys[f"{group}._target_"] = False
        keys.update({f"{group}.{name}": name in required for name in names})
    return keys


def _check_settings(cfg: Any) -> None:
    """Unknown and missing keys, and the type and range of the trainer's own settings."""
    tree = _resolved(cfg)
    kwargs_node = tree.get("reward", {}).get("kwargs")
    flat = flatten_config({k: v for k, v in tree.items() if k not in FREE_FORM})
    flat = {k: v for k, v in flat.items() if not k.startswith("reward.kwargs.")}
    if "reward" in tree and "kwargs" in tree["reward"]:
        flat["reward.kwargs"] = kwargs_node
    known = train_setting_keys(tree)
    for key in flat:
        if key not in known:
            close = difflib.get_close_matches(key, list(known), n=1, cutoff=0.6)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ConfigError(
                f"{key} is not a setting of the train config{hint} (a typo, or a key added "
                "with + that nothing reads)"
            )
    for key, required in known.items():
        if required and key not in flat:
            raise ConfigError(f"{key} is missing from the train config")
    for key, setting in TRAIN_SETTINGS.items():
        if key in flat:
            setting.check(key, flat[key])
    _check_reward_kwargs(tree["reward"]["name"], kwargs_node or {})


def _check_reward_kwargs(name: str, kwargs: Mapping[str, Any]) -> None:
    """reward.kwargs must be constructor parameters of the reward, with values it accepts."""
    cls = REWARDS[name]
    params = inspect.signature(cls.__init__).parameters
    accepted = [p for p in params if p != "self" and not p.endswith("_key")]
    for key in kwargs:
        if key not in accepted:
            raise ConfigError(
                f"reward.kwargs.{key} is not a parameter of {cls.__name__} "
                f"(reward.name={name!r}); allowed: {accepted}"
            )
    try:
        cls(**dict(kwargs))
    except (TypeError, ValueError) as err:
        raise ConfigError(f"reward.kwargs: {err}") from err


def _count(value: Any) -> int | None:
    """``value`` if it is an integer >= 1, else ``None`` (its constructor reports it)."""
    ok = isinstance(value, int) and not isinstance(value, bool) and value >= 1
    return value if ok else None


def validate_train_config(cfg: Any) -> None:
    """Checks a composed ``train`` config before anything is built (``docs/design/config.md``).

    Args:
        cfg: the composed config (an OmegaConf ``DictConfig`` or a nested dict).

    Raises:
        ConfigError: naming the offending key and the allowed values.

    Examples:
        >>> from torchrl_mbmf.trainers.config import ConfigError, validate_train_config
        >>> try:
        ...     validate_train_config({"method": "dqn"})
        ... except ConfigError as err:
        ...     print(err)  # doctest: +NORMALIZE_WHITESPACE
        method='dqn' is not a method; allowed: ['ppo', 'mpc', 'ppo_mpc', 'sac', 'sac_mpc',
        'sac_mbpo']
    """
    method = cfg["method"]
    if method not in METHODS:
        raise ConfigError(f"method={method!r} is not a method; allowed: {list(METHODS)}")
    if "reward" in cfg and cfg["reward"]["name"] not in REWARDS:
        raise ConfigError(
            f"reward.name={cfg['reward']['name']!r} is not a reward; allowed: {sorted(REWARDS)}"
        )
    _check_settings(cfg)
    try:
        resolve_device(cfg.get("device", "cpu"))
    except DeviceError as err:
        raise ConfigError(str(err)) from err
    _check_env(cfg["env"])
    _check_budgets(cfg, method)
    _check_planner_variants(cfg, method)
    _check_world_model_variants(cfg, method)
    if method == "sac_mbpo":
        check_mbpo_config(cfg)


def _check_env(env: Any) -> None:
    """``env.id`` is a registered Gymnasium id and ``env.device`` a torch device."""
    import gymnasium as gym
    import torch

    env_id = env["id"]
    if env_id not in gym.registry:
        close = difflib.get_close_matches(str(env_id), list(gym.registry), n=3, cutoff=0.6)
        hint = f"; close ids: {close}" if close else ""
        raise ConfigError(
            f"env.id={env_id!r} is not a registered Gymnasium id{hint}; the tasks with configs: "
            "env=half_cheetah|hopper|walker2d|ant|inverted_pendulum|pendulum"
        )
    try:
        torch.device(env["device"])
    except (RuntimeError, TypeError) as err:
        raise ConfigError(
            f"env.device={env['device']!r} is not a torch device (the real envs run on the "
            "CPU: use cpu)"
        ) from err


def _check_budgets(cfg: Any, method: str) -> None:
    n_envs = int(cfg["env"]["num_envs"])
    algo = "ppo" if method in PPO_METHODS else "sac"
    frames = _count(cfg[algo]["frames_per_batch"])
    if frames is not None and frames % n_envs:
        raise ConfigError(
            f"{algo}.frames_per_batch={frames} must be a multiple of env.num_envs={n_envs}"
        )
    minibatch = _count(cfg["ppo"]["minibatch_size"])
    if method in PPO_METHODS and frames and minibatch and frames % minibatch:
        raise ConfigError(
            f"ppo.frames_per_batch={frames} must be a multiple of ppo.minibatch_size={minibatch}"
        )
    total = int(cfg["total_steps"])
    random_steps = _count(cfg["world_model"]["random_steps"])
    if method in ("mpc", "ppo_mpc") and frames and random_steps:
        updates = int(cfg["planning_updates"])
        needed = random_steps + updates * frames
        if needed > total:
            raise ConfigError(
                f"planning_updates={updates} needs world_model.random_steps + planning_updates "
                f"x ppo.frames_per_batch = {needed} real steps, beyond total_steps={total}"
            )
    if method in MODEL_BASED and random_steps and random_steps >= total:
        raise ConfigError(
            f"world_model.random_steps={random_steps} leaves no steps "
            f"of total_steps={total} for training"
        )
    if algo == "sac":
        _check_sac_sizes(cfg["sac"], frames, total)


def _check_sac_sizes(sac: Any, frames: int | None, total: int) -> None:
    """SAC's replay, batch and warm-up sizes against each other and the budget."""
    replay, batch = _count(sac["replay_size"]), _count(sac["batch_size"])
    if replay and batch and batch > replay:
        raise ConfigError(
            f"sac.batch_size={batch} is larger than sac.replay_size={replay}: no batch can be "
            "sampled without repeats"
        )
    if replay and frames and replay < frames:
        raise ConfigError(
            f"sac.replay_size={replay} is smaller than sac.frames_per_batch={frames}: a "
            "collected batch would overwrite itself"
        )
    warmup = sac.get("init_random_frames")
    if isinstance(warmup, int) and not isinstance(warmup, bool) and warmup >= total:
        raise ConfigError(
            f"sac.init_random_frames={warmup} leaves no steps of total_steps={total} for SAC "
            "updates (the run would end without one)"
        )


#: The planner's refinement keys, checked even without a refinement (a NaN there is no
#: setting): ``(key, integer, minimum, upper bound excluded)``.
_REFINEMENT_KEYS: tuple[tuple[str, bool, float, float | None], ...] = (
    ("iterations", True, 1, None),
    ("num_elites", True, 1, None),
    ("policy_fraction", False, 0, 1.0),
    ("temperature", False, 0, None),
    ("min_std", False, 0, None),
)


def _check_refinement_keys(planner: Any) -> None:
    for key, integer, minimum, below in _REFINEMENT_KEYS:
        if key not in planner:
            continue
        value = planner[key]
        try:
            value = check_number(value, f"planner.{key}", minimum=minimum, integer=integer)
        except ValueError as err:
            raise ConfigError(str(err)) from err
        if (below is not None and value >= below) or (key == "temperature" and value == 0):
            bound = f"in [{minimum}, {below})" if below is not None else "> 0"
            raise ConfigError(f"planner.{key} must be {bound}, got {value}")


def _check_planner_variants(cfg: Any, method: str) -> None:
    planner = cfg["planner"]
    _check_refinement_keys(planner)
    refinement = planner.get("refinement")
    if refinement is None:
        return
    if method not in GUIDED:
        raise ConfigError(
            f"planner.refinement={refinement!r} refines around the policy prior; it needs "
            f"method ppo_mpc or sac_mpc, got method={method!r}"
        )
    elites, m = planner.get("num_elites", 3), _count(planner["num_candidates"])
    if m is not None and not (_count(elites) and elites <= m):
        raise ConfigError(
            f"planner.num_elites must be an integer in [1, planner.num_candidates={m}], "
            f"got {elites!r}"
        )


def _check_world_model_variants(cfg: Any, method: str) -> None:
    wm = cfg["world_model"]
    members = _count(wm.get("ensemble_size", 1)) or 1
    if members > 1 and method not in (*GUIDED, "sac_mbpo"):
        raise ConfigError(
            f"world_model.ensemble_size={members} plans with the ensemble policy-guided planner; "
            f"it needs method ppo_mpc or sac_mpc (or sac_mbpo), got method={method!r}"
        )
    if members > 1 and (_count(wm.get("multi_step", 1)) or 1) > 1:
        raise ConfigError(
            "world_model.multi_step > 1 is implemented for the single model only; set "
            "world_model.ensemble_size=1 or world_model.multi_step=1"
        )
    if wm.get("adaptive_horizon", False) is True and members < 2:
        raise ConfigError(
            "world_model.adaptive_horizon needs an ensemble (world_model.ensemble_size >= 2), "
            f"got ensemble_size={members}"
        )


@dataclass(frozen=True)
class TrainSettings:
    """The trainer's own settings (what the loop reads while it runs), parsed once.

    Args:
        method: one of :data:`METHODS`.
        seed: the run's seed.
        total_steps: the real-step budget.
        frames_per_batch: real steps per collected batch (``ppo.`` or ``sac.frames_per_batch``).
        eval_episodes: evaluation episodes (0: no evaluation).
        checkpoint_every: real steps between two checkpoints.
        keep_last: checkpoints kept.
        env_id: the env's id.
        reward: the reward's name.
        collector: ``"lean"`` or ``"stock"``.
        device: the ``device`` setting.
        threads: torch threads (``None``: torch's default).
        logger_backend: the logger's backend.

    Examples:
        >>> from hydra import compose, initialize_config_dir
        >>> from pathlib import Path
        >>> with initialize_config_dir(str(Path("configs").resolve()), version_base="1.3"):
        ...     cfg = compose("train", overrides=["method=sac", "env=pendulum"])
        >>> settings = TrainSettings.from_config(cfg)
        >>> settings.method, settings.family, settings.model_based
        ('sac', 'sac', False)
    """

    method: str
    seed: int
    total_steps: int
    frames_per_batch: int
    eval_episodes: int
    checkpoint_every: int
    keep_last: int
    env_id: str
    reward: str
    collector: str = "lean"
    device: str = "cpu"
    threads: int | None = None
    logger_backend: str = "csv"

    @property
    def family(self) -> str:
        """``"ppo"`` or ``"sac"``: the agent's config group."""
        return "ppo" if self.method in PPO_METHODS else "sac"

    @property
    def model_based(self) -> bool:
        """Whether the method plans with a learned model."""
        return self.method in MODEL_BASED

    @classmethod
    def from_config(cls, cfg: DictConfig) -> TrainSettings:
        """Validates ``cfg`` (:func:`validate_train_config`) and parses the trainer's settings.

        Args:
            cfg: the composed training config.

        Raises:
            ConfigError: naming the first invalid key.
        """
        validate_train_config(cfg)
        family = "ppo" if cfg.method in PPO_METHODS else "sac"
        threads = cfg.get("threads")
        return cls(
            method=str(cfg.method),
            seed=int(cfg.seed),
            total_steps=int(cfg.total_steps),
            frames_per_batch=int(cfg[family].frames_per_batch),
            eval_episodes=int(cfg.eval_episodes),
            checkpoint_every=int(cfg.checkpoint.every_steps),
            keep_last=int(cfg.checkpoint.keep_last),
            env_id=str(cfg.env.id),
            reward=str(cfg.reward.name),
            collector=str(cfg.get("collector", "lean")),
            device=str(cfg.get("device", "cpu")),
            threads=None if threads is None else int(threads),
            logger_backend=str(cfg.logger.backend),
        )
