"""Config groups as components: ``_target_`` + :func:`hydra.utils.instantiate`.

A builder's keyword-only parameters are its group's keys; the design:
``docs/design/config.md``.
"""

from __future__ import annotations

import inspect
import re
from collections.abc import Callable, Sequence
from typing import Any

from hydra.errors import InstantiationException
from hydra.utils import get_object, instantiate
from omegaconf import DictConfig, OmegaConf

from torchrl_mbmf.checks import (
    ConfigError,
    Setting,
    check_arguments,
    choice,
    settings,
)
from torchrl_mbmf.runs.resume import DEFAULT_TARGETS

__all__ = [
    "DEFAULT_TARGETS",
    "ConfigError",
    "Setting",
    "check_arguments",
    "choice",
    "group_keys",
    "group_target",
    "instantiate_group",
    "qualified_error",
    "settings",
]


def group_target(cfg: Any, group: str) -> Callable[..., Any]:
    """The builder a group's ``_target_`` names (:data:`DEFAULT_TARGETS` without one).

    Args:
        cfg: the training config.
        group: the group's name (``"planner"``).

    Examples:
        >>> from torchrl_mbmf.trainers.components import group_target
        >>> group_target({"planner": {"horizon": 3}}, "planner").__name__
        'make_planner'
    """
    node = cfg[group]
    path = node.get("_target_") or DEFAULT_TARGETS[group]
    try:
        return get_object(str(path))
    except (ImportError, AttributeError, ValueError) as err:
        raise ConfigError(f"{group}._target_={path!r} cannot be imported: {err}") from err


def group_keys(target: Callable[..., Any]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``(keys, required keys)`` of a builder's group: its keyword-only parameters.

    Args:
        target: a group's builder (see :func:`group_target`).

    Examples:
        >>> from torchrl_mbmf.trainers.components import group_keys
        >>> from torchrl_mbmf.trainers.build import make_logger
        >>> group_keys(make_logger)
        (('backend',), ('backend',))
    """
    params = inspect.signature(target).parameters.values()
    keys = [p for p in params if p.kind is inspect.Parameter.KEYWORD_ONLY]
    return (
        tuple(p.name for p in keys),
        tuple(p.name for p in keys if p.default is inspect.Parameter.empty),
    )


def _other_groups(group: str) -> tuple[str, ...]:
    """The key prefixes of the groups other than ``group`` (``"planner."``, ...)."""
    return tuple(f"{g}." for g in DEFAULT_TARGETS if g != group)


def _qualified(group: str, keys: Sequence[str], message: str) -> str:
    """``message`` with the group prefixed to the argument it starts with (else ``group: ``)."""
    if message.startswith(f"{group}."):
        return message
    for key in sorted(keys, key=len, reverse=True):
        if re.match(rf"{re.escape(key)}\b(?!_)", message):
            return f"{group}.{message}"
    return f"{group}: {message}"


def instantiate_group(cfg: Any, group: str, **runtime: Any) -> Any:
    """Builds the component of config group ``group`` with :func:`hydra.utils.instantiate`.

    Args:
        cfg: the training config (a group without ``_target_`` is built with its
            :data:`DEFAULT_TARGETS` entry).
        group: the group's name (its keys become the builder's keyword arguments).

    Keyword Args:
        **runtime: the builder's other arguments (the same objects reach the builder).

    Raises:
        ConfigError: the builder or a constructor refused an argument; the message names the
            config key (``planner.horizon must be ...``).

    Examples:
        >>> from omegaconf import OmegaConf
        >>> from torchrl_mbmf.trainers.components import ConfigError, instantiate_group
        >>> cfg = OmegaConf.create({"logger": {"backend": "foo"}})
        >>> try:
        ...     instantiate_group(cfg, "logger", run_dir="out")
        ... except ConfigError as err:
        ...     print(str(err).split(";")[0])
        logger.backend='foo' is not supported
    """
    node = cfg[group]
    node = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node
    node = {"_target_": DEFAULT_TARGETS[group], **dict(node)}
    keys, _ = group_keys(group_target({group: node}, group))
    try:
        return instantiate(node, **runtime, _convert_="all")
    except InstantiationException as err:
        cause = err.__cause__
        if isinstance(cause, TypeError | ValueError):
            error = qualified_error(group, keys, cause)
            raise error from (None if error is cause else cause)
        raise


def qualified_error(group: str, keys: Sequence[str], err: TypeError | ValueError) -> ConfigError:
    """The :class:`ConfigError` of a group builder's error, naming the config key.

    Args:
        group: the group whose builder raised.
        keys: the builder's keys.
        err: the builder's error (kept as it is if it names another group's key).

    Examples:
        >>> from torchrl_mbmf.trainers.components import qualified_error
        >>> str(qualified_error("planner", ["horizon"], ValueError("horizon must be >= 1")))
        'planner.horizon must be >= 1'
        >>> str(qualified_error("world_model", ["lr"], ConfigError("planner.horizon bad")))
        'planner.horizon bad'
    """
    if isinstance(err, ConfigError) and str(err).startswith(_other_groups(group)):
        return err
    return ConfigError(_qualified(group, keys, str(err)))
