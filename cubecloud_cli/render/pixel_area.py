"""Pixel-area renders: each pixel the mean of a k × k grid of sub-pixel rays.

A splat is a continuous image, and a pixel of a real camera integrates light over its area; a
reference that samples each pixel's centre only would alias when the view zooms out. Through
any field and image model, the k² sub-pixel images are rendered one after another. For ``dvr``
through a grid on the CPU (the novel-view references) all k² rays of a pixel go through the
numba march in one call, next to each other, and the pixels in tiles of :data:`RAY_TILE` rays a
side: rays that pass the same voxels follow each other, and find them in the cache. A 512²
reference of a 512³ chest CT at 2 × 2 took 11.2 s as four images and 6.1 s so; every ray and
every sum is the same, so the image is the same to the bit (tests/test_pixel_area.py).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.render.image_models import ImageModel
from cubecloud_cli.render.rays import RAY_TILE, camera_rays, tiled_order
from cubecloud_cli.render.renderer import fused_grid_dvr, march_grid_view, render_view_under


def subpixel_points(factor: int) -> list[tuple[float, float]]:
    """The centres of a factor × factor grid over a pixel, in fractions of a pixel."""
    return [((i + 0.5) / factor, (j + 0.5) / factor) for j in range(factor) for i in range(factor)]


def pixel_area_render(
    field, cameras: PinholeCameras, index: int, model: ImageModel, support, device: torch.device, factor: int
) -> np.ndarray:
    """(H, W) float32 view ``index`` with each pixel the mean of factor × factor sub-pixel samples."""
    return pixel_area_renders(field, cameras, index, [model], None if support is None else [support], device, factor)[0]


def pixel_area_renders(
    field,
    cameras: PinholeCameras,
    index: int,
    models: Sequence[ImageModel],
    supports,
    device: torch.device,
    factor: int,
) -> np.ndarray:
    """(K, H, W) float32: :func:`pixel_area_render` under each of K image models; a fused grid
    march takes each ray once for all K (each image to the bit as alone)."""
    points = subpixel_points(factor)
    total = np.zeros((len(models), cameras.height * cameras.width), dtype=np.float64)
    if supports is None:
        supports = [None if model.kind == "slice" else field.support(model.support_threshold) for model in models]
    if fused_grid_dvr(field, models, torch.device(device)):
        order = tiled_order(cameras.height, cameras.width, max(1, RAY_TILE // factor))
        rays = [camera_rays(cameras, index, torch.device(device), point) for point in points]
        origin = rays[0][0]
        # (pixels in tile order, sub-pixels, 3): a pixel's rays next to each other.
        directions = torch.stack([d[order] for _, d in rays], dim=1).reshape(-1, 3).contiguous()
        colours = march_grid_view(field, models, origin, directions, supports).clamp(0.0, 1.0)
        colours = colours.numpy().reshape(len(models), -1, len(points))
        for sample in range(len(points)):  # summed in the same order as the images below
            total[:, order] += colours[:, :, sample]
    else:
        for point in points:
            images = render_view_under(field, cameras, index, models, supports, device, subpixel=point)
            total += images.cpu().numpy().reshape(len(models), -1)
    return (total / (factor * factor)).astype(np.float32).reshape(len(models), cameras.height, cameras.width)
