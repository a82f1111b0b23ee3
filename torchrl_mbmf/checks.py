"""The one validation system: :class:`Setting` (a value's type and range) and its helpers.

The modules, the losses, the fitters, the config and the recipes check values here (numbers,
input files, output paths); an error names the key, what was expected and the value.
"""

from __future__ import annotations

import difflib
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import ListConfig

__all__ = [
    "KINDS",
    "ConfigError",
    "Setting",
    "TrainingDivergedError",
    "check_arguments",
    "check_finite",
    "check_input_file",
    "check_multi_step",
    "check_multi_step_weight",
    "check_no_added_keys",
    "check_number",
    "check_output_path",
    "check_recipe_overrides",
    "choice",
    "settings",
]


class ConfigError(ValueError):
    """A training config value is invalid; the message names the key and the allowed values."""


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
        >>> from torchrl_mbmf.checks import Setting
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
        if not self.fits(value):
            raise ConfigError(f"{key} must be {self.describe()}, got {value!r}")

    def fits(self, value: Any) -> bool:
        """Whether ``value`` has this type and lies in this range (``null`` not included).

        Args:
            value: the value.
        """
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
        >>> from torchrl_mbmf.checks import settings
        >>> settings(unit=("gamma",))["gamma"].describe()
        'a number in (0, 1]'
    """
    return {name: KINDS[kind] for kind, names in kinds.items() for name in names}


def choice(*choices: Any) -> Setting:
    """The setting whose value must be one of ``choices``.

    Args:
        choices: the allowed values.

    Examples:
        >>> from torchrl_mbmf.checks import choice
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
        >>> from torchrl_mbmf.checks import Setting, check_arguments
        >>> try:
        ...     check_arguments({"epochs": Setting("int", 1)}, {"epochs": True})
        ... except ValueError as err:
        ...     print(err)
        epochs must be an integer >= 1, got True
    """
    for name, setting in specs.items():
        if name in values:
            setting.check(name, values[name])


def check_number(
    value: Any, key: str, *, minimum: float, integer: bool = False, note: str = ""
) -> Any:
    """Checks a numeric setting: a finite number (or an integer) ``>= minimum``; not a bool.

    Args:
        value: the value.
        key: its name in the error message.

    Keyword Args:
        minimum: the smallest allowed value.
        integer: the value must be an ``int``. Defaults to ``False`` (an int or a float).
        note: said after the bound in the error message. Defaults to ``""``.

    Returns:
        ``value`` as an ``int`` (``integer=True``) or a ``float``.

    Raises:
        ValueError: naming ``key``, the bound and the value.

    Examples:
        >>> from torchrl_mbmf.checks import check_number
        >>> check_number(3, "ensemble_size", minimum=1, integer=True)
        3
        >>> try:
        ...     check_number(float("nan"), "multi_step_weight", minimum=0)
        ... except ValueError as err:
        ...     print(err)
        multi_step_weight must be a finite number >= 0, got nan
    """
    if not Setting("int" if integer else "float", minimum).fits(value):
        what = "an integer" if integer else "a finite number"
        bound = int(minimum) if float(minimum).is_integer() else minimum
        raise ValueError(f"{key} must be {what} >= {bound}{note}, got {value!r}")
    return int(value) if integer else float(value)


def check_multi_step(multi_step: int, *, key: str = "multi_step") -> int:
    """Validates a multi-step horizon ``k`` (an integer ``>= 1``; ``1`` turns the term off).

    Args:
        multi_step: the value.

    Keyword Args:
        key: the name used in the error message. Defaults to ``"multi_step"``.

    Raises:
        ValueError: naming ``key`` if the value is not an integer ``>= 1``.

    Examples:
        >>> from torchrl_mbmf.checks import check_multi_step
        >>> try:
        ...     check_multi_step(0, key="world_model.multi_step")
        ... except ValueError as err:
        ...     print(err)
        world_model.multi_step must be an integer >= 1 (1 = one-step loss only), got 0
    """
    return check_number(multi_step, key, minimum=1, integer=True, note=" (1 = one-step loss only)")


def check_multi_step_weight(weight: float, *, key: str = "multi_step_weight") -> float:
    """Validates the weight of the multi-step term: :func:`check_number` with ``minimum=0``.

    Args:
        weight: the value (a ``ValueError`` naming ``key`` if it is negative, not finite or
            not a number).
        key: the name used in the error message. Defaults to ``"multi_step_weight"``.

    Examples:
        >>> from torchrl_mbmf.checks import check_multi_step_weight
        >>> check_multi_step_weight(1)
        1.0
    """
    return check_number(weight, key, minimum=0)


def check_input_file(path: str | os.PathLike, key: str) -> Path:
    """Checks that a setting names an existing, readable file.

    Args:
        path: the value.
        key: its name in the error message.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        FileNotFoundError: naming ``key`` and the path when it is missing or not a file.

    Examples:
        >>> from torchrl_mbmf.checks import check_input_file
        >>> try:
        ...     check_input_file("no/such/notes.md", "notes")
        ... except FileNotFoundError as err:
        ...     print(err)
        notes='no/such/notes.md' is not a file (expected an existing file; null to leave it out)
    """
    file = Path(path)
    if not file.is_file() or not os.access(file, os.R_OK):
        what = "is not readable" if file.is_file() else "is not a file"
        raise FileNotFoundError(
            f"{key}={str(path)!r} {what} (expected an existing file; null to leave it out)"
        )
    return file


def check_output_path(path: str | os.PathLike, key: str, *, folder: bool) -> Path:
    """Checks, before any work, that an output file or folder can be written.

    The path's nearest existing ancestor must be a writable folder; a folder output must not be
    an existing file, and a file output must not be an existing folder.

    Args:
        path: the value.
        key: its name in the error message.

    Keyword Args:
        folder: whether the output is a folder (else a file).

    Returns:
        ``path`` as a :class:`~pathlib.Path` (nothing is created).

    Raises:
        ValueError: naming ``key`` and the path when it cannot be written there.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from torchrl_mbmf.checks import check_output_path
        >>> with tempfile.NamedTemporaryFile() as f:
        ...     try:
        ...         check_output_path(f.name, "out_dir", folder=True)
        ...     except ValueError as err:
        ...         print(str(err).split(": ")[1])
        an existing file, expected a folder
    """
    out = Path(path)
    if folder and out.is_file():
        raise ValueError(f"{key}={str(path)!r}: an existing file, expected a folder")
    if not folder and out.is_dir():
        raise ValueError(f"{key}={str(path)!r}: an existing folder, expected a file")
    ancestor = out if out.is_dir() else out.parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir() or not os.access(ancestor, os.W_OK | os.X_OK):
        raise ValueError(
            f"{key}={str(path)!r} cannot be written: {str(ancestor)!r} is not a writable folder"
        )
    return out


def _leaf_keys(cfg: Mapping[str, Any], prefix: str = "") -> list[str]:
    keys = []
    for key, value in cfg.items():
        name = f"{prefix}{key}"
        keys.append(name)
        if isinstance(value, Mapping):
            keys += _leaf_keys(value, prefix=f"{name}.")
    return keys


def check_no_added_keys(
    overrides: Sequence[str], known: Mapping[str, Any], *, groups: Sequence[str] = ()
) -> None:
    """Refuses command-line overrides that add a setting the recipe does not have (``+key=...``).

    Hydra refuses ``key=value`` for a key its config lacks, but ``+key=value`` adds it, and a
    recipe would then ignore it silently (a typo such as ``+world_model.hiden_sizes=[8]``).

    Args:
        overrides: the command-line overrides (Hydra's ``HydraConfig.get().overrides.task``).
        known: the recipe's composed config as plain containers (its keys are the settings).

    Keyword Args:
        groups: config groups that may be added with ``+group=option``. Defaults to none.

    Raises:
        ValueError: naming the added key and the closest known setting.

    Examples:
        >>> from torchrl_mbmf.checks import check_no_added_keys
        >>> known = {"eval_starts": 2000, "world_model": {"hidden_sizes": [500, 500]}}
        >>> try:
        ...     check_no_added_keys(["+world_model.hiden_sizes=[8]"], known)
        ... except ValueError as err:
        ...     print(str(err).split("; ")[1])
        did you mean 'world_model.hidden_sizes'?
    """
    names = _leaf_keys(known)
    for override in overrides:
        if not override.startswith("+") or override.startswith("++"):
            continue
        key = override[1:].split("=", 1)[0].strip()
        if key in groups:
            continue
        # The composed config holds the added key; a key is known if it is not only there.
        others = [n for n in names if n != key and not n.startswith(f"{key}.")]
        close = difflib.get_close_matches(key, others, n=1, cutoff=0.6)
        hint = f"did you mean {close[0]!r}?" if close else f"known: {sorted(others)[:20]}"
        raise ValueError(f"unknown setting {key!r} (added with +); {hint}")


def check_recipe_overrides(cfg: Any) -> None:
    """In a ``@hydra.main`` recipe: refuses ``+key=...`` overrides of unknown settings.

    :func:`check_no_added_keys` over the running job's command-line overrides.

    Args:
        cfg: the recipe's config (a ``DictConfig``).

    Examples:
        >>> from torchrl_mbmf.checks import check_recipe_overrides
        >>> check_recipe_overrides  # doctest: +ELLIPSIS
        <function check_recipe_overrides at ...>
    """
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    known = OmegaConf.to_container(cfg, resolve=False)
    check_no_added_keys(list(HydraConfig.get().overrides.task), known)  # type: ignore[arg-type]


class TrainingDivergedError(RuntimeError):
    """A logged loss, return or statistic became NaN or infinite; the message names it."""


def check_finite(metrics: Mapping[str, float], step: int) -> None:
    """Raises if any scalar is NaN or infinite (one ``math.isfinite`` per scalar: cheap).

    Args:
        metrics: name -> value, as logged.
        step: the real-step count the values belong to (named in the message).

    Raises:
        TrainingDivergedError: naming the first non-finite quantity, its value and the step.

    Examples:
        >>> from torchrl_mbmf.checks import TrainingDivergedError, check_finite
        >>> check_finite({"loss/loss_objective": 0.1}, step=2048)
        >>> try:
        ...     check_finite({"loss/loss_critic": float("nan")}, step=4096)
        ... except TrainingDivergedError as err:
        ...     print(err)
        loss/loss_critic=nan at real step 4096: the run diverged (not logged, not checkpointed)
    """
    for name, value in metrics.items():
        if not math.isfinite(value):
            raise TrainingDivergedError(
                f"{name}={value} at real step {step}: the run diverged (not logged, not "
                "checkpointed)"
            )
