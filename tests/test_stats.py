"""Seed statistics against values computed by hand."""

import math

import pytest

from mftcn_bench.results.stats import STD_KIND, bootstrap_iqm_ci, format_iqm, format_mean_std, iqm, seed_stats


def test_one_seed_has_no_std_and_no_iqm():
    s = seed_stats([2.0])
    assert (s.n, s.mean, s.std, s.iqm, s.ci_low) == (1, 2.0, None, None, None)
    assert format_mean_std(s) == "2.0000" and format_iqm(s) == "-"


def test_two_seeds_sample_std_and_no_iqm():
    s = seed_stats([1.0, 3.0])
    assert s.mean == 2.0 and s.std == pytest.approx(math.sqrt(2.0))  # ddof=1: ((1 + 1) / 1) ** 0.5
    assert s.iqm is None and "ddof=1" in STD_KIND
    assert format_mean_std(s, 2) == "2.00 ± 1.41"


def test_four_seeds_mean_std_and_interquartile_mean():
    s = seed_stats([10.0, 1.0, 3.0, 2.0])
    assert s.mean == 4.0
    assert s.std == pytest.approx(math.sqrt(50 / 3))  # deviations -3, -2, -1, 6: (9 + 4 + 1 + 36) / 3
    assert s.iqm == 2.5  # the outer quarter (1 and 10) cut: mean of 2 and 3


@pytest.mark.parametrize("values", [[10.0, 1.0, 3.0, 2.0], [0.3, 0.1, 0.7, 0.4, 0.9]])
def test_bootstrap_interval_is_the_exact_resampling_distributions_percentiles(values):
    """Every one of the n^n equally likely resamples enumerated: the 2.5 % and 97.5 % quantiles of their
    IQM are the interval (10,000 random resamples find the same atoms of this discrete distribution)."""
    import itertools

    import numpy as np
    from scipy.stats import trim_mean

    exact = np.array([trim_mean(np.array(c), 0.25) for c in itertools.product(values, repeat=len(values))])
    low, high = np.quantile(exact, [0.025, 0.975])
    assert bootstrap_iqm_ci(values) == pytest.approx((low, high), abs=1e-9)


def test_iqm_of_eight_values_keeps_the_middle_four():
    assert iqm([8, 1, 7, 2, 6, 3, 5, 4]) == 4.5


def test_bootstrap_interval_matches_the_exact_resampling_distribution():
    # Three values, nothing trimmed: a resample's mean is k where k ~ Binomial(3, 1/3). P(k = 0) = 8/27
    # (above 2.5 %) and P(k = 3) = 1/27 (above 2.5 %), so the 95 % percentile interval is exactly [0, 3].
    assert bootstrap_iqm_ci([0.0, 0.0, 3.0]) == (0.0, 3.0)


def test_bootstrap_is_deterministic_and_constant_values_give_a_point():
    values = [0.3, 0.1, 0.7, 0.4, 0.9]
    assert bootstrap_iqm_ci(values) == bootstrap_iqm_ci(list(values))
    s = seed_stats([5.0, 5.0, 5.0])
    assert (s.std, s.iqm, s.ci_low, s.ci_high) == (0.0, 5.0, 5.0, 5.0)


def test_missing_values_are_left_out():
    assert seed_stats([None, float("nan")]) is None
    assert seed_stats([1.0, None, 3.0]).n == 2
