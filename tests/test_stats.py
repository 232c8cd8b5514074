"""Bootstrap intervals, paired differences and the exact McNemar test against closed forms."""

import math

import numpy as np
import pytest

from hipolicy_jax.evaluation import stats


def test_bootstrap_mean_is_the_mean_of_seed_means_and_covers_it():
    groups = {0: [1, 1, 0, 1], 1: [0, 0, 1, 0, 0, 0], 2: [1, 1, 1]}
    iv = stats.bootstrap_mean(groups, resamples=4000)
    assert iv.mean == pytest.approx(np.mean([0.75, 1 / 6, 1.0]))
    assert 0.0 <= iv.low < iv.mean < iv.high <= 1.0
    assert stats.bootstrap_mean(groups, resamples=4000) == iv  # deterministic for a fixed seed


def test_bootstrap_width_matches_the_binomial_standard_error_for_one_seed():
    """One seed of n Bernoulli(p) outcomes: the interval is about ±1.96·sqrt(p(1-p)/n)."""
    x = np.r_[np.ones(60), np.zeros(40)]
    iv = stats.bootstrap_mean([x])
    half = 1.96 * math.sqrt(0.6 * 0.4 / 100)
    assert iv.low == pytest.approx(0.6 - half, abs=0.015) and iv.high == pytest.approx(0.6 + half, abs=0.015)


def test_seed_variation_widens_the_interval():
    """Seeds that disagree (0 % vs 100 %) give a far wider interval than seeds that agree at the same mean."""
    agree = stats.bootstrap_mean({s: np.r_[np.ones(50), np.zeros(50)] for s in range(4)}, resamples=4000)
    disagree = stats.bootstrap_mean({0: np.ones(100), 1: np.zeros(100), 2: np.ones(100), 3: np.zeros(100)},
                                    resamples=4000)
    assert agree.mean == disagree.mean == 0.5
    assert (disagree.high - disagree.low) > 3 * (agree.high - agree.low)


def test_nonfinite_values_are_dropped_and_empty_is_nan():
    iv = stats.bootstrap_mean({0: [50.0, math.nan, 70.0], 1: [math.nan]})
    assert iv.mean == 60.0
    assert all(math.isnan(v) for v in stats.bootstrap_mean({0: [math.nan]}))
    assert stats.bootstrap_mean({0: [3.0]}) == (3.0, 3.0, 3.0)


def test_paired_difference_and_mcnemar():
    a = {0: [1, 1, 1, 0, 1], 1: [1, 1, 0, 1, 1], 2: [0, 0, 0, 0, 0]}
    b = {0: [1, 0, 0, 0, 1], 1: [1, 0, 0, 1, 0], 3: [1, 1, 1, 1, 1]}  # seed 2 / 3 are not shared
    d = stats.paired_difference(a, b, resamples=4000)
    assert d.mean == pytest.approx(0.4)  # (2/5 + 2/5) / 2
    only_a, only_b, p = stats.mcnemar_exact(a, b)
    assert (only_a, only_b) == (4, 0)
    assert p == pytest.approx(2 / 16)  # exact two-sided binomial: 2 · P(X <= 0 | n = 4)
    assert stats.mcnemar_exact({0: [1, 0]}, {0: [1, 0]}) == (0, 0, 1.0)
    assert stats.verdict(stats.Interval(0.1, 0.02, 0.2)) == "wins"
    assert stats.verdict(stats.Interval(-0.1, -0.2, -0.01)) == "loses"
    assert stats.verdict(stats.Interval(0.1, -0.02, 0.2)) == "ties"
    with pytest.raises(ValueError, match="same episodes"):
        stats.paired_difference({0: [1, 0]}, {0: [1, 0, 1]})


def test_task_average_interval():
    a = {0: np.ones(50), 1: np.ones(50)}
    b = {0: np.r_[np.ones(10), np.zeros(40)], 1: np.r_[np.ones(20), np.zeros(30)]}
    iv = stats.bootstrap_average([a, b, {0: [math.nan]}], resamples=4000)  # the empty task is left out
    assert iv.mean == pytest.approx((1.0 + 0.3) / 2)
    assert iv.low < iv.mean < iv.high and iv.high <= 1.0
