"""Across-seed statistics and sample-efficiency measures for learning curves.

With three seeds a bare mean misleads; following Agarwal et al. (2021, "Deep RL at the edge of
the statistical precipice", the ``rliable`` recommendations) results are aggregated with the
interquartile mean and percentile-bootstrap confidence intervals.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats


def iqm(values: Sequence[float] | np.ndarray, axis: int = -1) -> np.ndarray | float:
    """Interquartile mean: the mean of the middle 50% of ``values`` (25% trimmed each side).

    Args:
        values: the samples.
        axis: axis to reduce. Defaults to ``-1``.

    Returns:
        The IQM (a float for 1-D input).

    Examples:
        >>> from torchrl_mbmf.analysis.stats import iqm
        >>> float(iqm([1.0, 2.0, 3.0, 100.0]))
        2.5
    """
    arr = np.asarray(values, dtype=np.float64)
    if arr.size == 0:
        raise ValueError("iqm of an empty sequence")
    return stats.trim_mean(arr, 0.25, axis=axis)


@dataclass
class Interval:
    """A point estimate with a confidence interval.

    Attributes:
        estimate: the statistic on the data.
        low: lower bound of the interval.
        high: upper bound of the interval.
        confidence: confidence level of the interval.
        n: number of samples.

    Examples:
        >>> from torchrl_mbmf.analysis.stats import Interval
        >>> str(Interval(1.0, 0.5, 1.5, 0.95, 3))
        '1 [0.5, 1.5]'
    """

    estimate: float
    low: float
    high: float
    confidence: float
    n: int

    def __str__(self) -> str:
        return f"{self.estimate:.4g} [{self.low:.4g}, {self.high:.4g}]"

    def overlaps(self, other: Interval) -> bool:
        """Whether the two intervals overlap."""
        return not (self.high < other.low or other.high < self.low)


def bootstrap_ci(
    values: Sequence[float] | np.ndarray,
    *,
    statistic: str = "iqm",
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> Interval:
    """Percentile-bootstrap confidence interval of a statistic over seeds.

    Uses :func:`scipy.stats.bootstrap` (percentile method, which is defined for the handful of
    seeds RL experiments have). With a single value the interval is that value.

    Args:
        values: one number per seed (for example the final return of each run).

    Keyword Args:
        statistic: ``"iqm"`` or ``"mean"``. Defaults to ``"iqm"``.
        confidence: confidence level. Defaults to ``0.95``.
        n_resamples: bootstrap resamples. Defaults to ``2000``.
        seed: seed of the resampling. Defaults to ``0``.

    Returns:
        An :class:`Interval`.

    Examples:
        >>> from torchrl_mbmf.analysis.stats import bootstrap_ci
        >>> ci = bootstrap_ci([1.0, 2.0, 3.0])
        >>> ci.low <= ci.estimate <= ci.high
        True
    """
    arr = np.asarray(values, dtype=np.float64).ravel()
    if arr.size == 0:
        raise ValueError("bootstrap_ci of an empty sequence")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    funcs = {"iqm": lambda x, axis: iqm(x, axis=axis), "mean": np.mean}
    if statistic not in funcs:
        raise ValueError(f"unknown statistic {statistic!r}; expected one of {sorted(funcs)}")
    func = funcs[statistic]
    estimate = float(func(arr, axis=-1))
    if arr.size == 1 or np.all(arr == arr[0]):
        return Interval(estimate, estimate, estimate, confidence, int(arr.size))
    res = stats.bootstrap(
        (arr,),
        func,
        confidence_level=confidence,
        n_resamples=n_resamples,
        method="percentile",
        vectorized=True,
        rng=np.random.default_rng(seed),
    )
    ci = res.confidence_interval
    return Interval(estimate, float(ci.low), float(ci.high), confidence, int(arr.size))


def iqm_ratio_ci(
    candidate: Sequence[float] | np.ndarray,
    reference: Sequence[float] | np.ndarray,
    *,
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> Interval:
    """Ratio of two configurations' IQMs with a percentile-bootstrap interval.

    Each resample draws the seeds of both configurations with replacement, independently, and
    takes the ratio of their IQMs ("the candidate reaches 1.15x the reference's return").

    Args:
        candidate: one number per seed of the configuration measured (the numerator).
        reference: one number per seed of the configuration it is measured against; its
            values must be positive (a ratio to a non-positive return means nothing).

    Keyword Args:
        confidence: confidence level. Defaults to ``0.95``.
        n_resamples: bootstrap resamples. Defaults to ``2000``.
        seed: seed of the resampling. Defaults to ``0``.

    Returns:
        An :class:`Interval` whose ``n`` is the candidate's seed count.

    Examples:
        >>> from torchrl_mbmf.analysis.stats import iqm_ratio_ci
        >>> ci = iqm_ratio_ci([6.0, 6.0, 6.0], [2.0, 3.0, 4.0])
        >>> round(ci.estimate, 3), ci.low <= 2.0 <= ci.high
        (2.0, True)
    """
    cand = np.asarray(candidate, dtype=np.float64).ravel()
    ref = np.asarray(reference, dtype=np.float64).ravel()
    if cand.size == 0 or ref.size == 0:
        raise ValueError(f"iqm_ratio_ci needs values on both sides, got {cand.size} and {ref.size}")
    if not np.all(ref > 0):
        raise ValueError(f"reference values must be positive for a ratio, got {ref.tolist()}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    rng = np.random.default_rng(seed)
    cand_iqm = iqm(cand[rng.integers(0, cand.size, (n_resamples, cand.size))], axis=-1)
    ref_iqm = iqm(ref[rng.integers(0, ref.size, (n_resamples, ref.size))], axis=-1)
    tail = (1 - confidence) / 2 * 100
    low, high = np.percentile(cand_iqm / ref_iqm, [tail, 100 - tail])
    estimate = float(iqm(cand)) / float(iqm(ref))
    return Interval(estimate, float(low), float(high), confidence, int(cand.size))


def interval_summary(values: Sequence[float]) -> dict[str, object] | None:
    """:func:`bootstrap_ci` of the IQM as a JSON-ready dict, with the values themselves.

    Args:
        values: one number per seed.

    Returns:
        ``{"iqm", "low", "high", "n", "values"}``, or ``None`` for no values.

    Examples:
        >>> from torchrl_mbmf.analysis.stats import interval_summary
        >>> interval_summary([2.0, 2.0])
        {'iqm': 2.0, 'low': 2.0, 'high': 2.0, 'n': 2, 'values': [2.0, 2.0]}
    """
    if not len(values):
        return None
    ci = bootstrap_ci(values)
    return {"iqm": ci.estimate, "low": ci.low, "high": ci.high, "n": ci.n, "values": list(values)}


def rolling_window_stats(
    returns: Sequence[float] | np.ndarray, window: int = 10
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, min and max of the last ``window`` episode returns after each episode.

    The thesis plots (figures 8, 11-13, 17) show the mean of the last 10 episodes with a
    min-max band.

    Args:
        returns: episode returns in order.
        window: episodes per window. Defaults to ``10``.

    Returns:
        ``(mean, min, max)`` arrays, one entry per episode (fewer episodes at the start).

    Examples:
        >>> from torchrl_mbmf.analysis.stats import rolling_window_stats
        >>> mean, low, high = rolling_window_stats([1.0, 3.0, 5.0], window=2)
        >>> mean.tolist(), low.tolist(), high.tolist()
        ([1.0, 2.0, 4.0], [1.0, 1.0, 3.0], [1.0, 3.0, 5.0])
    """
    if window < 1:
        raise ValueError(f"window must be >= 1, got {window}")
    arr = np.asarray(returns, dtype=np.float64)
    mean, low, high = (np.empty_like(arr) for _ in range(3))
    for i in range(arr.size):
        chunk = arr[max(0, i - window + 1) : i + 1]
        mean[i], low[i], high[i] = chunk.mean(), chunk.min(), chunk.max()
    return mean, low, high


def first_step_reaching(
    steps: Sequence[int] | np.ndarray,
    values: Sequence[float] | np.ndarray,
    threshold: float,
) -> int | None:
    """The first step at which ``values`` reaches ``threshold`` (the thesis' "PPO-maximum").

    Args:
        steps: real-step count of each value, increasing.
        values: the curve (for example the mean of the last 10 episode returns).
        threshold: the level to reach.

    Returns:
        The step, or ``None`` if the curve never reaches it.

    Examples:
        >>> from torchrl_mbmf.analysis.stats import first_step_reaching
        >>> first_step_reaching([10, 20, 30], [0.0, 5.0, 9.0], 5.0)
        20
        >>> first_step_reaching([10, 20], [0.0, 1.0], 5.0) is None
        True
    """
    s = np.asarray(steps)
    v = np.asarray(values, dtype=np.float64)
    if s.shape != v.shape:
        raise ValueError(f"steps {s.shape} and values {v.shape} must have the same shape")
    hit = np.nonzero(v >= threshold)[0]
    return int(s[hit[0]]) if hit.size else None


def interpolate_curve(
    steps: Sequence[int] | np.ndarray,
    values: Sequence[float] | np.ndarray,
    grid: Sequence[int] | np.ndarray,
) -> np.ndarray:
    """Step-wise (last value carried forward) resampling of a curve onto ``grid``.

    Runs log episodes at different steps; to aggregate seeds, each curve is read on a common
    grid of real-step counts. Grid points before the first logged step are NaN.

    Args:
        steps: logged steps, increasing.
        values: logged values.
        grid: steps to read the curve at.

    Returns:
        Values on the grid.

    Examples:
        >>> from torchrl_mbmf.analysis.stats import interpolate_curve
        >>> interpolate_curve([10, 20], [1.0, 2.0], [5, 10, 15, 25]).tolist()
        [nan, 1.0, 1.0, 2.0]
    """
    s = np.asarray(steps)
    v = np.asarray(values, dtype=np.float64)
    g = np.asarray(grid)
    idx = np.searchsorted(s, g, side="right") - 1
    out = (
        np.where(idx >= 0, v[np.clip(idx, 0, None)], np.nan) if s.size else np.full(g.shape, np.nan)
    )
    return out.astype(np.float64)
