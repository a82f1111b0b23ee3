"""Config groups as components: ``_target_`` + :func:`hydra.utils.instantiate`.

Each component group of the train config names its builder in ``_target_``: ``ppo`` and
``sac`` the agents (:class:`~torchrl_mbmf.trainers.agents.PPOAgent`,
:class:`~torchrl_mbmf.trainers.agents.SACAgent`: networks, loss, optimiser), ``world_model``
the model-based part (:class:`~torchrl_mbmf.trainers.planning.WorldModelPart`: the network,
its fit and refit schedule), ``planner`` :func:`~torchrl_mbmf.trainers.planning.make_planner`
and ``logger`` :func:`~torchrl_mbmf.trainers.build.make_logger`. A builder's keyword-only
parameters are exactly its group's keys (their names are the config's); its other parameters
are the runtime objects the trainer passes (env, device, actor). A builder forwards each key
to the constructor it belongs to (``world_model.hidden_sizes`` to the network,
``world_model.lr`` to the fit), and the constructors check their own arguments, naming them;
:func:`instantiate_group` prefixes the group, so the error names the key a user typed
(``planner.horizon must be an integer >= 1, got 0``). The builders' signatures are also the
schema of the group's key names (:func:`group_keys`): an unknown key is refused before
anything is built. :class:`Setting` is the check the constructors share.
"""

from __future__ import annotations

import inspect
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from hydra.errors import InstantiationException
from hydra.utils import get_object, instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf

from torchrl_mbmf.checks import ConfigError
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
    "settings",
]


@dataclass(frozen=True)
class Setting:
    """The type and range of one argument (or config setting).

    Args:
        kind: ``"int"``, ``"float"``, ``"bool"``, ``"str"``, ``"choice"``, ``"dict"`` (not
            checked here) or ``"sizes"`` (a list of integers >= 1, possibly empty).
        low: smallest allowed value, or ``None``. Defaults to ``None``.
        high: largest allowed value, or ``None``. Defaults to ``None``.
        low_open: ``low`` itself is excluded. Defaults to ``False``.
        high_open: ``high`` itself is excluded. Defaults to ``False``.
        choices: the allowed values of a ``"choice"``. Defaults to none.
        nullable: ``null`` is allowed too. Defaults to ``False``.
        required: the key must be present (the trainer reads it without a default).
            Defaults to ``True``.

    Examples:
        >>> from torchrl_mbmf.trainers.components import Setting
        >>> Setting("float", 0, 1, low_open=True).check("gamma", 0.99)
        >>> try:
        ...     Setting("float", 0, 1, low_open=True).check("gamma", 5)
        ... except ValueError as err:
        ...     print(err)
        gamma must be a number in (0, 1], got 5
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
        if (value is None and self.nullable) or self.kind == "dict":
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


#: The named ranges of :func:`settings`.
KINDS: dict[str, Setting] = {
    "positive_int": Setting("int", 1),
    "count": Setting("int", 0),
    "positive": Setting("float", 0, low_open=True),
    "non_negative": Setting("float", 0),
    "unit": Setting("float", 0, 1, low_open=True),
    "probability": Setting("float", 0, 1),
    "fraction": Setting("float", 0, 1, low_open=True, high_open=True),
    "finite": Setting("float"),
    "sizes": Setting("sizes"),
    "flag": Setting("bool"),
}


def settings(**kinds: Sequence[str]) -> dict[str, Setting]:
    """``{argument: Setting}`` from argument names grouped by their :data:`KINDS` entry.

    Args:
        **kinds: for each kind (``positive_int``, ``count``, ``positive``, ``non_negative``,
            ``unit`` (0, 1], ``probability`` [0, 1], ``fraction`` (0, 1), ``finite``,
            ``sizes``, ``flag``), the names of the arguments of that kind.

    Examples:
        >>> from torchrl_mbmf.trainers.components import settings
        >>> settings(unit=("gamma",))["gamma"].describe()
        'a number in (0, 1]'
    """
    return {name: KINDS[kind] for kind, names in kinds.items() for name in names}


def choice(*choices: Any) -> Setting:
    """The setting whose value must be one of ``choices``.

    Args:
        choices: the allowed values.

    Examples:
        >>> from torchrl_mbmf.trainers.components import choice
        >>> choice("fused", "stock").check("update", "stock")
    """
    return Setting("choice", choices=tuple(choices))


def check_arguments(specs: Mapping[str, Setting], values: Mapping[str, Any]) -> None:
    """Checks each argument of ``specs`` present in ``values`` (a constructor's ``locals()``).

    Args:
        specs: ``{argument: Setting}``.
        values: the arguments' values.

    Raises:
        ConfigError: naming the first argument that does not fit, its value and what was
            expected.

    Examples:
        >>> from torchrl_mbmf.trainers.components import Setting, check_arguments
        >>> try:
        ...     check_arguments({"epochs": Setting("int", 1)}, {"epochs": True})
        ... except ValueError as err:
        ...     print(err)
        epochs must be an integer >= 1, got True
    """
    for name, setting in specs.items():
        if name in values:
            setting.check(name, values[name])


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

    The group's keys become the builder's keyword arguments, ``runtime`` its other ones
    (objects: the same instances reach the builder). A group without ``_target_`` is built
    with the group's :data:`DEFAULT_TARGETS` entry.

    Args:
        cfg: the training config.
        group: the group's name.

    Keyword Args:
        **runtime: the builder's runtime arguments.

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
            raise ConfigError(_qualified(group, keys, str(cause))) from cause
        raise
