"""Image and volume metrics of docs/design.md §5, vectorised over stacks of slices.

* PSNR with data range 1 (MSE of 0 gives +inf, never a division by zero).
* SSIM after Wang et al., as ``skimage.metrics.structural_similarity(..., gaussian_weights=True,
  sigma=1.5, use_sample_covariance=False, data_range=1)`` computes it: an 11-tap Gaussian
  window (σ = 1.5, truncated at 3.5σ), K1 = 0.01, K2 = 0.03, averaged over the pixels whose
  window lies inside the image (skimage crops the 5-pixel border the same way).
* Masked variants average only over foreground pixels (where the reference is non-zero), since
  black background inflates both numbers.
* 3D: PSNR over all voxels; SSIM as the mean of 2D SSIM over the slices along all three axes.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch
from scipy.ndimage import correlate1d

from cubecloud_cli.numerics.ssim_kernel import stack_ssim_sums

SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5
SSIM_RADIUS = int(SSIM_TRUNCATE * SSIM_SIGMA + 0.5)  # 5, so an 11-tap window
K1, K2 = 0.01, 0.03


def _as_tensor(array) -> torch.Tensor:
    return torch.as_tensor(np.asarray(array, dtype=np.float64))


def psnr_from_mse(mse: float, data_range: float = 1.0) -> float:
    if not math.isfinite(mse):
        return float("nan")
    if mse <= 0.0:
        return float("inf")
    return 10.0 * math.log10(data_range * data_range / mse)


def mse(reference, estimate, mask=None) -> float:
    """Mean squared error, over ``mask`` when given (NaN for an empty mask)."""
    difference = (_as_tensor(estimate) - _as_tensor(reference)) ** 2
    if mask is not None:
        mask = torch.as_tensor(np.asarray(mask, dtype=bool))
        if not bool(mask.any()):
            return float("nan")
        return float(difference[mask].mean())
    return float(difference.mean())


def psnr(reference, estimate, mask=None, data_range: float = 1.0) -> float:
    return psnr_from_mse(mse(reference, estimate, mask), data_range)


def gaussian_window() -> torch.Tensor:
    """The normalised 11-tap Gaussian (σ = 1.5) of SSIM, float64."""
    x = torch.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=torch.float64)
    window = torch.exp(-0.5 * (x / SSIM_SIGMA) ** 2)
    return window / window.sum()


def _valid_blur(stack: np.ndarray, window: np.ndarray) -> np.ndarray:
    """The Gaussian window over the last two axes of ``stack``, kept where it lies inside
    (…, H−10, W−10): the same sums as an unpadded convolution. scipy's 1D pass runs 3× faster
    than torch's one-channel conv2d in float64, which made a 128³ volume's SSIM cost 3 s."""
    r = SSIM_RADIUS
    rows = correlate1d(stack, window, axis=-2, mode="constant")[..., r:-r, :]
    return correlate1d(rows, window, axis=-1, mode="constant")[..., r:-r]


def _valid_blur_torch(stack: torch.Tensor, window: torch.Tensor) -> torch.Tensor:
    """``_valid_blur`` as two unpadded 1D convolutions on ``stack``'s device: on a GPU a 512³
    volume's SSIM takes seconds where scipy's single-threaded passes take minutes."""
    n, h, w = stack.shape
    kernel = window.view(1, 1, -1)
    rows = torch.nn.functional.conv1d(stack.reshape(n * h, 1, w), kernel).view(n, h, w - 2 * SSIM_RADIUS)
    columns = rows.transpose(1, 2).reshape(-1, 1, h)
    blurred = torch.nn.functional.conv1d(columns, kernel).view(n, w - 2 * SSIM_RADIUS, h - 2 * SSIM_RADIUS)
    return blurred.transpose(1, 2)


# Slices per pass on a device: at 512² in float64, about 2 GB of temporaries however deep the stack.
SSIM_DEVICE_CHUNK = 64


def _ssim_formula(x, y, blur, c1: float, c2: float):
    mean_x, mean_y = blur(x), blur(y)
    mean_xy = mean_x * mean_y
    mean_sq = mean_x * mean_x + mean_y * mean_y
    cov = blur(x * y) - mean_xy
    var_sum = blur(x * x + y * y) - mean_sq  # var_x + var_y in one blur: it is linear
    # c1, c2 > 0 keep the denominator positive.
    return (2 * mean_xy + c1) * (2 * cov + c2) / ((mean_sq + c1) * (var_sum + c2))


def ssim_maps(reference, estimate, data_range: float = 1.0, device: torch.device | None = None) -> torch.Tensor:
    """SSIM maps (N, H−10, W−10) of a stack of 2D images (N, H, W) or one image (H, W), float64 on
    the CPU. With ``device``, the blurs run there with torch (the same sums, to rounding)."""
    x = np.asarray(reference, dtype=np.float64)
    y = np.asarray(estimate, dtype=np.float64)
    if x.ndim == 2:
        x, y = x[None], y[None]
    if min(x.shape[-2:]) < 2 * SSIM_RADIUS + 1:
        raise ValueError(f"SSIM needs images of at least {2 * SSIM_RADIUS + 1}×{2 * SSIM_RADIUS + 1} pixels")
    c1, c2 = (K1 * data_range) ** 2, (K2 * data_range) ** 2
    if device is None:
        window = gaussian_window().numpy()
        return torch.from_numpy(_ssim_formula(x, y, lambda a: _valid_blur(a, window), c1, c2))
    window = gaussian_window().to(device)
    parts = []
    for start in range(0, x.shape[0], SSIM_DEVICE_CHUNK):
        chunk_x = torch.from_numpy(x[start : start + SSIM_DEVICE_CHUNK]).to(device)
        chunk_y = torch.from_numpy(y[start : start + SSIM_DEVICE_CHUNK]).to(device)
        parts.append(_ssim_formula(chunk_x, chunk_y, lambda a: _valid_blur_torch(a, window), c1, c2).cpu())
    return torch.cat(parts)


def _crop_mask(mask, shape) -> torch.Tensor:
    mask = torch.as_tensor(np.asarray(mask, dtype=bool))
    if mask.ndim == 2:
        mask = mask[None]
    r = SSIM_RADIUS
    return mask[:, r : mask.shape[1] - r, r : mask.shape[2] - r].expand(shape)


def _masked_mean(maps: torch.Tensor, mask) -> float:
    inside = _crop_mask(mask, maps.shape)
    if not bool(inside.any()):
        return float("nan")
    return float(maps[inside].mean())


def ssim(reference, estimate, mask=None, data_range: float = 1.0) -> float:
    """Mean SSIM over the images of a stack (each image's own mean, then their mean).

    With ``mask``, one mean over all foreground pixels of the stack (NaN if there are none).
    """
    maps = ssim_maps(reference, estimate, data_range)
    if mask is None:
        return float(maps.mean(dim=(-2, -1)).mean())
    return _masked_mean(maps, mask)


def ssim_and_masked(reference, estimate, mask, data_range: float = 1.0) -> tuple[float, float]:
    """``ssim(reference, estimate)`` and ``ssim(reference, estimate, mask)`` from one set of maps."""
    maps = ssim_maps(reference, estimate, data_range)
    return float(maps.mean(dim=(-2, -1)).mean()), _masked_mean(maps, mask)


# Slices per pass of the 3D metrics: their float64 temporaries stay at a few hundred MB at 512³
# instead of a dozen copies of the whole volume (about 18 GB).
VOLUME_SLAB = 32
# From this size on, a volume's SSIM goes through ``ssim_kernel`` (its first compilation takes
# about 7 s; 512³: 35 s against 116–134 s through scipy on the 2-core VM). Below, scipy's passes
# cost less than that compilation (128³: under 1 s).
KERNEL_MIN_VOXELS = 256**3


def volume_metrics(
    reference: np.ndarray, estimate: np.ndarray, mask: np.ndarray | None = None, device: torch.device | None = None
) -> dict[str, float]:
    """3D PSNR, SSIM (mean over slices along the three axes) and MSE, also inside ``mask``
    (default: the body, where the reference is non-zero). ``device``: where SSIM's blurs run
    (default: the CPU). Works through :data:`VOLUME_SLAB` slices at a time, so memory stays flat
    whatever the size (the inputs may be memory-mapped)."""
    if reference.shape != estimate.shape or reference.ndim != 3:
        raise ValueError(f"shapes differ or are not 3D: {reference.shape} vs {estimate.shape}")

    def body(axis: int, part: slice) -> np.ndarray:
        index = (slice(None),) * axis + (part,)
        return np.asarray(reference[index]) > 0 if mask is None else np.asarray(mask[index], dtype=bool)

    squared, squared_body, body_voxels = 0.0, 0.0, 0
    for start in range(0, reference.shape[0], VOLUME_SLAB):
        part = slice(start, start + VOLUME_SLAB)
        difference = (np.asarray(estimate[part], dtype=np.float64) - np.asarray(reference[part], dtype=np.float64)) ** 2
        inside = body(0, part)
        squared += float(difference.sum())
        squared_body += float(difference[inside].sum())
        body_voxels += int(inside.sum())
    mse_all = squared / max(reference.size, 1)
    mse_body = squared_body / body_voxels if body_voxels else float("nan")
    result = {
        "psnr": psnr_from_mse(mse_all),
        "mse": mse_all,
        "psnr_body": psnr_from_mse(mse_body),
        "mse_body": mse_body,
    }
    if min(reference.shape) >= 2 * SSIM_RADIUS + 1:
        result["ssim"], result["ssim_body"] = _volume_ssim(reference, estimate, body, device)
    return result


def _volume_ssim(reference, estimate, body: Callable[[int, slice], np.ndarray], device) -> tuple[float, float]:
    """Mean SSIM of the slices along the three axes, and over the body's pixels; ``body(axis,
    part)`` gives the body of a slab. On the CPU, large volumes go through ``ssim_kernel``."""
    slice_means, body_sum, body_pixels = [], 0.0, 0
    use_kernel = device is None and reference.size >= KERNEL_MIN_VOXELS
    window, c1, c2 = gaussian_window().numpy(), K1**2, K2**2
    for axis in range(3):
        for start in range(0, reference.shape[axis], VOLUME_SLAB):
            part = slice(start, start + VOLUME_SLAB)
            index = (slice(None),) * axis + (part,)
            slab_reference = np.moveaxis(np.asarray(reference[index]), axis, 0)
            slab_estimate = np.moveaxis(np.asarray(estimate[index]), axis, 0)
            inside = np.moveaxis(body(axis, part), axis, 0)
            if use_kernel:
                sums, body_sums, body_counts = stack_ssim_sums(slab_reference, slab_estimate, inside, window, c1, c2)
                height, width = (side - 2 * SSIM_RADIUS for side in slab_reference.shape[1:])
                slice_means.append(torch.from_numpy(sums / (height * width)))
                body_sum += float(body_sums.sum())
                body_pixels += int(body_counts.sum())
                continue
            maps = ssim_maps(slab_reference, slab_estimate, device=device)
            slice_means.append(maps.mean(dim=(-2, -1)))
            cropped = _crop_mask(inside, maps.shape)
            body_sum += float(maps[cropped].sum())
            body_pixels += int(cropped.sum())
    return float(torch.cat(slice_means).mean()), body_sum / body_pixels if body_pixels else float("nan")


def image_metrics(reference: np.ndarray, estimate: np.ndarray) -> dict[str, float]:
    """docs/design.md §5 2D metrics of a stack of views (N, H, W): PSNR, SSIM and MSE per view, then
    averaged over views; the ``*_foreground`` variants count only pixels where the reference is
    non-zero (black background inflates PSNR). Views smaller than the SSIM window get no SSIM."""
    reference = np.asarray(reference, dtype=np.float32)
    estimate = np.asarray(estimate, dtype=np.float32)
    if reference.shape != estimate.shape or reference.ndim != 3:
        raise ValueError(f"need two (N, H, W) stacks of one shape, got {reference.shape} and {estimate.shape}")
    foreground = reference > 0
    per_view = [
        (mse(r, e), mse(r, e, m) if m.any() else float("nan")) for r, e, m in zip(reference, estimate, foreground)
    ]
    result = {
        "psnr": float(np.mean([psnr_from_mse(m) for m, _ in per_view])),
        "mse": float(np.mean([m for m, _ in per_view])),
    }
    with_foreground = [f for _, f in per_view if np.isfinite(f)]
    result["psnr_foreground"] = (
        float(np.mean([psnr_from_mse(f) for f in with_foreground])) if with_foreground else float("nan")
    )
    result["mse_foreground"] = float(np.mean(with_foreground)) if with_foreground else float("nan")
    if min(reference.shape[1:]) >= 2 * SSIM_RADIUS + 1:
        result["ssim"], result["ssim_foreground"] = ssim_and_masked(reference, estimate, foreground)
    return result
