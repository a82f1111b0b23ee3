"""What a resume may change: the resume-safe settings, the config comparison, the fingerprint.

:class:`~torchrl_mbmf.runs.checkpoint.RunCheckpoint` resumes a run; here are the rules it
applies. :data:`RESUME_SAFE_SETTINGS` are the settings a resumed run may change,
:func:`resume_changes` splits two configs' differences into refused and allowed ones,
:func:`fingerprint` is the older record of settings a checkpoint must agree on, and
:data:`DEFAULT_TARGETS` what a config written before the groups named their builders means.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from typing import Any

from omegaconf import OmegaConf

from torchrl_mbmf.checks import ConfigError
from torchrl_mbmf.methods import METHODS, MODEL_BASED, PPO_METHODS

__all__ = [
    "DEFAULT_TARGETS",
    "IMPLIED_DEFAULTS",
    "OPTIONAL_GROUPS",
    "RESUME_SAFE_SETTINGS",
    "check_resume_budget",
    "describe_refused",
    "fingerprint",
    "flatten_settings",
    "resume_changes",
]

logger = logging.getLogger(__name__)

#: The builder of each component group, used for a config that has no ``_target_`` (a run
#: folder's ``config.yaml`` written before the groups named their builders): such a config
#: means exactly these.
DEFAULT_TARGETS: dict[str, str] = {
    "ppo": "torchrl_mbmf.trainers.agents.PPOAgent",
    "sac": "torchrl_mbmf.trainers.agents.SACAgent",
    "world_model": "torchrl_mbmf.trainers.planning.WorldModelPart",
    "planner": "torchrl_mbmf.trainers.planning.make_planner",
    "logger": "torchrl_mbmf.trainers.build.make_logger",
    "mbpo": "torchrl_mbmf.world_model.branched_rollouts.BranchedRollouts",
}

#: Groups that configs written before them lack (what only their method reads).
OPTIONAL_GROUPS: dict[str, str] = {"mbpo": "sac_mbpo"}

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
    "restart",
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
        side has the value ``"<missing>"`` there, except a group's ``_target_``, which a
        config without one means to be the group's default builder
        (:data:`DEFAULT_TARGETS`). ``allowed`` holds the keys of
        :data:`RESUME_SAFE_SETTINGS`. The group of the policy family a run's method does not
        train (``sac`` for the PPO methods, ``ppo`` for the SAC ones) is built by nothing, so
        its settings are no change.

    Examples:
        >>> from torchrl_mbmf.runs.resume import resume_changes
        >>> resume_changes({"ppo.lr": 3e-4, "total_steps": 400},
        ...                {"ppo.lr": 0.01, "total_steps": 800})
        ({'ppo.lr': (0.0003, 0.01)}, {'total_steps': (400, 800)})
        >>> resume_changes({"method": "ppo", "sac.lr": 3e-4}, {"method": "ppo", "sac.lr": 0.01})
        ({}, {})
    """
    missing = "<missing>"
    refused: dict[str, tuple[Any, Any]] = {}
    allowed: dict[str, tuple[Any, Any]] = {}
    unused = _unused_group(saved.get("method"), now.get("method"))
    methods = {saved.get("method"), now.get("method")}
    skipped = tuple(f"{g}." for g, m in OPTIONAL_GROUPS.items() if m not in methods)
    for key in sorted(set(saved) | set(now)):
        if (unused is not None and key.startswith(unused)) or key.startswith(skipped):
            continue
        old, new = saved.get(key, _implied(key, missing)), now.get(key, _implied(key, missing))
        if _same(old, new) or (key in SAME_WHEN and SAME_WHEN[key](old) == SAME_WHEN[key](new)):
            continue
        safe = any(
            key == s or (s.endswith(".") and key.startswith(s)) for s in RESUME_SAFE_SETTINGS
        )
        (allowed if safe else refused)[key] = (old, new)
    return refused, allowed


def _device(value: Any) -> Any:
    """The device a ``device`` setting means on this machine (``auto`` and ``cuda`` resolved).

    The same rule as :func:`torchrl_mbmf.device.resolve_device`, without its checks
    (a device this machine lacks is refused when the run builds).
    """
    if value == "auto":
        import torch

        return "cuda:0" if torch.cuda.is_available() else "cpu"
    return "cuda:0" if value == "cuda" else value


#: Settings whose values are compared by what they mean here: ``device=auto`` resolving to the
#: device a run was written with is no change.
SAME_WHEN: dict[str, Callable[[Any], Any]] = {"device": _device}


def check_resume_budget(real_steps: int, config: Mapping[str, Any], checkpoint: Any) -> None:
    """Refuses a resume whose ``total_steps`` is below the steps its checkpoint has taken.

    A raised ``total_steps`` continues the run; one equal to the checkpoint's steps ends it at
    once (its summary is written); a lower one would end with more steps than asked, so it is
    refused.

    Args:
        real_steps: the checkpoint's real-step count.
        config: the resuming run's flattened config (``total_steps``).
        checkpoint: the checkpoint's folder (named in the error).

    Raises:
        ConfigError: naming ``total_steps``, the checkpoint and its steps.

    Examples:
        >>> from torchrl_mbmf.runs.resume import check_resume_budget
        >>> check_resume_budget(480, {"total_steps": 960}, "ckpt")
        >>> try:
        ...     check_resume_budget(480, {"total_steps": 320}, "ckpt")
        ... except ValueError as err:
        ...     print(str(err).split(";")[0])
        total_steps=320 is below the 480 real steps checkpoint ckpt has already taken
    """
    total = config.get("total_steps")
    if isinstance(total, int) and not isinstance(total, bool) and total < int(real_steps):
        raise ConfigError(
            f"total_steps={total} is below the {int(real_steps)} real steps checkpoint "
            f"{checkpoint} has already taken; resume with total_steps >= {int(real_steps)} "
            "(equal: the run ends at once) or use another run_dir"
        )


#: Settings added after runs were written, with the value a config without them means.
IMPLIED_DEFAULTS: dict[str, Any] = {
    "restart": False,
    "world_model.learn_termination": False,
    "sac.loss_function": "smooth_l1",
    "sac.scale": "biased_softplus",
}


def flatten_settings(cfg: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Flattens nested settings into ``{"a.b.c": value}``; lists and empty mappings are leaves.

    Args:
        cfg: nested plain mappings (a resolved config).
        prefix: prepended to every key. Defaults to ``""``.

    Examples:
        >>> from torchrl_mbmf.runs.resume import flatten_settings
        >>> flatten_settings({"ppo": {"lr": 3e-4, "hidden_sizes": [64, 64]}, "kw": {}})
        {'ppo.lr': 0.0003, 'ppo.hidden_sizes': [64, 64], 'kw': {}}
    """
    flat: dict[str, Any] = {}
    for key, value in cfg.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            flat.update(flatten_settings(value, prefix=f"{name}."))
        else:
            flat[name] = value
    return flat


def describe_refused(refused: Mapping[str, tuple[Any, Any]]) -> str:
    """One line per refused change: ``was written with key=old, this run has key=new``.

    Args:
        refused: ``{key: (saved value, new value)}`` (the first result of
            :func:`resume_changes`).

    Examples:
        >>> from torchrl_mbmf.runs.resume import describe_refused
        >>> print(describe_refused({"seed": (0, 1)}))
          was written with seed=0, this run has seed=1
    """
    return "\n".join(
        f"  was written with {key}={old!r}, this run has {key}={new!r}"
        for key, (old, new) in refused.items()
    )


def _unused_group(saved_method: Any, method: Any) -> str | None:
    """The key prefix of the policy group neither config's method trains (``None``: both)."""
    if saved_method != method or method not in METHODS:
        return None
    return "sac." if method in PPO_METHODS else "ppo."


def _implied(key: str, missing: str) -> Any:
    """The value a config without ``key`` means (``missing`` but for a group's ``_target_``).

    A config written before the groups named their builders means the default ones; one
    written before a setting of :data:`IMPLIED_DEFAULTS` existed means its default.
    """
    if key in IMPLIED_DEFAULTS:
        return IMPLIED_DEFAULTS[key]
    group, _, name = key.partition(".")
    return DEFAULT_TARGETS[group] if name == "_target_" and group in DEFAULT_TARGETS else missing


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    return a == b


def fingerprint(cfg: Any) -> dict[str, Any]:
    """Config entries a checkpoint must agree on to be resumed (kept for old checkpoints).

    Args:
        cfg: the training config.

    Examples:
        >>> from omegaconf import OmegaConf
        >>> cfg = OmegaConf.create({"method": "ppo", "env": {"id": "E", "num_envs": 1},
        ...     "reward": {"name": "default"}, "seed": 0,
        ...     "ppo": {"hidden_sizes": [8], "frames_per_batch": 64}})
        >>> fingerprint(cfg)["ppo.hidden_sizes"]
        [8]
    """
    algo = "ppo" if cfg.method in PPO_METHODS else "sac"
    out = {
        "method": cfg.method,
        "env.id": cfg.env.id,
        "env.num_envs": int(cfg.env.num_envs),
        "reward": OmegaConf.to_container(cfg.reward, resolve=True),
        "seed": int(cfg.seed),
        f"{algo}.hidden_sizes": list(cfg[algo].hidden_sizes),
        f"{algo}.frames_per_batch": int(cfg[algo].frames_per_batch),
    }
    if cfg.method in MODEL_BASED:
        out["world_model.hidden_sizes"] = list(cfg.world_model.hidden_sizes)
        out["world_model.random_steps"] = int(cfg.world_model.random_steps)
        for key in ("ensemble_size", "probabilistic", "multi_step", "multi_step_weight"):
            if key in cfg.world_model:
                out[f"world_model.{key}"] = cfg.world_model[key]
        planner = OmegaConf.to_container(cfg.planner, resolve=True)
        # the builder's name is no setting of the planner (fingerprints predate it)
        out["planner"] = {k: v for k, v in planner.items() if k != "_target_"}
    if cfg.method in ("mpc", "ppo_mpc"):
        out["planning_updates"] = int(cfg.planning_updates)
    return out
