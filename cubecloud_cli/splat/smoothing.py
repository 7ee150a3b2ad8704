"""Mip-Splatting's 3D smoothing filter (Yu et al., CVPR 2024): no Gaussian finer than its training
views could see.

The training images sample a point at most ν = focal / depth pixels per world unit, over the
cameras that see it. Detail finer than that was never observed, yet plain 3DGS happily fits
Gaussians far thinner than a pixel, which break into dots when the view zooms in. The filter
convolves every Gaussian with an isotropic one of variance s / ν² (s = 0.2, the paper's), so
Σ' = Σ + (s / ν²) I, and scales its opacity by √(det Σ / det Σ') so that the blur spreads the
Gaussian's mass rather than adding to it. ν is recomputed from the current means as they move
(Mip-Splatting: at each densification and every 100 iterations after), and held fixed between.

The filter depends only on the training cameras, so once trained it is part of the scene: the
PLY carries it baked in (``Gaussians.baked``), and a viewer that knows nothing of it shows what
eval scored.
"""

from __future__ import annotations

import torch

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.raster.projection import NEAR_PLANE

FILTER_SCALE = 0.2  # s: the filter's variance in squared training pixels
# A Gaussian projecting within this band beyond the image border still counts as seen: the
# filter should not jump when a mean drifts across the edge (Mip-Splatting's 15%).
SCREEN_MARGIN = 0.15
RECOMPUTE_EVERY = 100  # iterations, after densification has stopped


def sampling_intervals(means: torch.Tensor, cameras: PinholeCameras, chunk: int = 16) -> torch.Tensor:
    """(N,) the finest world distance one training pixel spans at each mean: min over the cameras
    that see it of depth / focal. Means that no camera sees get the largest interval of those
    seen (or 1 pixel at the cameras' mean distance, if none is seen)."""
    device, dtype = means.device, means.dtype
    rotations = torch.as_tensor(cameras.rotations, dtype=dtype, device=device)
    translations = torch.as_tensor(cameras.translations, dtype=dtype, device=device)
    focal = float(cameras.focal)
    half_w, half_h = cameras.width / 2.0, cameras.height / 2.0
    limit_x, limit_y = (1.0 + 2.0 * SCREEN_MARGIN) * half_w, (1.0 + 2.0 * SCREEN_MARGIN) * half_h
    nearest = torch.full((means.shape[0],), float("inf"), dtype=dtype, device=device)
    with torch.no_grad():
        for start in range(0, len(cameras), chunk):
            camera = (
                torch.einsum("cij,nj->cni", rotations[start : start + chunk], means)
                + translations[start : start + chunk, None]
            )
            depth = camera[..., 2]
            in_front = depth > NEAR_PLANE
            safe = torch.where(in_front, depth, torch.ones_like(depth))
            x = focal * camera[..., 0] / safe
            y = focal * camera[..., 1] / safe
            seen = in_front & (x.abs() <= limit_x) & (y.abs() <= limit_y)
            depth_seen = torch.where(seen, depth, torch.full_like(depth, float("inf")))
            nearest = torch.minimum(nearest, depth_seen.min(dim=0).values)
        seen_any = torch.isfinite(nearest)
        if bool(seen_any.any()):
            fallback = nearest[seen_any].max()
        else:
            fallback = torch.as_tensor(cameras.centres(), dtype=dtype, device=device).norm(dim=1).mean()
        nearest = torch.where(seen_any, nearest, fallback)
    return nearest / focal


def filter_variances(means: torch.Tensor, cameras: PinholeCameras) -> torch.Tensor:
    """(N,) the 3D filter's variance (world units²) for each mean."""
    return FILTER_SCALE * sampling_intervals(means, cameras) ** 2


def smoothed_scales(log_scales: torch.Tensor, variances: torch.Tensor) -> torch.Tensor:
    """√(s² + v) per axis: the scales of Σ + v I for a Gaussian with axis scales s."""
    return torch.sqrt(torch.exp(2.0 * log_scales) + variances[:, None])


def smoothing_attenuation(log_scales: torch.Tensor, variances: torch.Tensor) -> torch.Tensor:
    """√(det Σ / det(Σ + v I)) = Π s / √(s² + v), in (0, 1], computed in logs: three tiny scales
    would underflow a product of squares."""
    log_ratio = log_scales - 0.5 * torch.log(torch.exp(2.0 * log_scales) + variances[:, None])
    return torch.exp(log_ratio.sum(dim=1).clamp_max(0.0))
