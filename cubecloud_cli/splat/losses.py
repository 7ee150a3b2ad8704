"""The training loss of the paper and of the reference 3DGS: (1 − λ)·L1 + λ·(1 − SSIM), λ = 0.2.

The SSIM here is the reference's training SSIM: the same 11-tap Gaussian window (σ = 1.5) as
the evaluation metric, but with zero padding so the map covers the whole image ("same"), and
its plain mean. Evaluation uses `cubecloud_cli.metrics` (cropped, as scikit-image).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from cubecloud_cli.metrics import K1, K2, SSIM_RADIUS, gaussian_window

DSSIM_WEIGHT = 0.2


def training_ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) images in [0, 1], zero-padded, per channel then averaged."""
    x = image.permute(2, 0, 1)[None]
    y = target.permute(2, 0, 1)[None]
    channels = x.shape[1]
    taps = gaussian_window().to(dtype=x.dtype, device=x.device)
    window = (taps[:, None] * taps[None, :]).expand(channels, 1, -1, -1).contiguous()

    def blur(value: torch.Tensor) -> torch.Tensor:
        return F.conv2d(value, window, padding=SSIM_RADIUS, groups=channels)

    mean_x, mean_y = blur(x), blur(y)
    var_x = blur(x * x) - mean_x * mean_x
    var_y = blur(y * y) - mean_y * mean_y
    cov = blur(x * y) - mean_x * mean_y
    c1, c2 = K1**2, K2**2
    numerator = (2 * mean_x * mean_y + c1) * (2 * cov + c2)
    denominator = (mean_x * mean_x + mean_y * mean_y + c1) * (var_x + var_y + c2)  # > 0 by c1, c2
    return (numerator / denominator).mean()


def photometric_loss(image: torch.Tensor, target: torch.Tensor, dssim_weight: float = DSSIM_WEIGHT) -> torch.Tensor:
    l1 = (image - target).abs().mean()
    if dssim_weight == 0.0:
        return l1
    return (1.0 - dssim_weight) * l1 + dssim_weight * (1.0 - training_ssim(image, target))
