from __future__ import annotations

import numpy as np
import pytest

from torchrl_mbmf.analysis.stats import (
    bootstrap_ci,
    first_step_reaching,
    interpolate_curve,
    iqm,
    iqm_ratio_ci,
    rolling_window_stats,
)


def test_iqm_against_sorted_middle_half():
    rng = np.random.default_rng(0)
    x = rng.normal(size=40)
    middle = np.sort(x)[10:30]
    assert iqm(x) == pytest.approx(middle.mean())
    with pytest.raises(ValueError, match="empty"):
        iqm([])


def test_bootstrap_ci_brackets_estimate_and_shrinks_with_data():
    rng = np.random.default_rng(1)
    small = bootstrap_ci(rng.normal(size=5), statistic="mean")
    big = bootstrap_ci(rng.normal(size=500), statistic="mean")
    assert small.low <= small.estimate <= small.high
    assert (big.high - big.low) < (small.high - small.low)
    # a 95% CI of the mean of N(0,1) samples covers 0 in a large sample
    assert big.low < 0 < big.high
    same = bootstrap_ci([2.0, 2.0, 2.0])
    assert (same.low, same.estimate, same.high) == (2.0, 2.0, 2.0)
    assert bootstrap_ci([3.0]).n == 1
    with pytest.raises(ValueError, match="statistic"):
        bootstrap_ci([1.0, 2.0], statistic="median")
    with pytest.raises(ValueError, match="confidence"):
        bootstrap_ci([1.0, 2.0], confidence=1.5)
    assert small.overlaps(small)


def test_rolling_window_brute_force():
    r = np.arange(25, dtype=float) ** 1.5 * np.where(np.arange(25) % 3, 1, -1)
    mean, low, high = rolling_window_stats(r, window=10)
    for i in range(25):
        chunk = r[max(0, i - 9) : i + 1]
        assert mean[i] == pytest.approx(chunk.mean())
        assert (low[i], high[i]) == (chunk.min(), chunk.max())
    with pytest.raises(ValueError, match="window"):
        rolling_window_stats(r, window=0)


def test_first_step_and_interpolation():
    assert first_step_reaching([1, 2, 3, 4], [0, 3, 2, 5], 3) == 2
    assert first_step_reaching([], [], 1.0) is None
    with pytest.raises(ValueError, match="same shape"):
        first_step_reaching([1, 2], [1.0], 0.0)
    out = interpolate_curve([100, 200, 300], [1.0, 2.0, 3.0], [0, 100, 150, 299, 300, 1000])
    np.testing.assert_array_equal(out, [np.nan, 1.0, 1.0, 2.0, 3.0, 3.0])
    assert np.isnan(interpolate_curve([], [], [1, 2])).all()


def test_iqm_ratio_ci_matches_a_brute_force_bootstrap_and_rejects_bad_input():
    cand = np.array([5.0, 6.0, 7.0, 6.5, 6.2])
    ref = np.array([4.0, 5.5, 5.0, 4.8, 5.9])
    ci = iqm_ratio_ci(cand, ref, n_resamples=4000, seed=3)
    assert ci.estimate == pytest.approx(iqm(cand) / iqm(ref))
    assert ci.n == 5 and ci.low < ci.estimate < ci.high
    # the same bootstrap written out resample by resample
    rng = np.random.default_rng(3)
    draws_c = rng.integers(0, 5, (4000, 5))
    draws_r = rng.integers(0, 5, (4000, 5))
    ratios = [iqm(cand[c]) / iqm(ref[r]) for c, r in zip(draws_c, draws_r, strict=True)]
    assert [ci.low, ci.high] == pytest.approx(np.percentile(ratios, [2.5, 97.5]))
    # constant seeds: no spread, the interval is the ratio itself
    point = iqm_ratio_ci([6.0, 6.0], [3.0, 3.0])
    assert (point.low, point.estimate, point.high) == pytest.approx((2.0, 2.0, 2.0))
    with pytest.raises(ValueError, match="positive"):
        iqm_ratio_ci([1.0], [0.0, 2.0])
    with pytest.raises(ValueError, match="both sides"):
        iqm_ratio_ci([], [1.0])
    with pytest.raises(ValueError, match="confidence"):
        iqm_ratio_ci([1.0], [1.0], confidence=1.5)
