"""The numba kernels as torch autograd functions: projection runs in ``projection_kernels``,
compositing in ``compositing``."""

from __future__ import annotations

import numpy as np
import torch

from cubecloud_cli.raster.constants import NEAR_PLANE, TILE
from cubecloud_cli.raster.cpu import binning, compositing, projection_kernels
from cubecloud_cli.raster.projection import Projected, dilation


def _numpy(tensor: torch.Tensor) -> np.ndarray:
    """A contiguous float32 or float64 array (the kernels composite in the precision of the
    conics). numba compiles a kernel once per dtype and layout, for 5–12 s each: a strided
    gradient slice or a broadcast gradient would compile a second copy of a kernel that training
    has compiled already, so they are copied instead (a few MB at most, where training's tensors,
    contiguous already, are not copied at all)."""
    array = tensor.detach().cpu().numpy()
    if array.dtype not in (np.float32, np.float64):
        array = array.astype(np.float32 if array.dtype.itemsize < 4 else np.float64)
    return array if array.flags.c_contiguous else array.copy(order="C")


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, scales, quaternions, rotation, translation, focal, width, height, near, antialias):
        inputs = (_numpy(means), _numpy(scales), _numpy(quaternions), _numpy(rotation), _numpy(translation))
        options = (focal, width, height, near, dilation(antialias), antialias)
        outputs = projection_kernels.project_forward(*inputs, *options)
        ctx.saved = (inputs, options)
        dtype = means.dtype
        means2d, conics, covariances2d, depths = (torch.from_numpy(a).to(dtype) for a in outputs[:4])
        radii = torch.from_numpy(outputs[4])
        compensations = torch.from_numpy(outputs[5]).to(dtype)
        ctx.mark_non_differentiable(covariances2d, depths, radii)
        if not antialias:
            ctx.mark_non_differentiable(compensations)
        return means2d, conics, covariances2d, depths, radii, compensations

    @staticmethod
    def backward(ctx, grad_means2d, grad_conics, _covariances, _depths, _radii, grad_compensations):
        inputs, options = ctx.saved
        if grad_compensations is None:
            grad_compensations = torch.zeros(inputs[0].shape[0], dtype=grad_means2d.dtype)
        grads = projection_kernels.project_backward(
            *inputs, *options, _numpy(grad_means2d), _numpy(grad_conics), _numpy(grad_compensations)
        )
        dtype = grad_means2d.dtype
        return (*(torch.from_numpy(g).to(dtype) for g in grads), None, None, None, None, None, None, None)


def project_cpu(
    means: torch.Tensor,
    scales: torch.Tensor,
    quaternions: torch.Tensor,
    rotation: torch.Tensor,
    translation: torch.Tensor,
    focal: float,
    width: int,
    height: int,
    near: float = NEAR_PLANE,
    antialias: bool = False,
) -> Projected:
    """:func:`cubecloud_cli.raster.projection.project` computed by the numba kernels (CPU
    tensors; the pose takes no gradient)."""
    means2d, conics, covariances2d, depths, radii, compensations = _Project.apply(
        means,
        scales,
        quaternions,
        rotation.detach(),
        translation.detach(),
        float(focal),
        int(width),
        int(height),
        float(near),
        bool(antialias),
    )
    return Projected(
        means2d=means2d,
        conics=conics,
        depths=depths,
        radii=radii,
        covariances2d=covariances2d,
        compensations=compensations if antialias else None,
    )


def kernel_inputs(means2d, conics, colours, opacities, background, covariances2d, radii, depths, width, height):
    """What the compositing kernels take for one view: the tile lists (CSR offsets, entries), the
    per-Gaussian arrays (pixel boxes, means, conics, colours, opacities, α levels, background) and
    the tile count across. Also what ``bench/kernels_ab.py`` times the kernels on."""
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    means2d_np, opacities_np = _numpy(means2d), _numpy(opacities)
    bounds, levels = binning.splat_boxes(
        means2d_np, _numpy(covariances2d), radii.cpu().numpy(), opacities_np, width, height
    )
    offsets, entries = binning.bin_tiles(bounds, _numpy(depths), tiles_x, tiles_y)
    arrays = (bounds, means2d_np, _numpy(conics), _numpy(colours), opacities_np, levels, _numpy(background))
    return offsets, entries, arrays, tiles_x


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colours, opacities, background, covariances2d, radii, depths, width, height):
        offsets, entries, arrays, tiles_x = kernel_inputs(
            means2d, conics, colours, opacities, background, covariances2d, radii, depths, width, height
        )
        image, final_transmittance, *blended = compositing.forward(offsets, entries, *arrays, width, height, tiles_x)
        ctx.saved = (
            offsets,
            entries,
            arrays,
            final_transmittance,
            blended,
            width,
            height,
            tiles_x,
        )
        ctx.count = means2d.shape[0]
        dtype, device = colours.dtype, colours.device
        coverage = torch.from_numpy(1.0 - final_transmittance).to(dtype=dtype, device=device)
        ctx.mark_non_differentiable(coverage)
        return torch.from_numpy(image).to(dtype=dtype, device=device).view(height, width, -1), coverage.view(
            height, width
        )

    @staticmethod
    def backward(ctx, grad_image, grad_coverage):
        offsets, entries, arrays, final_transmittance, blended, width, height, tiles_x = ctx.saved
        grad = _numpy(grad_image.reshape(height * width, -1)).astype(arrays[2].dtype, copy=False)
        row_grads, gaussian_rows = compositing.backward(
            offsets, entries, *arrays, width, height, tiles_x, final_transmittance, *blended, grad
        )
        dtype, device = grad_image.dtype, grad_image.device
        real = np.float64 if dtype == torch.float64 else np.float32
        count, channels = ctx.count, row_grads.shape[1] - 6
        # contiguous: the projection's backward reads the first two as they are, uncopied
        grads = [np.empty(shape, real) for shape in ((count, 2), (count, 3), count, (count, channels))]
        binning.sum_per_gaussian(row_grads, gaussian_rows, *grads)
        means2d_grad, conics_grad, opacities_grad, colours_grad = (
            torch.from_numpy(g).to(dtype=dtype, device=device) for g in grads
        )
        return (
            means2d_grad,
            conics_grad,
            colours_grad,
            opacities_grad,
            None,
            None,
            None,
            None,
            None,
            None,
        )


def composite_cpu(
    projected: Projected,
    colours: torch.Tensor,
    opacities: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`cubecloud_cli.raster.pairs.composite` computed by the numba compositing."""
    if background is None:
        background = torch.zeros(colours.shape[1], dtype=colours.dtype)
    return _Composite.apply(
        projected.means2d,
        projected.conics,
        colours,
        opacities,
        background,
        projected.covariances2d.detach(),
        projected.radii,
        projected.depths.detach(),
        width,
        height,
    )
