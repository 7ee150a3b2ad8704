"""The training loss: the reference's zero-padded SSIM, and L1 + D-SSIM."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.numerics.blur_kernel import blur_same
from cubecloud_cli.numerics.metrics import gaussian_window
from cubecloud_cli.splat.losses import (
    RMSE_FLOOR_SQUARED,
    blur_matrix,
    blur_same_size,
    photometric_loss,
    pixel_loss,
    training_ssim,
    value_anchor_loss,
    volume_at,
)


def dense_reference_ssim(image, target):
    """The reference 3DGS formula with a dense 11×11 window, one channel at a time."""
    window = gaussian_window()
    window = (window[:, None] * window[None, :])[None, None]
    scores = []
    for c in range(image.shape[2]):
        x, y = image[None, None, :, :, c].double(), target[None, None, :, :, c].double()

        def blur(v):
            return F.conv2d(v, window, padding=5)

        mx, my = blur(x), blur(y)
        vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
        scores.append(
            ((2 * mx * my + 1e-4) * (2 * cxy + 9e-4) / ((mx * mx + my * my + 1e-4) * (vx + vy + 9e-4))).mean()
        )
    return torch.stack(scores).mean()


def test_separable_ssim_equals_the_dense_window():
    g = torch.Generator().manual_seed(0)
    for channels in (1, 3):
        image, target = torch.rand(20, 27, channels, generator=g), torch.rand(20, 27, channels, generator=g)
        blurred_target = (image + 0.1 * target).clamp(0, 1)
        for other in (target, blurred_target, image):
            assert abs(float(training_ssim(image, other)) - float(dense_reference_ssim(image, other))) < 1e-6


def test_loss_is_zero_for_a_perfect_image_and_differentiable():
    image = torch.rand(16, 16, 1, requires_grad=True)
    assert float(photometric_loss(image, image.detach()).detach()) < 1e-6
    loss = photometric_loss(image, torch.zeros(16, 16, 1))
    loss.backward()
    assert torch.isfinite(image.grad).all() and image.grad.abs().sum() > 0
    assert float(photometric_loss(image, torch.zeros(16, 16, 1), dssim_weight=0.0).detach()) == float(
        image.abs().mean().detach()
    )


def banded_blur(stack: torch.Tensor) -> torch.Tensor:
    """The window as the two dense banded matrix products the GPU path computes."""
    height, width = stack.shape[-2:]
    return blur_matrix(height, stack.dtype, stack.device) @ stack @ blur_matrix(width, stack.dtype, stack.device).T


@settings(max_examples=30, deadline=None)
@given(
    count=st.integers(1, 5),
    height=st.integers(1, 40),
    width=st.integers(1, 40),
    float32=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_the_blur_kernel_is_the_banded_products_at_any_size(count, height, width, float32, seed):
    # Sizes below the window's 11 taps keep only the taps that land inside the image.
    dtype = torch.float32 if float32 else torch.float64
    stack = torch.rand(count, height, width, generator=torch.Generator().manual_seed(seed), dtype=dtype)
    tolerance = 1e-6 if float32 else 1e-13
    assert torch.allclose(blur_same_size(stack), banded_blur(stack), atol=tolerance, rtol=0)


def test_the_blur_kernel_refuses_a_window_it_would_not_transpose():
    with pytest.raises(ValueError, match="symmetric"):
        blur_same(np.zeros((1, 4, 4)), np.array([0.2, 0.3, 0.5]))
    with pytest.raises(ValueError, match="odd"):
        blur_same(np.zeros((1, 4, 4)), np.array([0.5, 0.5]))


def test_the_blur_backward_is_the_banded_products_backward():
    stack = torch.rand(3, 13, 17, dtype=torch.float64, generator=torch.Generator().manual_seed(1), requires_grad=True)
    assert torch.autograd.gradcheck(blur_same_size, (stack,))
    weights = torch.rand(3, 13, 17, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    (kernel_gradient,) = torch.autograd.grad((blur_same_size(stack) * weights).sum(), stack)
    (banded_gradient,) = torch.autograd.grad((banded_blur(stack) * weights).sum(), stack)
    assert torch.allclose(kernel_gradient, banded_gradient, atol=1e-13, rtol=0)


@settings(max_examples=30, deadline=None)
@given(
    image_level=st.sampled_from([0.0, 1e-30, 0.5, 1.0, 1e6]),
    target_level=st.sampled_from([0.0, 1e-30, 0.5, 1.0, 1e6]),
    noise=st.sampled_from([0.0, 1e-7, 0.3]),
    rmse_share=st.sampled_from([0.0, 0.5, 1.0]),
)
def test_the_loss_and_its_gradient_stay_finite_at_flat_and_extreme_images(image_level, target_level, noise, rmse_share):
    # Flat images zero every variance: c1 and c2 keep SSIM's denominator above zero; a perfect
    # fit zeroes the RMSE, whose square root the floor keeps differentiable.
    generator = torch.Generator().manual_seed(3)
    image = (image_level + noise * torch.rand(24, 24, 1, generator=generator)).requires_grad_(True)
    target = target_level + noise * torch.rand(24, 24, 1, generator=generator)
    loss = photometric_loss(image, target, rmse_share=rmse_share)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(image.grad).all()


@settings(max_examples=30, deadline=None)
@given(
    share=st.floats(0.0, 1.0),
    scale=st.sampled_from([1e-5, 1e-2, 1.0]),
    seed=st.integers(0, 2**16),
)
def test_the_pixel_loss_is_l1_and_rmse_in_their_shares(share, scale, seed):
    generator = torch.Generator().manual_seed(seed)
    image = torch.rand(9, 11, 1, generator=generator, dtype=torch.float64)
    # every error at least scale / 2 from 0, so that finite differences of eps ≪ scale stay off L1's kink
    signs = torch.randint(0, 2, (9, 11, 1), generator=generator, dtype=torch.float64) * 2 - 1
    magnitudes = 0.5 + torch.rand(9, 11, 1, generator=generator, dtype=torch.float64)
    target = image + scale * signs * magnitudes
    difference = (image - target).numpy()
    rmse = np.sqrt((difference**2).mean() + RMSE_FLOOR_SQUARED)
    expected = (1 - share) * np.abs(difference).mean() + share * rmse
    assert float(pixel_loss(image, target, share)) == pytest.approx(expected, rel=1e-12)
    assert torch.autograd.gradcheck(
        lambda x: pixel_loss(x, target, share), image.clone().requires_grad_(True), eps=1e-3 * scale
    )


def test_the_rmse_pulls_large_errors_harder_than_l1_and_nothing_at_a_perfect_fit():
    target = torch.zeros(4, 4, 1, dtype=torch.float64)
    image = torch.full((4, 4, 1), 0.01, dtype=torch.float64)
    image[0, 0, 0] = 0.5
    image.requires_grad_(True)
    (l1_gradient,) = torch.autograd.grad(pixel_loss(image, target, 0.0), image)
    (rmse_gradient,) = torch.autograd.grad(pixel_loss(image, target, 1.0), image)
    assert float(l1_gradient[0, 0, 0]) == pytest.approx(float(l1_gradient[1, 1, 0]))
    assert float(rmse_gradient[0, 0, 0]) == pytest.approx(50 * float(rmse_gradient[1, 1, 0]))
    perfect = target.clone().requires_grad_(True)
    (at_rest,) = torch.autograd.grad(pixel_loss(perfect, target, 1.0), perfect)
    assert float(pixel_loss(perfect.detach(), target, 1.0)) == pytest.approx(1e-6)
    assert torch.equal(at_rest, torch.zeros_like(at_rest))


def voxel_centres(shape):
    """World coordinates of every voxel centre of a volume of ``shape`` over the cube [-1, 1]³, [x, y, z] order."""
    axes = [(2 * torch.arange(n, dtype=torch.float64) + 1) / n - 1 for n in shape]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)


@settings(max_examples=25, deadline=None)
@given(shape=st.tuples(st.integers(1, 7), st.integers(1, 7), st.integers(1, 7)), seed=st.integers(0, 2**16))
def test_the_volume_is_read_at_its_voxel_centres_in_its_own_axis_order(shape, seed):
    volume = torch.rand(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    sampled = volume_at(volume, voxel_centres(shape))
    assert torch.allclose(sampled, volume.reshape(-1), atol=1e-12, rtol=0)


def test_the_volume_is_air_outside_the_cube_and_trilinear_between_centres():
    volume = torch.tensor([[[0.0]], [[1.0]]], dtype=torch.float64)  # two voxels along x
    points = torch.tensor([[-0.5, 0, 0], [0.0, 0, 0], [0.5, 0, 0], [1.5, 0, 0], [0, 3, 0], [0, 0, -7]])
    assert volume_at(volume, points).tolist() == [0.0, 0.5, 1.0, 0.0, 0.0, 0.0]


def grid_sample_at(volume, points):
    """What a GPU reads (torch's grid_sample, zero padding), for the CPU kernel to match."""
    grid = points.to(volume.dtype)[:, [2, 1, 0]].reshape(1, -1, 1, 1, 3)
    return F.grid_sample(volume[None, None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)


@settings(max_examples=25, deadline=None)
@given(
    shape=st.tuples(st.integers(1, 9), st.integers(1, 9), st.integers(1, 9)),
    seed=st.integers(0, 2**16),
    dtype=st.sampled_from([torch.float32, torch.float64]),
)
def test_the_cpu_kernel_reads_the_volume_as_grid_sample_does(shape, seed, dtype):
    generator = torch.Generator().manual_seed(seed)
    volume = torch.rand(shape, generator=generator, dtype=torch.float64).to(dtype)
    points = (torch.rand(200, 3, generator=generator, dtype=torch.float64) * 2.6 - 1.3).to(dtype)
    expected = grid_sample_at(volume, points).reshape(-1)
    tolerance = 1e-6 if dtype == torch.float32 else 1e-12
    assert volume_at(volume, points).dtype == dtype
    assert torch.allclose(volume_at(volume, points), expected, atol=tolerance, rtol=0)


def test_the_cpu_kernel_reads_air_at_points_that_are_not_finite_or_huge():
    volume = torch.ones(3, 4, 5)
    points = torch.tensor(
        [[float("nan"), 0, 0], [0, float("inf"), 0], [0, 0, -float("inf")], [1e30, 0, 0], [0, -1e30, 0], [0, 0, 0]]
    )
    assert volume_at(volume, points).tolist() == [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]


def test_the_value_anchor_pulls_values_and_is_finite_at_the_extremes():
    volume = torch.rand(4, 5, 6, generator=torch.Generator().manual_seed(0))
    means = voxel_centres((4, 5, 6)).float().requires_grad_(True)
    exact = volume.reshape(-1).clone().requires_grad_(True)
    assert float(value_anchor_loss(exact, volume_at(volume, means)).detach()) < 1e-12
    for level in (0.0, 1.0):  # values at the sigmoid's ends, a scan of air and of bone
        values = torch.full((len(means),), level, requires_grad=True)
        loss = value_anchor_loss(values, volume_at(volume, means))
        loss.backward()
        assert torch.isfinite(loss) and torch.isfinite(values.grad).all()
        expected = 2 * (level - volume.reshape(-1)) / len(means)
        assert torch.allclose(values.grad, expected, atol=1e-6)
    empty = value_anchor_loss(torch.zeros(0, requires_grad=True), volume_at(volume, torch.zeros(0, 3)))
    assert float(empty.detach()) == 0.0
    # A read from before the Gaussians changed, even one that would broadcast, is refused.
    for stale in (torch.zeros(1), torch.zeros(len(means) - 1)):
        with pytest.raises(ValueError, match="scan values for"):
            value_anchor_loss(values, stale)
