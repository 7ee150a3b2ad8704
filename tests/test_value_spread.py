"""The scan's spread over a scalar Gaussian (splat/value_spread.py): gᵀΣg, its kernel against the
torch formula and finite differences, what it means, its extremes, and the scan's gradient."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from kernel_oracle import assert_matches_formula

from cubecloud_cli.raster.projection import quaternion_to_rotation
from cubecloud_cli.splat.value_spread import (
    scan_gradient_at,
    scan_gradient_reference,
    value_spread,
    value_spread_loss,
    value_spread_reference,
)


def _random(seed: int, count: int, dtype=torch.float64):
    generator = torch.Generator().manual_seed(seed)
    quaternions = torch.randn(count, 4, generator=generator, dtype=dtype)
    log_scales = torch.randn(count, 3, generator=generator, dtype=dtype) - 3.0
    gradients = torch.randn(count, 3, generator=generator, dtype=dtype) * 20.0
    return quaternions, log_scales, gradients


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), dtype=st.sampled_from(["32", "64"]))
def test_the_kernel_matches_the_torch_formula_and_its_gradients(seed, dtype):
    dtype = torch.float32 if dtype == "32" else torch.float64
    quaternions, log_scales, gradients = _random(seed, 64, dtype)
    quaternions.requires_grad_(True)
    log_scales.requires_grad_(True)
    kernel = value_spread(quaternions, log_scales, gradients)
    formula = value_spread_reference(quaternions, log_scales, gradients)
    tolerance = {"rtol": 1e-4, "atol": 1e-6} if dtype == torch.float32 else {"rtol": 1e-10, "atol": 1e-12}
    assert_matches_formula(kernel, formula, (quaternions, log_scales), seed, tolerance, gradient_atol=1e-4)


def test_the_kernels_gradients_match_finite_differences():
    quaternions, log_scales, gradients = _random(5, 6)
    assert torch.autograd.gradcheck(
        lambda q, s: value_spread(q, s, gradients),
        (quaternions.requires_grad_(True), log_scales.requires_grad_(True)),
    )


def test_it_is_the_variance_of_a_linear_scan_over_the_gaussians_footprint():
    """Points drawn from N(μ, Σ): the scan g·x at them varies by gᵀΣg (Monte Carlo, 200,000 draws);
    a Gaussian flat across g has almost none, the same turned to lie along g has much more."""
    generator = torch.Generator().manual_seed(0)
    quaternion = torch.tensor([[0.8, 0.3, -0.4, 0.2]], dtype=torch.float64)
    log_scales = torch.log(torch.tensor([[0.05, 0.01, 0.002]], dtype=torch.float64))
    g = torch.tensor([[3.0, -7.0, 12.0]], dtype=torch.float64)
    rotation = quaternion_to_rotation(quaternion / quaternion.norm())[0]
    draws = (rotation @ (torch.randn(3, 200_000, generator=generator, dtype=torch.float64) * log_scales.exp().T)).T
    sampled = (draws @ g[0]).var()
    assert float(value_spread(quaternion, log_scales, g)) == pytest.approx(float(sampled), rel=0.01)
    flat = torch.log(torch.tensor([[0.05, 0.05, 0.001]], dtype=torch.float64))
    identity = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    across = value_spread(identity, flat, torch.tensor([[0.0, 0.0, 10.0]], dtype=torch.float64))
    along = value_spread(identity, flat, torch.tensor([[10.0, 0.0, 0.0]], dtype=torch.float64))
    assert float(across) == pytest.approx(1e-4) and float(along) == pytest.approx(0.25)


def test_minimizing_it_thins_a_gaussian_across_the_edge_only():
    log_scales = torch.log(torch.full((1, 3), 0.05, dtype=torch.float64)).requires_grad_(True)
    identity = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    edge = torch.tensor([[0.0, 40.0, 0.0]], dtype=torch.float64)
    loss = value_spread_loss(identity, log_scales, edge)
    (gradient,) = torch.autograd.grad(loss, log_scales)
    assert gradient[0, 1] > 0 and gradient[0, 0] == 0 and gradient[0, 2] == 0


@pytest.mark.parametrize(
    "quaternion, log_scale, gradient",
    [
        ([0.0, 0, 0, 0], [-3.0, -3.0, -3.0], [1.0, 2.0, 3.0]),  # no rotation
        ([math.inf, 0, 0, 0], [-3.0, -3.0, -3.0], [1.0, 2.0, 3.0]),
        ([math.nan, 0, 0, 0], [-3.0, -3.0, -3.0], [1.0, 2.0, 3.0]),
        ([1.0, 0, 0, 0], [-3.0, -3.0, -3.0], [math.nan, 2.0, 3.0]),
        ([1.0, 0, 0, 0], [-3.0, -3.0, -3.0], [math.inf, 2.0, 3.0]),
        ([1.0, 0, 0, 0], [-3.0, math.nan, -3.0], [1.0, 2.0, 3.0]),
        ([1.0, 0, 0, 0], [60.0, 60.0, 60.0], [1e6, 1e6, 1e6]),  # past float32's range
        ([1.0, 0, 0, 0], [1000.0, 0.0, 0.0], [1.0, 2.0, 3.0]),  # past float64's
    ],
)
def test_where_it_cannot_be_computed_it_is_zero_with_no_gradient(quaternion, log_scale, gradient):
    for function in (value_spread, value_spread_reference):
        for dtype in (torch.float32, torch.float64):
            q = torch.tensor([quaternion], dtype=dtype, requires_grad=True)
            s = torch.tensor([log_scale], dtype=dtype, requires_grad=True)
            value = function(q, s, torch.tensor([gradient], dtype=dtype))
            assert value.item() == 0.0
            value.sum().backward()
            assert not q.grad.any() and not s.grad.any()


@settings(max_examples=40, deadline=None)
@given(
    log_scales=st.lists(st.floats(-10.0, 10.0), min_size=3, max_size=3),
    gradient=st.lists(st.floats(-1e4, 1e4), min_size=3, max_size=3),
    quaternion=st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4),
)
def test_it_and_its_gradient_stay_finite_over_the_scales_limits(log_scales, gradient, quaternion):
    """Scales e^-10 to e^10 (LOG_SCALE_LIMIT), any gradient a normalized scan can have on any grid,
    any quaternion including 0, in float32: a finite, non-negative spread and finite gradients."""
    q = torch.tensor([quaternion], dtype=torch.float32, requires_grad=True)
    s = torch.tensor([log_scales], dtype=torch.float32, requires_grad=True)
    loss = value_spread_loss(q, s, torch.tensor([gradient], dtype=torch.float32))
    assert torch.isfinite(loss) and loss.item() >= 0.0
    loss.backward()
    assert torch.isfinite(q.grad).all() and torch.isfinite(s.grad).all()


def test_no_gaussians_give_a_zero_loss():
    log_scales = torch.zeros(0, 3, requires_grad=True)
    loss = value_spread_loss(torch.zeros(0, 4), log_scales, torch.zeros(0, 3))
    assert loss.item() == 0.0
    loss.backward()


def _cube_points(size: int) -> np.ndarray:
    """World coordinates of the voxel centres of a size³ grid over [-1, 1]³, along one axis."""
    return (np.arange(size) + 0.5) * 2.0 / size - 1.0


def test_the_scans_gradient_of_a_linear_scan_is_its_slope_inside_and_falls_outside():
    size = 32
    x, y, z = np.meshgrid(*[_cube_points(size)] * 3, indexing="ij")
    volume = torch.from_numpy((0.5 + 0.2 * x - 0.1 * y + 0.05 * z).astype(np.float32))
    inside = torch.rand(500, 3, generator=torch.Generator().manual_seed(1)) * 1.6 - 0.8
    gradient = scan_gradient_at(volume, inside)
    torch.testing.assert_close(gradient, torch.tensor([[0.2, -0.1, 0.05]]).expand(500, 3), atol=1e-5, rtol=1e-4)
    far = torch.tensor([[3.0, 0.0, 0.0], [math.nan, 0.0, 0.0], [0.0, math.inf, 0.0]])
    assert not scan_gradient_at(volume, far).any()
    # At the cube's face the scan falls to 0 (air) over half a voxel: a gradient pointing inward.
    face = scan_gradient_at(volume, torch.tensor([[1.0, 0.0, 0.0]]))
    assert face[0, 0] < -4.0


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), shape=st.sampled_from([(8, 8, 8), (5, 9, 7), (16, 4, 12)]))
def test_the_scans_gradient_kernel_matches_grid_sample(seed, shape):
    generator = torch.Generator().manual_seed(seed)
    volume = torch.rand(shape, generator=generator)
    points = torch.rand(300, 3, generator=generator) * 2.6 - 1.3  # inside, at the faces and beyond
    torch.testing.assert_close(
        scan_gradient_at(volume, points), scan_gradient_reference(volume, points), atol=2e-5, rtol=1e-4
    )
