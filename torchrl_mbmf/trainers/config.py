"""Validation of the training config: fail before any work starts, naming the key."""

from __future__ import annotations

import difflib
import inspect
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from torchrl_mbmf.envs.transforms.rewards import REWARDS
from torchrl_mbmf.modules.planners.policy_guided import REFINEMENTS
from torchrl_mbmf.trainers.device import DeviceError, resolve_device

#: Methods of ``recipes/train.py``.
METHODS: tuple[str, ...] = ("ppo", "mpc", "ppo_mpc", "sac", "sac_mpc")
#: Methods that plan with a learned model.
MODEL_BASED: tuple[str, ...] = ("mpc", "ppo_mpc", "sac_mpc")
#: Methods trained with PPO.
PPO_METHODS: tuple[str, ...] = ("ppo", "mpc", "ppo_mpc")
SAC_UPDATES: tuple[str, ...] = ("fused", "stock")
COLLECTORS: tuple[str, ...] = ("lean", "stock")
PPO_UPDATES: tuple[str, ...] = ("fused", "fused_autograd", "stock")
LOGGERS: tuple[str, ...] = ("csv", "tensorboard", "wandb", "mlflow", "")
DISTRIBUTIONS: tuple[str, ...] = ("tanh_normal", "normal")
EARLY_STOPPING: tuple[str, ...] = ("objective", "one_step")
#: Largest seed NumPy accepts (``np.random.seed``).
MAX_SEED = 2**32 - 1


class ConfigError(ValueError):
    """A training config value is invalid; the message names the key and the allowed values."""


@dataclass(frozen=True)
class Setting:
    """The type and range of one train setting.

    Args:
        kind: ``"int"``, ``"float"``, ``"bool"``, ``"str"``, ``"choice"`` or ``"sizes"`` (a list
            of integers >= 1, possibly empty).
        low: smallest allowed value, or ``None``. Defaults to ``None``.
        high: largest allowed value, or ``None``. Defaults to ``None``.
        low_open: ``low`` itself is excluded. Defaults to ``False``.
        high_open: ``high`` itself is excluded. Defaults to ``False``.
        choices: the allowed values of a ``"choice"``. Defaults to none.
        nullable: ``null`` is allowed too. Defaults to ``False``.
        required: the key must be present (the trainer reads it without a default).
            Defaults to ``True``.

    Examples:
        >>> from torchrl_mbmf.trainers.config import Setting
        >>> Setting("float", 0, 1, low_open=True).check("ppo.gamma", 0.99)
        >>> try:
        ...     Setting("float", 0, 1, low_open=True).check("ppo.gamma", 5)
        ... except ValueError as err:
        ...     print(err)
        ppo.gamma must be a number in (0, 1], got 5
    """

    kind: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[Any, ...] = ()
    nullable: bool = False
    required: bool = True

    def describe(self) -> str:
        """What the setting must be, in words (``"a number in (0, 1]"``)."""
        what = {
            "int": "an integer",
            "float": "a number",
            "bool": "true or false",
            "str": "a string",
            "sizes": "a list of integers >= 1",
        }.get(self.kind, "")
        if self.kind in ("int", "float"):
            if self.low is not None and self.high is not None:
                left = "(" if self.low_open else "["
                right = ")" if self.high_open else "]"
                what += f" in {left}{_fmt(self.low)}, {_fmt(self.high)}{right}"
            elif self.low is not None:
                what += f" {'>' if self.low_open else '>='} {_fmt(self.low)}"
            elif self.high is not None:
                what += f" {'<' if self.high_open else '<='} {_fmt(self.high)}"
            elif self.kind == "float":
                what = "a finite number"
        return f"null or {what}" if self.nullable else what

    def check(self, key: str, value: Any) -> None:
        """Raises :class:`ConfigError` naming ``key`` and ``value`` unless the value fits."""
        if value is None and self.nullable:
            return
        if self.kind == "choice":
            if value not in self.choices:
                raise ConfigError(
                    f"{key}={value!r} is not supported; allowed: {list(self.choices)}"
                )
            return
        if not self._fits(value):
            raise ConfigError(f"{key} must be {self.describe()}, got {value!r}")

    def _fits(self, value: Any) -> bool:
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind == "str":
            return isinstance(value, str) and bool(value)
        if self.kind == "sizes":
            return (
                isinstance(value, Sequence | ListConfig)
                and not isinstance(value, str)
                and all(_is_int(h) and h >= 1 for h in value)
            )
        if self.kind == "int" and not _is_int(value):
            return False
        if isinstance(value, bool) or not isinstance(value, int | float):
            return False
        if not math.isfinite(value):
            return False
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return self.high is None or (value < self.high if self.high_open else value <= self.high)


def _fmt(bound: float) -> str:
    return str(bound) if isinstance(bound, int) else f"{bound:g}"


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _int(low: int | None = None, **kw: Any) -> Setting:
    return Setting("int", low, **kw)


def _num(low: float | None = None, high: float | None = None, **kw: Any) -> Setting:
    return Setting("float", low, high, **kw)


_UNIT = _num(0, 1, low_open=True)  # (0, 1]
_FRACTION = _num(0, 1, low_open=True, high_open=True)  # (0, 1)
_OPTIONAL = {"required": False}

#: Every setting of the ``train`` config (flattened keys), with its type and range. A key of
#: the composed config that is not here is refused as unknown (a typo such as
#: ``planer.horizon`` would otherwise be ignored). The entries under ``reward.kwargs`` are
#: checked against the reward's constructor; ``experiment`` (a preset's name and budgets) is
#: free-form: its values reach the trainer only through the settings below.
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
    "budget.name": Setting("str", **_OPTIONAL),
    "logger.backend": Setting("choice", choices=LOGGERS),
    "env.id": Setting("str"),
    "env.num_envs": _int(1),
    "env.device": Setting("str"),
    "reward.name": Setting("choice", choices=tuple(sorted(REWARDS))),
    "reward.kwargs": Setting("dict", nullable=True, **_OPTIONAL),
    "world_model.hidden_sizes": Setting("sizes"),
    "world_model.lr": _num(0, low_open=True),
    "world_model.batch_size": _int(1),
    "world_model.max_epochs": _int(1),
    "world_model.val_fraction": _FRACTION,
    "world_model.patience": _int(1),
    "world_model.random_steps": _int(1),
    "world_model.refit_every": _int(1),
    "world_model.multi_step": _int(1, **_OPTIONAL),
    "world_model.multi_step_weight": _num(0, **_OPTIONAL),
    "world_model.early_stopping": Setting("choice", choices=EARLY_STOPPING, **_OPTIONAL),
    "world_model.ensemble_size": _int(1, **_OPTIONAL),
    "world_model.probabilistic": Setting("bool", **_OPTIONAL),
    "world_model.adaptive_horizon": Setting("bool", **_OPTIONAL),
    "world_model.save_fits": Setting("bool", **_OPTIONAL),
    "world_model.disagreement_quantile": Setting(
        "float", 0, 1, low_open=True, high_open=True, required=False
    ),
    "planner.num_candidates": _int(1),
    "planner.horizon": _int(1),
    "planner.discount": _UNIT,
    "planner.terminal_value": Setting("bool", **_OPTIONAL),
    "planner.refinement": Setting("choice", choices=REFINEMENTS, **_OPTIONAL),
    "planner.iterations": _int(1, **_OPTIONAL),
    "planner.num_elites": _int(1, **_OPTIONAL),
    "planner.policy_fraction": Setting("float", 0, 1, high_open=True, required=False),
    "planner.temperature": _num(0, low_open=True, **_OPTIONAL),
    "planner.min_std": _num(0, **_OPTIONAL),
    "ppo.frames_per_batch": _int(1),
    "ppo.minibatch_size": _int(1),
    "ppo.epochs": _int(1),
    "ppo.clip_epsilon": _UNIT,
    "ppo.entropy_coeff": _num(0),
    "ppo.critic_coeff": _num(0),
    "ppo.gamma": _UNIT,
    "ppo.lmbda": _num(0, 1),
    "ppo.lr": _num(0, low_open=True),
    "ppo.max_grad_norm": _num(0, low_open=True),
    "ppo.hidden_sizes": Setting("sizes"),
    "ppo.distribution": Setting("choice", choices=DISTRIBUTIONS),
    "ppo.init_log_std": _num(),
    "sac.frames_per_batch": _int(1),
    "sac.utd_ratio": _num(0, low_open=True),
    "sac.batch_size": _int(1),
    "sac.init_random_frames": _int(0),
    "sac.replay_size": _int(1),
    "sac.hidden_sizes": Setting("sizes"),
    "sac.lr": _num(0, low_open=True),
    "sac.gamma": _UNIT,
    "sac.tau": _UNIT,
    "sac.alpha_init": _num(0, low_open=True),
    "sac.update": Setting("choice", choices=SAC_UPDATES, **_OPTIONAL),
    "ppo.update": Setting("choice", choices=PPO_UPDATES, **_OPTIONAL),
    "collector": Setting("choice", choices=COLLECTORS, **_OPTIONAL),
    "device": Setting("str", **_OPTIONAL),
    "sac.refit_every_steps": _int(1),
}
#: Subtrees whose keys are not fixed (see :data:`TRAIN_SETTINGS`).
FREE_FORM: tuple[str, ...] = ("experiment",)
#: Top-level nodes that are not train settings: Hydra's own (present when a config is composed
#: with ``return_hydra_config=True``); they are neither checked nor compared on resume.
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

    Hydra's own node (``hydra``, see :data:`NOT_SETTINGS`) is left out of a ``DictConfig``.

    Args:
        cfg: a ``DictConfig`` or a nested mapping.
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
    flat: dict[str, Any] = {}
    for key, value in cfg.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            flat.update(flatten_config(value, prefix=f"{name}."))
        else:
            flat[name] = value
    return flat


def _check_settings(cfg: Any) -> None:
    """Unknown keys, missing keys, types and ranges of every setting (see TRAIN_SETTINGS)."""
    tree = _resolved(cfg)
    kwargs_node = tree.get("reward", {}).get("kwargs")
    flat = flatten_config({k: v for k, v in tree.items() if k not in FREE_FORM})
    flat = {k: v for k, v in flat.items() if not k.startswith("reward.kwargs.")}
    if "reward" in tree and "kwargs" in tree["reward"]:
        flat["reward.kwargs"] = kwargs_node
    for key in flat:
        if key not in TRAIN_SETTINGS:
            close = difflib.get_close_matches(key, list(TRAIN_SETTINGS), n=1, cutoff=0.6)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ConfigError(
                f"{key} is not a setting of the train config{hint} (a typo, or a key added "
                "with + that nothing reads)"
            )
    for key, setting in TRAIN_SETTINGS.items():
        if key not in flat:
            if setting.required:
                raise ConfigError(f"{key} is missing from the train config")
            continue
        if setting.kind == "dict":
            continue
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


def validate_train_config(cfg: Any) -> None:
    """Checks a composed ``train`` config before anything is built.

    Every key must be a setting of :data:`TRAIN_SETTINGS` (unknown keys are refused, naming
    the key and the setting probably meant), of its type and inside its range; the reward's
    keyword arguments must be accepted by its constructor; then the settings are checked
    against each other (batch sizes, budgets, planner variants).

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
    if "reward" in cfg and cfg["reward"]["name"] not in REWARDS:
        raise ConfigError(
            f"reward.name={cfg['reward']['name']!r} is not a reward; allowed: {sorted(REWARDS)}"
        )
    _check_settings(cfg)
    try:
        resolve_device(cfg.get("device", "cpu"))
    except DeviceError as err:
        raise ConfigError(str(err)) from err
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
    if not 0 < cfg["planner"]["discount"] <= 1:
        raise ConfigError(f"planner.discount must be in (0, 1], got {cfg['planner']['discount']}")
    _check_planner_variants(cfg, method)
    _check_world_model_variants(cfg, method)
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


def _check_planner_variants(cfg: Any, method: str) -> None:
    planner = cfg["planner"]
    value = planner.get("terminal_value", False)
    if not isinstance(value, bool):
        raise ConfigError(f"planner.terminal_value must be true or false, got {value!r}")
    refinement = planner.get("refinement")
    if refinement not in REFINEMENTS:
        raise ConfigError(
            f"planner.refinement={refinement!r} is not supported; allowed: {list(REFINEMENTS)}"
        )
    if refinement is None:
        return
    if method not in ("ppo_mpc", "sac_mpc"):
        raise ConfigError(
            f"planner.refinement={refinement!r} refines around the policy prior; it needs "
            f"method ppo_mpc or sac_mpc, got method={method!r}"
        )
    elites, m = planner["num_elites"], planner["num_candidates"]
    if not isinstance(elites, int) or not 1 <= elites <= m:
        raise ConfigError(
            f"planner.num_elites must be an integer in [1, planner.num_candidates={m}], "
            f"got {elites!r}"
        )
    if not 0 <= planner["policy_fraction"] < 1:
        raise ConfigError(
            f"planner.policy_fraction must be in [0, 1), got {planner['policy_fraction']!r}"
        )
    if planner["temperature"] <= 0:
        raise ConfigError(f"planner.temperature must be > 0, got {planner['temperature']!r}")
    if planner["min_std"] < 0:
        raise ConfigError(f"planner.min_std must be >= 0, got {planner['min_std']!r}")


def _check_world_model_variants(cfg: Any, method: str) -> None:
    from torchrl_mbmf.trainers.dynamics import fit_dynamics_kwargs

    wm = cfg["world_model"]
    try:
        kwargs = fit_dynamics_kwargs(wm)
    except (TypeError, ValueError) as err:
        raise ConfigError(str(err)) from err
    members = wm.get("ensemble_size", 1)
    if isinstance(members, bool) or not isinstance(members, int) or members < 1:
        raise ConfigError(f"world_model.ensemble_size must be an integer >= 1, got {members!r}")
    adaptive = wm.get("adaptive_horizon", False)
    if not isinstance(adaptive, bool):
        raise ConfigError(f"world_model.adaptive_horizon must be true or false, got {adaptive!r}")
    if members > 1 and method not in ("ppo_mpc", "sac_mpc"):
        raise ConfigError(
            f"world_model.ensemble_size={members} plans with the ensemble policy-guided planner; "
            f"it needs method ppo_mpc or sac_mpc, got method={method!r}"
        )
    if members > 1 and cfg["planner"].get("refinement"):
        raise ConfigError(
            "planner.refinement is not supported with world_model.ensemble_size > 1; set one "
            "of them back (planner.refinement=null or world_model.ensemble_size=1)"
        )
    if members > 1 and kwargs["multi_step"] > 1:
        raise ConfigError(
            "world_model.multi_step > 1 is implemented for the single model only; set "
            "world_model.ensemble_size=1 or world_model.multi_step=1"
        )
    if adaptive and members < 2:
        raise ConfigError(
            "world_model.adaptive_horizon needs an ensemble (world_model.ensemble_size >= 2), "
            f"got ensemble_size={members}"
        )
    if adaptive and not 0 < wm.get("disagreement_quantile", 0.9) < 1:
        raise ConfigError(
            "world_model.disagreement_quantile must be in (0, 1), got "
            f"{wm.get('disagreement_quantile')!r}"
        )


#: Settings a resumed run may change: they do not change what is trained (the budget, the
#: progress bar, torch threads, evaluation and checkpoint retention, folder names). Every other
#: setting is refused on resume, since the checkpoint's weights, optimisers and data were made
#: with the old value. Not here on purpose: ``checkpoint.every_steps`` (each checkpoint ends the
#: episode in progress, so moving them changes the data) and ``logger.backend`` (the logs would
#: be split across backends). Entries ending in ``.`` are prefixes.
RESUME_SAFE_SETTINGS: tuple[str, ...] = (
    "total_steps",
    "progress",
    "threads",
    "eval_every",
    "eval_episodes",
    "checkpoint.keep_last",
    "world_model.save_fits",
    "run_dir",
    "run_name",
    "budget.name",
    "experiment.",
)


def resume_changes(
    saved: Mapping[str, Any], now: Mapping[str, Any]
) -> tuple[dict[str, tuple[Any, Any]], dict[str, tuple[Any, Any]]]:
    """Splits the differences of two flattened configs into refused and allowed changes.

    Args:
        saved: the flattened config the checkpoint was written with.
        now: the flattened config of the resuming run.

    Returns:
        ``(refused, allowed)``, each ``{key: (saved value, new value)}``; a key missing on one
        side has the value ``"<missing>"`` there. ``allowed`` holds the keys of
        :data:`RESUME_SAFE_SETTINGS`.

    Examples:
        >>> from torchrl_mbmf.trainers.config import resume_changes
        >>> resume_changes({"ppo.lr": 3e-4, "total_steps": 400},
        ...                {"ppo.lr": 0.01, "total_steps": 800})
        ({'ppo.lr': (0.0003, 0.01)}, {'total_steps': (400, 800)})
    """
    missing = "<missing>"
    refused: dict[str, tuple[Any, Any]] = {}
    allowed: dict[str, tuple[Any, Any]] = {}
    for key in sorted(set(saved) | set(now)):
        old, new = saved.get(key, missing), now.get(key, missing)
        if _same(old, new):
            continue
        safe = any(
            key == s or (s.endswith(".") and key.startswith(s)) for s in RESUME_SAFE_SETTINGS
        )
        (allowed if safe else refused)[key] = (old, new)
    return refused, allowed


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    return a == b
