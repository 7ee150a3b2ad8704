"""The cohort's paired statistics against scipy on known inputs, and at the extremes."""

import math

import numpy as np
import pytest
import scipy.stats
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cohort.statistics import (
    average_ranks,
    bootstrap_mean_interval,
    mean_std,
    paired_summary,
    wilcoxon_signed_rank_p,
)

distinct = st.lists(st.floats(-50.0, 50.0, allow_nan=False), min_size=1, max_size=30, unique=True)


@settings(max_examples=80, deadline=None)
@given(values=distinct)
def test_the_exact_wilcoxon_p_is_scipys(values):
    d = np.array([v for v in values if v != 0.0])
    if d.size == 0 or np.unique(np.abs(d)).size < d.size:
        return  # ties between |d| are the other test's
    assert wilcoxon_signed_rank_p(d) == pytest.approx(scipy.stats.wilcoxon(d, method="exact").pvalue, rel=1e-9)


@settings(max_examples=60, deadline=None)
@given(values=st.lists(st.integers(-6, 6), min_size=8, max_size=70))
def test_with_ties_and_zeros_the_normal_approximation_is_scipys(values):
    d = np.array(values, dtype=float)
    nonzero = d[d != 0]
    if nonzero.size < 2 or np.unique(np.abs(nonzero)).size == nonzero.size:
        return
    expected = scipy.stats.wilcoxon(nonzero, method="approx", correction=False).pvalue
    assert wilcoxon_signed_rank_p(d) == pytest.approx(expected, rel=1e-9)


def test_a_large_cohort_without_ties_uses_the_normal_approximation_like_scipy():
    d = np.random.default_rng(4).normal(0.3, 1.0, 80)
    expected = scipy.stats.wilcoxon(d, method="approx", correction=False).pvalue
    assert wilcoxon_signed_rank_p(d) == pytest.approx(expected, rel=1e-9)


def test_wilcoxon_at_the_extremes():
    assert wilcoxon_signed_rank_p([]) == 1.0
    assert wilcoxon_signed_rank_p([0.0, 0.0, np.nan, np.inf]) == 1.0
    assert wilcoxon_signed_rank_p([3.0]) == 1.0  # one scan cannot reject anything
    assert wilcoxon_signed_rank_p([1.0] * 200) < 1e-30  # all ties: the variance is guarded, not zero
    assert wilcoxon_signed_rank_p(np.arange(1.0, 11.0)) == pytest.approx(2 / 1024)


def test_ranks_average_over_ties():
    assert average_ranks(np.array([3.0, 1.0, 3.0, 2.0])).tolist() == [3.5, 1.0, 3.5, 2.0]


def test_the_bootstrap_interval_matches_scipys_percentile_bootstrap():
    d = np.random.default_rng(1).normal(1.5, 2.0, 40)
    low, high = bootstrap_mean_interval(d, resamples=20_000, seed=3)
    theirs = scipy.stats.bootstrap((d,), np.mean, method="percentile", n_resamples=20_000, random_state=5)
    assert low == pytest.approx(theirs.confidence_interval.low, abs=0.05)
    assert high == pytest.approx(theirs.confidence_interval.high, abs=0.05)
    assert low < d.mean() < high


def test_the_bootstrap_at_the_extremes():
    assert all(math.isnan(v) for v in bootstrap_mean_interval([]))
    assert bootstrap_mean_interval([2.5]) == (2.5, 2.5)
    assert bootstrap_mean_interval([1e308, 1e308]) == (1e308, 1e308)


def test_mean_and_std_leave_out_what_is_not_finite():
    assert mean_std([1.0, 3.0, np.nan, np.inf]) == (2.0, pytest.approx(math.sqrt(2.0)))
    mean, std = mean_std([4.0])
    assert mean == 4.0 and math.isnan(std)
    assert all(math.isnan(v) for v in mean_std([np.nan]))
    assert mean_std([1e308, 1e308, 1e308]) == (1e308, 0.0)


def test_the_paired_summary_drops_scans_without_both_scores():
    summary = paired_summary([46.0, 44.0, np.nan, 40.0, 41.0], [44.0, 45.0, 43.0, 40.0, np.inf])
    assert summary.scans == 3 and (summary.wins, summary.losses, summary.ties) == (1, 1, 1)
    assert summary.mean_difference == pytest.approx(1.0 / 3.0)
    assert summary.ci_low <= summary.mean_difference <= summary.ci_high
