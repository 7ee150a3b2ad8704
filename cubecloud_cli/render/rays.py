"""Rays through pixel centres and where they cross an axis-aligned box."""

from __future__ import annotations

import functools

import numpy as np
import torch

from cubecloud_cli.cameras import PinholeCameras

# Direction components smaller than this are treated as parallel to the slab: 1/d would
# overflow to inf and inf·0 gives NaN at the slab faces.
PARALLEL = 1e-12
# Rays per side of a tile when a march takes an image's rays tile by tile: neighbours pass the
# same voxels one after another, so they are still in the cache. A 512² view of a 512³ CT took
# 1.6 s in tiles of 8, 1.7 s of 4, 2.1 s of 16 and 2.7 s in rows (two cores).
RAY_TILE = 8


def camera_rays(
    cameras: PinholeCameras, index: int, device: torch.device, subpixel: tuple[float, float] = (0.5, 0.5)
) -> tuple[torch.Tensor, torch.Tensor]:
    """The camera centre (3,) shared by all rays of view ``index``, and the rays' unit
    directions (H·W, 3) through the pixel centres (or another ``subpixel`` point), pixels in
    row-major (v, u) order."""
    directions = torch.as_tensor(cameras.pixel_directions(index, subpixel), dtype=torch.float32, device=device)
    origin = torch.as_tensor(cameras.centres()[index], dtype=torch.float32, device=device)
    return origin, directions


def ray_box(
    origins: torch.Tensor, directions: torch.Tensor, low: torch.Tensor, high: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry and exit distances of rays through the box [low, high] (slab method); ``origins``
    is (P, 3) or one (3,) origin for all rays.

    Rays that miss get ``near >= far``; ``near`` is clamped at 0 so nothing behind the camera
    counts.
    """
    safe = torch.where(directions.abs() < PARALLEL, torch.full_like(directions, PARALLEL), directions)
    inverse = 1.0 / safe
    t_low = (low - origins) * inverse
    t_high = (high - origins) * inverse
    near = torch.minimum(t_low, t_high).amax(dim=1).clamp_min(0.0)
    far = torch.maximum(t_low, t_high).amin(dim=1)
    return near, far


@functools.lru_cache(maxsize=8)
def tiled_order(height: int, width: int, tile: int = RAY_TILE) -> np.ndarray:
    """The row-major pixel indices of an image listed tile by tile (tiles row-major, pixels in a
    tile row-major); edge tiles are cut to the image. Made once per image size and shared by
    every view of an export, so callers only index with it."""
    v, u = np.divmod(np.arange(height * width), width)
    tiles_across = -(-width // tile)
    key = (v // tile * tiles_across + u // tile) * tile * tile + (v % tile) * tile + u % tile
    return np.argsort(key, kind="stable")
