"""The training loss of the paper and of the reference 3DGS: (1 − λ)·L1 + λ·(1 − SSIM), λ = 0.2.

The SSIM here is the reference's training SSIM: the same 11-tap Gaussian window (σ = 1.5) as
the evaluation metric, but with zero padding so the map covers the whole image ("same"), and
its plain mean. Evaluation uses `cubecloud_cli.numerics.metrics` (cropped, as scikit-image).
"""

from __future__ import annotations

import torch

from cubecloud_cli.numerics.metrics import K1, K2, SSIM_RADIUS, gaussian_window

DSSIM_WEIGHT = 0.2


def blur_matrix(size: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(size, size) banded matrix applying the 11-tap Gaussian along one axis with zero padding."""
    taps = gaussian_window().to(dtype=dtype, device=device)
    offsets = torch.arange(size, device=device)
    distance = offsets[None, :] - offsets[:, None]
    inside = distance.abs() <= SSIM_RADIUS
    return torch.where(
        inside, taps[(distance + SSIM_RADIUS).clamp(0, 2 * SSIM_RADIUS)], torch.zeros((), dtype=dtype, device=device)
    )


def training_ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) images in [0, 1], zero-padded, per channel then averaged.

    The five local moments (x, y, x², y², xy) are blurred by two banded matrix products, which
    is the separable zero-padded window exactly. The loss runs every iteration, and on a CPU
    torch's convolutions for these one-channel images cost more than the rasterizer.
    """
    height, width, channels = image.shape
    x = image.permute(2, 0, 1)
    y = target.permute(2, 0, 1)
    moments = torch.cat((x, y, x * x, y * y, x * y), dim=0)
    rows = blur_matrix(height, x.dtype, x.device)
    columns = blur_matrix(width, x.dtype, x.device)
    blurred = rows @ moments @ columns.T
    mean_x, mean_y, xx, yy, xy = blurred.split(channels, dim=0)
    var_x = xx - mean_x * mean_x
    var_y = yy - mean_y * mean_y
    cov = xy - mean_x * mean_y
    c1, c2 = K1**2, K2**2
    numerator = (2 * mean_x * mean_y + c1) * (2 * cov + c2)
    denominator = (mean_x * mean_x + mean_y * mean_y + c1) * (var_x + var_y + c2)  # > 0 by c1, c2
    return (numerator / denominator).mean()


def photometric_loss(image: torch.Tensor, target: torch.Tensor, dssim_weight: float = DSSIM_WEIGHT) -> torch.Tensor:
    l1 = (image - target).abs().mean()
    if dssim_weight == 0.0:
        return l1
    return (1.0 - dssim_weight) * l1 + dssim_weight * (1.0 - training_ssim(image, target))
