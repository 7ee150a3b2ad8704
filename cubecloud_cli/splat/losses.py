"""The training loss of the paper and of the reference 3DGS: (1 − λ)·L1 + λ·(1 − SSIM), λ = 0.2,
whose pixel term may give a share ρ to the image's root-mean-square error:
(1 − λ)·[(1 − ρ)·L1 + ρ·RMSE] + λ·(1 − SSIM).

The SSIM here is the reference's training SSIM: the same 11-tap Gaussian window (σ = 1.5) as
the evaluation metric, but with zero padding so the map covers the whole image ("same"), and
its plain mean. Evaluation uses `cubecloud_cli.numerics.metrics` (cropped, as scikit-image).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from cubecloud_cli.numerics.blur_kernel import blur_same
from cubecloud_cli.numerics.metrics import K1, K2, SSIM_RADIUS, gaussian_window
from cubecloud_cli.numerics.trilinear import sample_cube_into

DSSIM_WEIGHT = 0.2
# Under the RMSE's square root: its gradient, error / (pixels · RMSE), stays finite at a perfect
# fit, and the floor (an RMSE of 1e-6) is far below an 8-bit level (3.9e-3).
RMSE_FLOOR_SQUARED = 1e-12
_WINDOW = gaussian_window().numpy()  # float64; the kernel takes it in each stack's dtype


def blur_matrix(size: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(size, size) banded matrix applying the 11-tap Gaussian along one axis with zero padding."""
    taps = gaussian_window().to(dtype=dtype, device=device)
    offsets = torch.arange(size, device=device)
    distance = offsets[None, :] - offsets[:, None]
    inside = distance.abs() <= SSIM_RADIUS
    return torch.where(
        inside, taps[(distance + SSIM_RADIUS).clamp(0, 2 * SSIM_RADIUS)], torch.zeros((), dtype=dtype, device=device)
    )


class _SameBlurOnCpu(torch.autograd.Function):
    """The window over a (N, H, W) CPU stack by the numba kernel; the operator is symmetric, so
    its backward is the same blur of the gradient."""

    @staticmethod
    def forward(ctx, stack: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(blur_same(stack.detach().numpy(), _WINDOW))

    @staticmethod
    def backward(ctx, gradient: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(blur_same(gradient.detach().numpy(), _WINDOW))


def blur_same_size(stack: torch.Tensor) -> torch.Tensor:
    """The separable zero-padded window over the last two axes of a (N, H, W) stack.

    On a CPU a numba kernel of 11 taps per axis; elsewhere two banded matrix products, which
    cost size³ but are what a GPU does fastest with one-channel images."""
    if stack.device.type == "cpu":
        return _SameBlurOnCpu.apply(stack)
    height, width = stack.shape[-2:]
    rows = blur_matrix(height, stack.dtype, stack.device)
    columns = blur_matrix(width, stack.dtype, stack.device)
    return rows @ stack @ columns.T


def training_ssim(image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two (H, W, C) images in [0, 1], zero-padded, per channel then averaged.

    The five local moments (x, y, x², y², xy) are blurred by the separable zero-padded window
    (``blur_same_size``). The loss runs every iteration, and on a CPU torch's convolutions for
    these one-channel images cost more than the rasterizer.
    """
    channels = image.shape[2]
    x = image.permute(2, 0, 1)
    y = target.permute(2, 0, 1)
    moments = torch.cat((x, y, x * x, y * y, x * y), dim=0)
    blurred = blur_same_size(moments)
    mean_x, mean_y, xx, yy, xy = blurred.split(channels, dim=0)
    var_x = xx - mean_x * mean_x
    var_y = yy - mean_y * mean_y
    cov = xy - mean_x * mean_y
    c1, c2 = K1**2, K2**2
    numerator = (2 * mean_x * mean_y + c1) * (2 * cov + c2)
    denominator = (mean_x * mean_x + mean_y * mean_y + c1) * (var_x + var_y + c2)  # > 0 by c1, c2
    return (numerator / denominator).mean()


def pixel_loss(image: torch.Tensor, target: torch.Tensor, rmse_share: float = 0.0) -> torch.Tensor:
    """(1 − ρ)·L1 + ρ·RMSE of two images. L1 pulls every pixel's error down at one rate; the RMSE
    pulls each in proportion to its size over the image's RMSE, as PSNR (−20·log10 RMSE) scores
    them, so the few large errors on the edges of small bright structures weigh more."""
    difference = image - target
    l1 = difference.abs().mean()
    if rmse_share == 0.0:
        return l1
    rmse = torch.sqrt((difference * difference).mean() + RMSE_FLOOR_SQUARED)
    return (1.0 - rmse_share) * l1 + rmse_share * rmse


def photometric_loss(
    image: torch.Tensor, target: torch.Tensor, dssim_weight: float = DSSIM_WEIGHT, rmse_share: float = 0.0
) -> torch.Tensor:
    pixels = pixel_loss(image, target, rmse_share)
    if dssim_weight == 0.0:
        return pixels
    return (1.0 - dssim_weight) * pixels + dssim_weight * (1.0 - training_ssim(image, target))


def volume_at(volume: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(N,) an (X, Y, Z) volume, indexed [x, y, z] as ``volume.npy`` is, read trilinearly at world
    points (N, 3) of the cube [-1, 1]³, whose faces are the outer faces of the edge voxels; it
    falls to 0 (air) over the voxel past the outer voxel centres, so it is 0 from half a voxel
    outside the cube on. Not differentiable: it reads a fixed scan at fixed points."""
    points = points.detach()
    if volume.device.type == "cpu":
        grid = np.ascontiguousarray(volume.detach().numpy())
        out = np.empty(points.shape[0], dtype=grid.dtype)
        sample_cube_into(grid, np.ascontiguousarray(points.to(volume.dtype).numpy()), out)
        return torch.from_numpy(out)
    # grid_sample reads its grid's last axis as (W, H, D): the volume's z, y, x.
    grid = points.to(volume.dtype)[:, [2, 1, 0]].reshape(1, -1, 1, 1, 3)
    sampled = F.grid_sample(volume[None, None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    return sampled.reshape(-1)


def value_anchor_loss(values: torch.Tensor, scan: torch.Tensor) -> torch.Tensor:
    """Mean squared gap between each Gaussian's value and ``scan``, the scan's value at its centre
    (:func:`volume_at`, which moves no centre). 0 for no Gaussians."""
    if scan.shape != values.shape:  # a read from before the Gaussians changed
        raise ValueError(f"{tuple(scan.shape)} scan values for {tuple(values.shape)} Gaussian values")
    if values.numel() == 0:
        return values.sum()
    return ((values - scan.to(values.dtype)) ** 2).mean()
