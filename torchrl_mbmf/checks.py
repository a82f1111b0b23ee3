"""Checks of numeric settings, shared by the modules, the losses and the fitters."""

from __future__ import annotations

import math
from typing import Any

__all__ = ["ConfigError", "check_multi_step", "check_multi_step_weight", "check_number"]


class ConfigError(ValueError):
    """A training config value is invalid; the message names the key and the allowed values."""


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
    kind = int if integer else int | float
    ok = not isinstance(value, bool) and isinstance(value, kind)
    if not ok or not math.isfinite(value) or value < minimum:
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


__all__ = ["check_multi_step", "check_multi_step_weight", "check_number"]
