"""SSIM and the volume metrics against scikit-image, including flat and saturated images."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st
from skimage.metrics import structural_similarity

from cubecloud_cli.numerics import metrics as metrics_module
from cubecloud_cli.numerics.metrics import SSIM_RADIUS, psnr, ssim, ssim_and_masked, ssim_maps, volume_metrics


def skimage_map(reference: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """skimage's SSIM map with the settings metrics.py documents, cropped to where the window fits."""
    _, full = structural_similarity(
        reference, estimate, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, full=True
    )
    r = SSIM_RADIUS
    return full[r:-r, r:-r]


@st.composite
def image_pairs(draw) -> tuple[np.ndarray, np.ndarray]:
    height, width = draw(st.integers(11, 24)), draw(st.integers(11, 24))
    seed = draw(st.integers(0, 2**32 - 1))
    kind = draw(st.sampled_from(["noise", "flat", "saturated", "sparse"]))
    rng = np.random.default_rng(seed)
    reference = rng.random((height, width))
    if kind == "flat":
        reference[:] = draw(st.sampled_from([0.0, 1.0, 0.5]))
    elif kind == "saturated":
        reference = (reference > 0.5).astype(np.float64)
    elif kind == "sparse":
        reference[reference < 0.9] = 0.0
    noise = draw(st.sampled_from([0.0, 1e-12, 1e-3, 0.3]))
    estimate = np.clip(reference + noise * rng.standard_normal(reference.shape), 0.0, 1.0)
    return reference, estimate


@settings(max_examples=60, deadline=None)
@given(image_pairs())
@example((np.zeros((11, 11)), np.zeros((11, 11))))
@example((np.ones((11, 11)), np.zeros((11, 11))))
def test_the_ssim_map_is_skimages_inside_the_border(pair):
    reference, estimate = pair
    ours = ssim_maps(reference, estimate).numpy()[0]
    assert np.all(np.isfinite(ours))
    np.testing.assert_allclose(ours, skimage_map(reference, estimate), rtol=0, atol=1e-9)


def test_the_pair_of_means_is_the_two_single_calls():
    rng = np.random.default_rng(3)
    reference = rng.random((4, 20, 17))
    reference[reference < 0.4] = 0.0
    estimate = np.clip(reference + 0.05 * rng.standard_normal(reference.shape), 0, 1)
    mask = reference > 0
    assert ssim_and_masked(reference, estimate, mask) == (ssim(reference, estimate), ssim(reference, estimate, mask))
    whole, inside = ssim_and_masked(reference, estimate, np.zeros_like(mask))
    assert math.isfinite(whole) and math.isnan(inside)


def test_volume_ssim_is_the_mean_over_the_slices_of_all_three_axes():
    rng = np.random.default_rng(5)
    reference = rng.random((13, 16, 12)).astype(np.float32)
    estimate = np.clip(reference + 0.1 * rng.standard_normal(reference.shape), 0, 1).astype(np.float32)
    per_slice = [
        structural_similarity(
            np.take(reference, k, axis).astype(np.float64),
            np.take(estimate, k, axis).astype(np.float64),
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
            data_range=1.0,
        )
        for axis in range(3)
        for k in range(reference.shape[axis])
    ]
    assert volume_metrics(reference, estimate)["ssim"] == pytest.approx(np.mean(per_slice), abs=1e-9)


def _near_white_pair() -> tuple[np.ndarray, np.ndarray]:
    """A white reference against an estimate a hair below it: σ² ≪ C2, where the blurs' order shows most."""
    rng = np.random.default_rng(90)
    estimate = np.where(rng.random((17, 15)) < 0.4, 1.0, 1 - 0.0025 * rng.random((17, 15)))
    return np.ones((17, 15)), estimate


@settings(max_examples=30, deadline=None)
@given(image_pairs())
@example((np.zeros((11, 11)), np.zeros((11, 11))))
@example(_near_white_pair())
@example((np.ones((11, 11)), np.zeros((11, 11))))
def test_the_device_ssim_map_is_the_cpu_one(pair):
    reference, estimate = pair
    on_device = ssim_maps(reference, estimate, device=torch.device("cpu"))
    assert on_device.dtype == torch.float64 and on_device.device.type == "cpu"
    # The two blurs sum their taps in another order, so the moments may differ by a few ulps of ~1.
    # σ² = E[x²] − μ² carries that absolute error, and the map divides it by σx² + σy² + C2 ≥ C2,
    # so agreement is bounded by a few dozen ulps over C2 (~1.6e-11), not by a fixed 1e-12.
    c2 = (metrics_module.K2 * 1.0) ** 2
    tolerance = 64 * np.finfo(np.float64).eps / c2
    np.testing.assert_allclose(on_device.numpy(), ssim_maps(reference, estimate).numpy(), rtol=0, atol=tolerance)


def test_the_device_volume_metrics_cross_chunks_and_axes_as_the_cpu_ones(monkeypatch):
    # A chunk smaller than every axis, so each axis's stack is cut unevenly into passes.
    monkeypatch.setattr(metrics_module, "SSIM_DEVICE_CHUNK", 5)
    rng = np.random.default_rng(7)
    reference = rng.random((13, 16, 12)).astype(np.float32)
    reference[reference < 0.3] = 0.0
    estimate = np.clip(reference + 0.1 * rng.standard_normal(reference.shape), 0, 1).astype(np.float32)
    on_cpu = volume_metrics(reference, estimate)
    on_device = volume_metrics(reference, estimate, device=torch.device("cpu"))
    assert on_device.keys() == on_cpu.keys()
    for key, value in on_cpu.items():
        assert on_device[key] == pytest.approx(value, abs=1e-12), key


def test_ssim_refuses_images_smaller_than_its_window():
    with pytest.raises(ValueError, match="11×11"):
        ssim_maps(np.zeros((10, 30)), np.zeros((10, 30)))


def test_the_3d_metrics_by_slabs_equal_the_whole_volume_at_once(monkeypatch):
    # Slabs of 5 cut every axis unevenly; the sums must come out as one pass over everything.
    monkeypatch.setattr(metrics_module, "VOLUME_SLAB", 5)
    rng = np.random.default_rng(8)
    reference = rng.random((13, 16, 12)).astype(np.float32)
    reference[reference < 0.3] = 0.0
    estimate = np.clip(reference + 0.1 * rng.standard_normal(reference.shape), 0, 1).astype(np.float32)
    got = volume_metrics(reference, estimate)
    body = reference > 0
    assert got["psnr"] == pytest.approx(psnr(reference, estimate), abs=1e-10)
    assert got["psnr_body"] == pytest.approx(psnr(reference, estimate, body), abs=1e-10)
    maps = [ssim_maps(np.moveaxis(reference, a, 0), np.moveaxis(estimate, a, 0)) for a in range(3)]
    assert got["ssim"] == pytest.approx(float(torch.cat([m.mean(dim=(-2, -1)) for m in maps]).mean()), abs=1e-12)
    inside = torch.cat([m[metrics_module._crop_mask(np.moveaxis(body, a, 0), m.shape)] for a, m in enumerate(maps)])
    assert got["ssim_body"] == pytest.approx(float(inside.mean()), abs=1e-12)
    empty = volume_metrics(np.zeros((12, 12, 12), np.float32), np.zeros((12, 12, 12), np.float32))
    assert np.isnan(empty["psnr_body"]) and np.isnan(empty["ssim_body"]) and empty["psnr"] == float("inf")
