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

import numpy as np
import torch
from numba import njit, prange

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.numerics.jit import PRANGE_ONLY
from cubecloud_cli.raster.projection import NEAR_PLANE

FILTER_SCALE = 0.2  # s: the filter's variance in squared training pixels (the paper's; `splat --filter-scale`)
# A Gaussian projecting within this band beyond the image border still counts as seen: the
# filter should not jump when a mean drifts across the edge (Mip-Splatting's 15%).
SCREEN_MARGIN = 0.15
RECOMPUTE_EVERY = 100  # iterations, after densification has stopped


def sampling_intervals(means: torch.Tensor, cameras: PinholeCameras) -> torch.Tensor:
    """(N,) the finest world distance one training pixel spans at each mean: min over the cameras
    that see it of depth / focal. Means that no camera sees get the largest interval of those
    seen (or 1 pixel at the cameras' mean distance, if none is seen)."""
    half_w, half_h = cameras.width / 2.0, cameras.height / 2.0
    nearest = nearest_seen_depths(
        means.detach().cpu().numpy().astype(np.float64),
        np.ascontiguousarray(cameras.rotations, dtype=np.float64),
        np.ascontiguousarray(cameras.translations, dtype=np.float64),
        float(cameras.focal),
        (1.0 + 2.0 * SCREEN_MARGIN) * half_w,
        (1.0 + 2.0 * SCREEN_MARGIN) * half_h,
        NEAR_PLANE,
    )
    seen_any = np.isfinite(nearest)
    if seen_any.any():
        fallback = nearest[seen_any].max()
    else:
        fallback = np.linalg.norm(cameras.centres(), axis=1).mean()
    nearest = np.where(seen_any, nearest, fallback)
    return torch.from_numpy(nearest / float(cameras.focal)).to(dtype=means.dtype, device=means.device)


@njit(parallel=PRANGE_ONLY, cache=True)
def nearest_seen_depths(means, rotations, translations, focal, limit_x, limit_y, near):
    """(N,) per mean, the smallest depth among the cameras that see it (in front of the near
    plane, projecting within ±limit pixels of the centre), +inf where none does.

    One compiled pass over means × cameras: the same test in torch tensors of N × cameras took
    0.12 s for 100k means and 112 views, and it runs at every densification step."""
    count, views = means.shape[0], rotations.shape[0]
    nearest = np.full(count, np.inf)
    for i in prange(count):
        x, y, z = means[i, 0], means[i, 1], means[i, 2]
        best = np.inf
        for c in range(views):
            depth = rotations[c, 2, 0] * x + rotations[c, 2, 1] * y + rotations[c, 2, 2] * z + translations[c, 2]
            if not depth > near or depth >= best:  # a NaN mean is seen by no camera
                continue
            across = rotations[c, 0, 0] * x + rotations[c, 0, 1] * y + rotations[c, 0, 2] * z + translations[c, 0]
            down = rotations[c, 1, 0] * x + rotations[c, 1, 1] * y + rotations[c, 1, 2] * z + translations[c, 1]
            if abs(focal * across / depth) <= limit_x and abs(focal * down / depth) <= limit_y:
                best = depth
        nearest[i] = best
    return nearest


def filter_variances(means: torch.Tensor, cameras: PinholeCameras, scale: float = FILTER_SCALE) -> torch.Tensor:
    """(N,) the 3D filter's variance (world units²) for each mean."""
    return scale * sampling_intervals(means, cameras) ** 2


def smoothed_scales(log_scales: torch.Tensor, variances: torch.Tensor) -> torch.Tensor:
    """√(s² + v) per axis: the scales of Σ + v I for a Gaussian with axis scales s."""
    return torch.sqrt(torch.exp(2.0 * log_scales) + variances[:, None])


def smoothing_attenuation(log_scales: torch.Tensor, variances: torch.Tensor) -> torch.Tensor:
    """√(det Σ / det(Σ + v I)) = Π s / √(s² + v), in (0, 1], computed in logs: three tiny scales
    would underflow a product of squares."""
    log_ratio = log_scales - 0.5 * torch.log(torch.exp(2.0 * log_scales) + variances[:, None])
    return torch.exp(log_ratio.sum(dim=1).clamp_max(0.0))
