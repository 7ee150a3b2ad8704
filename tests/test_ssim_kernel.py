"""The SSIM kernel (numerics/ssim_kernel.py) against the scipy path of numerics/metrics.py: the
same sums to rounding, over random stacks, extreme values and masks, and through volume_metrics."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.numerics import metrics
from cubecloud_cli.numerics.metrics import K1, K2, SSIM_RADIUS, gaussian_window, ssim_maps, volume_metrics
from cubecloud_cli.numerics.ssim_kernel import stack_ssim_sums

WINDOW = gaussian_window().numpy()


def kernel_and_scipy(reference, estimate, body, data_range=1.0):
    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    sums, body_sums, counts = stack_ssim_sums(reference, estimate, body, WINDOW, c1, c2)
    maps = ssim_maps(reference, estimate, data_range).numpy()
    r = SSIM_RADIUS
    inside = body[:, r:-r, r:-r]
    expected = maps.sum(axis=(1, 2)), np.where(inside, maps, 0.0).sum(axis=(1, 2)), inside.sum(axis=(1, 2))
    return (sums, body_sums, counts), expected


@given(
    slices=st.integers(1, 3),
    height=st.integers(11, 24),
    width=st.integers(11, 24),
    scale=st.sampled_from([1e-6, 1.0, 1e3]),
    dtype=st.sampled_from([np.float32, np.float64]),
    seed=st.integers(0, 2**16),
)
@settings(max_examples=25, deadline=None)
def test_the_kernel_sums_the_scipy_maps(slices, height, width, scale, dtype, seed):
    rng = np.random.default_rng(seed)
    reference = (rng.random((slices, height, width)) * scale).astype(dtype)
    reference[reference < 0.3 * scale] = 0  # air, so the body is a real subset
    estimate = np.clip(reference + 0.1 * scale * rng.standard_normal(reference.shape), 0, None).astype(dtype)
    (sums, body_sums, counts), (want_sums, want_body, want_counts) = kernel_and_scipy(
        reference, estimate, reference > 0, data_range=scale
    )
    np.testing.assert_allclose(sums, want_sums, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(body_sums, want_body, rtol=1e-9, atol=1e-9)
    assert np.array_equal(counts, want_counts)


@pytest.mark.parametrize("value", [0.0, 1e-30, 1.0, 3e38])
def test_identical_constant_slices_score_one_and_stay_finite(value):
    # Constant slices: every variance is 0 (or rounds below it, which the kernel clamps).
    stack = np.full((2, 13, 12), value, np.float32)
    sums, body_sums, counts = stack_ssim_sums(stack, stack, stack > 0, WINDOW, K1**2, K2**2)
    pixels = (13 - 2 * SSIM_RADIUS) * (12 - 2 * SSIM_RADIUS)
    assert np.isfinite(sums).all() and np.isfinite(body_sums).all()
    if value < 1e30:  # at 3e38 the sums round by ~1e61, which dwarfs c1 and c2: only finiteness holds
        np.testing.assert_allclose(sums, pixels, rtol=1e-12)
    assert counts.tolist() == ([pixels, pixels] if value > 0 else [0, 0])


def test_volume_metrics_through_the_kernel_are_the_scipy_ones(monkeypatch):
    rng = np.random.default_rng(5)
    reference = rng.random((26, 21, 17)).astype(np.float32)
    reference[reference < 0.4] = 0
    estimate = np.clip(reference + 0.05 * rng.standard_normal(reference.shape), 0, 1).astype(np.float32)
    mask = rng.random(reference.shape) < 0.3
    for given_mask in (None, mask):
        by_scipy = volume_metrics(reference, estimate, given_mask)
        monkeypatch.setattr(metrics, "KERNEL_MIN_VOXELS", 0)
        by_kernel = volume_metrics(reference, estimate, given_mask)
        monkeypatch.undo()
        assert by_kernel.keys() == by_scipy.keys()
        for key in by_scipy:
            assert by_kernel[key] == pytest.approx(by_scipy[key], rel=1e-12, abs=1e-12), key
