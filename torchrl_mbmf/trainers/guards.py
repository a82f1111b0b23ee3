"""Run-time guards of the training loop: a diverged run stops, naming the step and quantity."""

from __future__ import annotations

import math
from collections.abc import Mapping


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
        >>> from torchrl_mbmf.trainers.guards import TrainingDivergedError, check_finite
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
