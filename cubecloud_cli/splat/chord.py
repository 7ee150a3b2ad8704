"""How much of a Gaussian a ray meets: its chord along the ray against a round Gaussian's.

Volume rendering integrates a Gaussian kernel's density along the ray. Through the centre, in
unit direction d, that integral is the chord sqrt(2π / dᵀΣ⁻¹d), with Σ = R S² Rᵀ: long for a ray
along an elongated Gaussian, short across a flat one. A scalar Gaussian's optical length ℓ is
scaled by the ratio of its chord to that of a round Gaussian of the same volume (scales the
geometric mean g = (s₁s₂s₃)^⅓), which depends only on the direction:

    r(d) = 1 / (g · ‖S⁻¹Rᵀd‖),    log r = −½ log Σⱼ (Rᵀd)ⱼ² / sⱼ² − mean log sⱼ,

1 for a round Gaussian, and its mean of log r over the sphere is 0 only then. The kernels take d
from the camera centre to each Gaussian's centre (the centres are not moved by it). A Gaussian
at the camera centre, a zero quaternion or a non-finite input gets r = 1, and log r is clamped
to ±LOG_RATIO_LIMIT, where its gradient is 0.

`cubecloud view` and the shared page compute r for their camera when it rests. A viewer that
draws one opacity per Gaussian (a PLY in any other splat viewer) gets ``sphere_mean_log_ratio``:
the mean of log r over directions spread evenly over the sphere, which the cameras of an orbit
around the volume approach.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from cubecloud_cli.numerics.jit import PRANGE_ONLY
from cubecloud_cli.numerics.local_axes import local, raw_quaternion_gradient

# r between e^-12 and e^12: scales within LOG_SCALE_LIMIT of each other stay well inside.
LOG_RATIO_LIMIT = 12.0
# Directions for the sphere's mean: a Fibonacci lattice, even to about a degree's worth of r.
SPHERE_DIRECTIONS = 64


@njit(inline="always")
def _unit_direction_and_quaternion(means, quaternions, centre, i):
    """d from the camera to centre i and q, both of unit length; ok is False where either is 0 or not finite."""
    dx, dy, dz = means[i, 0] - centre[0], means[i, 1] - centre[1], means[i, 2] - centre[2]
    w, x, y, z = quaternions[i, 0], quaternions[i, 1], quaternions[i, 2], quaternions[i, 3]
    length_d = math.sqrt(dx * dx + dy * dy + dz * dz)
    length_q = math.sqrt(w * w + x * x + y * y + z * z)
    ok = 0.0 < length_d < math.inf and 0.0 < length_q < math.inf
    if ok:  # one division each (no fast-math in these kernels: numba/jit.py)
        inverse_d, inverse_q = 1.0 / length_d, 1.0 / length_q
        dx, dy, dz = dx * inverse_d, dy * inverse_d, dz * inverse_d
        w, x, y, z = w * inverse_q, x * inverse_q, y * inverse_q, z * inverse_q
    return ok, dx, dy, dz, w, x, y, z, length_q


@njit(inline="always")
def _log_ratio(l0, l1, l2, s0, s1, s2):
    """log r and dᵀΣ⁻¹d from the local direction and the scales; ok is False where it is undefined
    or clamped. One log: −½ log(dᵀΣ⁻¹d) − ⅓ log(s₀s₁s₂) = −⅙ log((dᵀΣ⁻¹d)³ (s₀s₁s₂)²), in float64."""
    volume = s0 * s1 * s2
    over_volume = 1.0 / volume
    a0, a1, a2 = l0 * s1 * s2 * over_volume, l1 * s0 * s2 * over_volume, l2 * s0 * s1 * over_volume
    inverse = a0 * a0 + a1 * a1 + a2 * a2
    product = inverse * inverse * inverse * volume * volume
    if not (0.0 < product < math.inf):
        return False, 0.0, inverse, a0, a1, a2
    value = -math.log(product) / 6.0
    if value >= LOG_RATIO_LIMIT:
        return False, LOG_RATIO_LIMIT, inverse, a0, a1, a2
    if value <= -LOG_RATIO_LIMIT:
        return False, -LOG_RATIO_LIMIT, inverse, a0, a1, a2
    return True, value, inverse, a0, a1, a2


@njit(inline="always")
def chord_terms(means, quaternions, centre, i, s0, s1, s2, with_jacobian):
    """log r of Gaussian i for the scales s0..s2 (float64), whether it is defined and unclamped,
    and with ``with_jacobian`` its derivatives by the four raw quaternion components and the three
    scales (0 where r is undefined or clamped). Inlined into ``_chord_forward`` and the scalar
    appearance kernel: after editing it, touch ``splat/scalar_appearance.py`` too (numba's cache
    checks only the file of the kernel it caches)."""
    ok, dx, dy, dz, w, x, y, z, length_q = _unit_direction_and_quaternion(means, quaternions, centre, i)
    if not ok:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    l0, l1, l2 = local(dx, dy, dz, w, x, y, z)
    inside, value, inverse, a0, a1, a2 = _log_ratio(l0, l1, l2, s0, s1, s2)
    if not (with_jacobian and inside):
        return inside, value, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0  # undefined or clamped: no gradient
    # ∂ log r / ∂sⱼ = (aⱼ² / dᵀΣ⁻¹d − ⅓) / sⱼ
    by_s0 = (a0 * a0 / inverse - 1.0 / 3.0) / s0
    by_s1 = (a1 * a1 / inverse - 1.0 / 3.0) / s1
    by_s2 = (a2 * a2 / inverse - 1.0 / 3.0) / s2
    # To l (∂ log r / ∂lⱼ = −aⱼ / (sⱼ dᵀΣ⁻¹d)), then to the raw quaternion.
    h0, h1, h2 = -a0 / (s0 * inverse), -a1 / (s1 * inverse), -a2 / (s2 * inverse)
    by_w, by_x, by_y, by_z = raw_quaternion_gradient(dx, dy, dz, h0, h1, h2, w, x, y, z, length_q)
    return True, value, by_w, by_x, by_y, by_z, by_s0, by_s1, by_s2


@njit(parallel=PRANGE_ONLY, cache=True)
def _chord_forward(means, quaternions, scales, centre, out, jacobian, with_jacobian) -> None:
    """out[i] = log r; with ``with_jacobian``, jacobian[i] = its derivatives by the four raw
    quaternion components and the three scales (0 where r is undefined or clamped), so that the
    backward pass is one product and nothing is computed twice."""
    for i in prange(means.shape[0]):
        s0, s1, s2 = float(scales[i, 0]), float(scales[i, 1]), float(scales[i, 2])
        _, value, by_w, by_x, by_y, by_z, by_s0, by_s1, by_s2 = chord_terms(
            means, quaternions, centre, i, s0, s1, s2, with_jacobian
        )
        out[i] = value
        if with_jacobian:
            jacobian[i, 0], jacobian[i, 1], jacobian[i, 2], jacobian[i, 3] = by_w, by_x, by_y, by_z
            jacobian[i, 4], jacobian[i, 5], jacobian[i, 6] = by_s0, by_s1, by_s2


class _ChordLogRatio(torch.autograd.Function):
    """log r per Gaussian by the kernel above, differentiable in the quaternions and scales."""

    @staticmethod
    def forward(ctx, means, quaternions, scales, centre):
        arrays = [np.ascontiguousarray(t.detach().numpy()) for t in (means, quaternions, scales, centre)]
        out = np.empty(means.shape[0], dtype=arrays[2].dtype)
        with_jacobian = bool(ctx.needs_input_grad[1] or ctx.needs_input_grad[2])
        jacobian = np.empty((means.shape[0] if with_jacobian else 0, 7), dtype=arrays[2].dtype)
        _chord_forward(*arrays, out, jacobian, with_jacobian)
        ctx.jacobian = torch.from_numpy(jacobian)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad_out):
        # A non-finite upstream gradient would turn the zeros of undefined rows into NaN.
        upstream = torch.nan_to_num(grad_out, nan=0.0, posinf=0.0, neginf=0.0)[:, None] * ctx.jacobian
        return None, upstream[:, :4], upstream[:, 4:], None


def chord_log_ratio_reference(
    means: torch.Tensor, quaternions: torch.Tensor, scales: torch.Tensor, centre: torch.Tensor
) -> torch.Tensor:
    """(N,) log r seen from ``centre``, in torch: the GPU's path and the kernels' oracle. Rows
    where r is undefined are computed on stand-ins (so that no NaN reaches a gradient) and give 0."""
    offset = means.detach() - centre
    norm_d = offset.norm(dim=1, keepdim=True)
    finite_q = torch.isfinite(quaternions).all(dim=1, keepdim=True)
    quaternions = torch.where(finite_q, quaternions, torch.ones_like(quaternions))  # no inf into norm's gradient
    norm_q = quaternions.norm(dim=1, keepdim=True)
    ok_d = (norm_d > 0) & torch.isfinite(norm_d)
    ok_q = finite_q & (norm_q > 0)
    ok_s = ((scales > 0) & torch.isfinite(scales)).all(dim=1, keepdim=True)
    d = torch.where(ok_d, offset / torch.where(ok_d, norm_d, torch.ones_like(norm_d)), torch.ones_like(offset))
    q = torch.where(
        ok_q, quaternions / torch.where(ok_q, norm_q, torch.ones_like(norm_q)), torch.ones_like(quaternions)
    )
    wide = torch.where(ok_s, scales, torch.ones_like(scales)).double()  # its cube may leave float32's range
    w, v = q[:, :1], -q[:, 1:]  # the conjugate rotates world directions into the Gaussian's axes
    t = 2.0 * torch.linalg.cross(v, d, dim=1)
    local = d + w * t + torch.linalg.cross(v, t, dim=1)
    product = (local.double() / wide).square().sum(dim=1) ** 3 * wide.prod(dim=1) ** 2
    valid = (ok_d & ok_q & ok_s)[:, 0] & (product > 0) & torch.isfinite(product)
    value = -torch.log(torch.where(valid, product, torch.ones_like(product))) / 6.0
    value = torch.where(valid, value, torch.zeros_like(value)).clamp(-LOG_RATIO_LIMIT, LOG_RATIO_LIMIT)
    return value.to(scales.dtype)


def chord_log_ratio(
    means: torch.Tensor, quaternions: torch.Tensor, scales: torch.Tensor, centre: torch.Tensor
) -> torch.Tensor:
    """(N,) log r of each Gaussian seen from ``centre`` (3,), differentiable in ``quaternions``
    and ``scales`` (as rendered, with the 3D filter); on a CPU one numba pass each way (torch
    took 10–16 ms a step for 50,000 Gaussians)."""
    if means.device.type != "cpu":
        return chord_log_ratio_reference(means, quaternions, scales, centre)
    dtype = scales.dtype
    return _ChordLogRatio.apply(means.detach().to(dtype), quaternions.to(dtype), scales, centre.to(dtype))


def sphere_directions(count: int = SPHERE_DIRECTIONS) -> np.ndarray:
    """(count, 3) unit directions spread evenly over the sphere (a Fibonacci lattice)."""
    index = np.arange(count) + 0.5
    polar = np.arccos(1.0 - 2.0 * index / count)
    azimuth = math.pi * (1.0 + math.sqrt(5.0)) * index
    return np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=1)


def sphere_mean_log_ratio(log_scales: torch.Tensor, chunk: int = 65_536) -> torch.Tensor:
    """(N,) the mean of log r over the sphere: what one fixed opacity per Gaussian can carry of r.
    A function of the scales alone (the rotation only turns the sphere)."""
    directions = torch.as_tensor(sphere_directions(), dtype=log_scales.dtype, device=log_scales.device)
    parts = []
    with torch.no_grad():
        for start in range(0, log_scales.shape[0], chunk):
            part = log_scales[start : start + chunk]
            inverse = (directions[None, :, :] * torch.exp(-part)[:, None, :]).square().sum(dim=2)
            mean = -0.5 * torch.log(inverse.clamp_min(1e-30)).mean(dim=1) - part.mean(dim=1)
            parts.append(mean.clamp(-LOG_RATIO_LIMIT, LOG_RATIO_LIMIT))
    return torch.cat(parts) if parts else log_scales.new_zeros(0)
