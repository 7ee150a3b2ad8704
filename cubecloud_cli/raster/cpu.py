"""The numba kernels as a torch autograd function: projection stays in torch, compositing runs
in ``cpu_kernels``."""

from __future__ import annotations

import numpy as np
import torch

from cubecloud_cli.raster import cpu_kernels as kernels
from cubecloud_cli.raster.pairs import pixel_bounds
from cubecloud_cli.raster.projection import Projected


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(tensor.detach().cpu().numpy().astype(np.float64, copy=False))


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colours, opacities, background, bounds, depths, width, height):
        tiles_x, tiles_y = -(-width // kernels.TILE), -(-height // kernels.TILE)
        bounds_np = bounds.cpu().numpy()
        candidates = np.flatnonzero((bounds_np[:, 1] >= bounds_np[:, 0]) & (bounds_np[:, 3] >= bounds_np[:, 2]))
        offsets, entries = kernels.bin_tiles(candidates, bounds_np, _numpy(depths), tiles_x, tiles_y)
        arrays = (bounds_np, _numpy(means2d), _numpy(conics), _numpy(colours), _numpy(opacities), _numpy(background))
        image, final_transmittance, last = kernels.forward(offsets, entries, *arrays, width, height, tiles_x)
        ctx.saved = (offsets, entries, arrays, final_transmittance, last, width, height, tiles_x)
        ctx.count = means2d.shape[0]
        dtype, device = colours.dtype, colours.device
        coverage = torch.from_numpy(1.0 - final_transmittance).to(dtype=dtype, device=device)
        ctx.mark_non_differentiable(coverage)
        return torch.from_numpy(image).to(dtype=dtype, device=device).view(height, width, -1), coverage.view(height, width)

    @staticmethod
    def backward(ctx, grad_image, grad_coverage):
        offsets, entries, arrays, final_transmittance, last, width, height, tiles_x = ctx.saved
        grad = _numpy(grad_image.reshape(height * width, -1))
        slots = kernels.backward(offsets, entries, *arrays, width, height, tiles_x, final_transmittance, last, grad)
        per_gaussian = torch.from_numpy(kernels.sum_per_gaussian(entries, slots, ctx.count))
        dtype, device = grad_image.dtype, grad_image.device
        per_gaussian = per_gaussian.to(dtype=dtype, device=device)
        return per_gaussian[:, 0:2], per_gaussian[:, 2:5], per_gaussian[:, 6:], per_gaussian[:, 5], None, None, None, None, None


def composite_cpu(
    projected: Projected,
    colours: torch.Tensor,
    opacities: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`cubecloud_cli.raster.pairs.composite` computed by the numba kernels."""
    if background is None:
        background = torch.zeros(colours.shape[1], dtype=colours.dtype)
    bounds = pixel_bounds(projected, width, height, opacities)
    return _Composite.apply(projected.means2d, projected.conics, colours, opacities, background, bounds,
                            projected.depths.detach(), width, height)
