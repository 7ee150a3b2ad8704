"""The training loss: the reference's zero-padded SSIM, and L1 + D-SSIM."""

import torch
import torch.nn.functional as F

from cubecloud_cli.numerics.metrics import gaussian_window
from cubecloud_cli.splat.losses import photometric_loss, training_ssim


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
