import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.pipeline.cost import describe_cost, expected_cost, power_law

POINTS = {128: 100.0, 256: 400.0, 512: 3200.0}  # slopes 2, then 3


def test_the_power_law_goes_through_the_measured_sizes_and_follows_their_slopes():
    assert [power_law(s, POINTS) for s in POINTS] == pytest.approx(list(POINTS.values()))
    assert power_law(192, POINTS) == pytest.approx(100.0 * 1.5**2)
    assert power_law(384, POINTS) == pytest.approx(400.0 * 1.5**3)
    assert power_law(64, POINTS) == pytest.approx(25.0)  # the first slope, below the first size
    assert power_law(1024, POINTS) == pytest.approx(25600.0)  # the last slope, beyond the last


@settings(max_examples=100, deadline=None)
@given(size=st.one_of(st.floats(1e-6, 1e9), st.sampled_from([0.0, -1.0, math.inf, math.nan])))
def test_the_power_law_is_finite_and_positive_or_nan_at_the_extremes(size):
    value = power_law(size, POINTS)
    if size > 0 and math.isfinite(size):
        assert value > 0 and not math.isnan(value)
    else:
        assert math.isnan(value)


def test_the_cost_line_says_minutes_and_gigabytes_or_nothing():
    measured = {128: (120.0, 0.6), 512: (1920.0, 6.0)}
    assert expected_cost(256, measured) == pytest.approx((480.0, 0.6 * 10**0.5))
    assert describe_cost(512, measured).startswith("a 512³ detail run takes about 32 min and 6.0 GB")
    assert expected_cost(256, {}) is None and describe_cost(256, {}) is None
    assert power_law(200, {256: 5.0}) == 5.0
