"""How much the scan changes across a scalar Gaussian: what its one value cannot show.

A scalar Gaussian carries one value, held to the scan's at its centre (``--value-anchor``). Where
the scan changes across the Gaussian's footprint (an edge, a thin shell of bone), a held-out
transfer function that shows a narrow band of values shows the whole Gaussian or none of it, where
the volume shows only the part of it inside the band. With the scan linear across the footprint,
its value at a point drawn from the Gaussian N(μ, Σ) has variance

    gᵀΣg = Σⱼ sⱼ² (rⱼ · g)²,    Σ = R S² Rᵀ,

for the scan's gradient g at the centre and the Gaussian's axes rⱼ (the columns of R) and scales
sⱼ: the expected squared gap, beyond the centre's, between the Gaussian's value and the scan's
over its footprint. ``--value-spread`` adds its mean over the Gaussians to a scalar scene's loss,
which makes Gaussians thin across edges and leaves them free along them and where the scan is flat.

The gradient is read by ``numerics/trilinear.sample_cube_gradient_into`` (central differences
over two voxels of the trilinear scan; over one, held-out scores were 0.4–1 dB lower) with the
scan's values at the centres, and as often. Rows with a zero or non-finite quaternion or scale,
or a non-finite gradient or spread, give 0 and no gradient.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from numba import njit, prange

from cubecloud_cli.numerics.jit import PRANGE_ONLY
from cubecloud_cli.numerics.local_axes import local, raw_quaternion_gradient
from cubecloud_cli.numerics.trilinear import sample_cube_gradient_into


@njit(parallel=PRANGE_ONLY, cache=True)
def _spread_forward(quaternions, variances, gradients, out, by_quaternion, by_log_scale, weight, with_gradient) -> None:
    """out[i] = gᵀΣg from the squared scales ``variances``, in float64 arithmetic; with
    ``with_gradient``, ``weight`` times its derivatives by the four raw quaternion components and
    the three log scales (the loss's mean passes 1 / N), so that the backward pass is one product
    and nothing is computed twice."""
    for i in prange(quaternions.shape[0]):
        out[i] = 0.0
        if with_gradient:
            for k in range(4):
                by_quaternion[i, k] = 0.0
            for k in range(3):
                by_log_scale[i, k] = 0.0
        w, x, y, z = (
            float(quaternions[i, 0]),
            float(quaternions[i, 1]),
            float(quaternions[i, 2]),
            float(quaternions[i, 3]),
        )
        gx, gy, gz = float(gradients[i, 0]), float(gradients[i, 1]), float(gradients[i, 2])
        length_q = math.sqrt(w * w + x * x + y * y + z * z)
        if not (0.0 < length_q < math.inf and math.isfinite(gx + gy + gz)):
            continue
        inverse_q = 1.0 / length_q
        w, x, y, z = w * inverse_q, x * inverse_q, y * inverse_q, z * inverse_q
        l0, l1, l2 = local(gx, gy, gz, w, x, y, z)
        v0, v1, v2 = float(variances[i, 0]), float(variances[i, 1]), float(variances[i, 2])
        spread = v0 * l0 * l0 + v1 * l1 * l1 + v2 * l2 * l2
        if not (math.isfinite(spread) and spread < 3.0e38):  # past float32: no value, no gradient
            continue
        out[i] = spread
        if not with_gradient:
            continue
        by_log_scale[i, 0] = weight * 2.0 * v0 * l0 * l0
        by_log_scale[i, 1] = weight * 2.0 * v1 * l1 * l1
        by_log_scale[i, 2] = weight * 2.0 * v2 * l2 * l2
        h0, h1, h2 = weight * 2.0 * v0 * l0, weight * 2.0 * v1 * l1, weight * 2.0 * v2 * l2
        by_quaternion[i, 0], by_quaternion[i, 1], by_quaternion[i, 2], by_quaternion[i, 3] = raw_quaternion_gradient(
            gx, gy, gz, h0, h1, h2, w, x, y, z, length_q
        )


def _run_kernel(quaternions, log_scales, gradients, weight: float, with_gradient: bool):
    # s² = exp(2 log s) by torch, vectorised (three exps a Gaussian were half the kernel's time);
    # one that overflows gives an infinite spread, a row the kernel leaves at 0.
    variances = torch.exp(2.0 * log_scales.detach())
    arrays = [np.ascontiguousarray(t.detach().numpy()) for t in (quaternions, variances, gradients)]
    count, dtype = quaternions.shape[0], arrays[1].dtype
    out = np.empty(count, dtype=dtype)
    rows = count if with_gradient else 0
    by_quaternion, by_log_scale = np.empty((rows, 4), dtype=dtype), np.empty((rows, 3), dtype=dtype)
    _spread_forward(*arrays, out, by_quaternion, by_log_scale, weight, with_gradient)
    return torch.from_numpy(out), torch.from_numpy(by_quaternion), torch.from_numpy(by_log_scale)


class _ValueSpread(torch.autograd.Function):
    """gᵀΣg by the kernel above, per Gaussian or (``mean``, the training loss) its mean, whose
    per-Gaussian derivatives the kernel writes already divided by N: the backward pass is then a
    product by one number (0.6 ms a step less at 50,000 Gaussians than a mean taken after)."""

    @staticmethod
    def forward(ctx, quaternions, log_scales, gradients, mean):
        with_gradient = bool(ctx.needs_input_grad[0] or ctx.needs_input_grad[1])
        weight = 1.0 / quaternions.shape[0] if mean else 1.0
        out, ctx.by_quaternion, ctx.by_log_scale = _run_kernel(
            quaternions, log_scales, gradients, weight, with_gradient
        )
        ctx.mean = mean
        return out.mean() if mean else out

    @staticmethod
    def backward(ctx, grad_out):
        # A non-finite upstream gradient would turn the zeros of undefined rows into NaN.
        upstream = torch.nan_to_num(grad_out, nan=0.0, posinf=0.0, neginf=0.0)
        upstream = upstream if ctx.mean else upstream[:, None]
        return upstream * ctx.by_quaternion, upstream * ctx.by_log_scale, None, None


def value_spread_reference(
    quaternions: torch.Tensor, log_scales: torch.Tensor, gradients: torch.Tensor
) -> torch.Tensor:
    """(N,) gᵀΣg in torch: the GPU's path and the kernel's oracle (rows it cannot compute give 0)."""
    finite_q = torch.isfinite(quaternions).all(dim=1, keepdim=True)
    quaternions = torch.where(finite_q, quaternions, torch.ones_like(quaternions))
    norm_q = quaternions.norm(dim=1, keepdim=True)
    ok_q = finite_q & (norm_q > 0)
    q = torch.where(
        ok_q, quaternions / torch.where(ok_q, norm_q, torch.ones_like(norm_q)), torch.ones_like(quaternions)
    )
    finite_g = torch.isfinite(gradients).all(dim=1, keepdim=True)
    g = torch.where(finite_g, gradients, torch.zeros_like(gradients)).double()
    w, v = q[:, :1].double(), -q[:, 1:].double()  # the conjugate turns world vectors into the Gaussian's axes
    t = 2.0 * torch.linalg.cross(v, g, dim=1)
    local_g = g + w * t + torch.linalg.cross(v, t, dim=1)
    # Stand-ins where a log scale is not finite or its square would overflow float64 (such a row
    # is past float32 and gives 0 either way), so that no NaN reaches a gradient.
    ok_s = (torch.isfinite(log_scales) & (log_scales < 300.0)).all(dim=1, keepdim=True)
    wide = torch.where(ok_s, log_scales, torch.zeros_like(log_scales)).double()
    spread = (torch.exp(2.0 * wide) * local_g.square()).sum(dim=1)
    valid = (ok_q & finite_g & ok_s)[:, 0] & torch.isfinite(spread) & (spread < 3.0e38)
    return torch.where(valid, spread, torch.zeros_like(spread)).to(log_scales.dtype)


def value_spread(quaternions: torch.Tensor, log_scales: torch.Tensor, gradients: torch.Tensor) -> torch.Tensor:
    """(N,) the scan's variance over each Gaussian, gᵀΣg for the scan's gradient ``gradients``
    (N, 3) at its centre; on a CPU one numba pass (in torch, a rotation per Gaussian and its
    gradient cost the chord ratio 10–16 ms a step at 50,000 Gaussians)."""
    if quaternions.device.type != "cpu":
        return value_spread_reference(quaternions, log_scales, gradients)
    dtype = log_scales.dtype
    return _ValueSpread.apply(quaternions.to(dtype), log_scales, gradients.detach().to(dtype), False)


def value_spread_loss(quaternions: torch.Tensor, log_scales: torch.Tensor, gradients: torch.Tensor) -> torch.Tensor:
    """The mean of :func:`value_spread` over the Gaussians; 0 for none."""
    if quaternions.shape[0] == 0:
        return log_scales.sum()
    if quaternions.device.type != "cpu":
        return value_spread_reference(quaternions, log_scales, gradients).mean()
    dtype = log_scales.dtype
    return _ValueSpread.apply(quaternions.to(dtype), log_scales, gradients.detach().to(dtype), True)


def scan_gradient_at(volume: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """(N, 3) the gradient of an (X, Y, Z) scan, in values per world unit, at world points (N, 3)
    of the cube [-1, 1]³ (as ``splat/losses.volume_at`` reads the values): differences of the
    trilinear scan one voxel either side of each point, over two voxels. Not differentiable."""
    points = points.detach()
    if volume.device.type == "cpu":
        grid = np.ascontiguousarray(volume.detach().numpy())
        out = np.empty((points.shape[0], 3), dtype=grid.dtype)
        sample_cube_gradient_into(grid, np.ascontiguousarray(points.to(volume.dtype).numpy()), out)
        return torch.from_numpy(out)
    return scan_gradient_reference(volume, points)


def scan_gradient_reference(volume: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """:func:`scan_gradient_at` by torch's ``grid_sample``: the GPU's path and the kernel's oracle."""
    points = points.detach()
    sizes = torch.tensor(volume.shape, dtype=volume.dtype, device=volume.device)
    steps = torch.diag(2.0 / sizes)  # one voxel along each axis, in world units
    points = points.to(volume.dtype)
    shifted = torch.cat(
        [points + steps[None, axis] for axis in range(3)] + [points - steps[None, axis] for axis in range(3)]
    )
    grid = shifted[:, [2, 1, 0]].reshape(1, -1, 1, 1, 3)  # grid_sample reads (W, H, D): z, y, x
    reads = F.grid_sample(volume[None, None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    reads = reads.reshape(6, -1)
    return ((reads[:3] - reads[3:]) * (0.25 * sizes)[:, None]).T
