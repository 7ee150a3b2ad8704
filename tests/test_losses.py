"""The training loss: the reference's zero-padded SSIM, and L1 + D-SSIM."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.numerics.blur_kernel import blur_same
from cubecloud_cli.numerics.metrics import gaussian_window
from cubecloud_cli.splat.losses import blur_matrix, blur_same_size, photometric_loss, training_ssim


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
)
def test_the_loss_and_its_gradient_stay_finite_at_flat_and_extreme_images(image_level, target_level, noise):
    # Flat images zero every variance: c1 and c2 keep SSIM's denominator above zero.
    generator = torch.Generator().manual_seed(3)
    image = (image_level + noise * torch.rand(24, 24, 1, generator=generator)).requires_grad_(True)
    target = target_level + noise * torch.rand(24, 24, 1, generator=generator)
    loss = photometric_loss(image, target)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(image.grad).all()
