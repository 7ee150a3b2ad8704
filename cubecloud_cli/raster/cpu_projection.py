"""EWA projection as numba kernels, forward and hand-written backward, parallel over Gaussians.

The same arithmetic as :func:`cubecloud_cli.raster.projection.project` (which stays the readable
reference and the path on other devices), in float64. Autograd through the PyTorch version costs
about 8 ms for 50k Gaussians on two cores, more than compositing a 128² view; the kernels take
well under a millisecond. The backward reproduces autograd's choices at the guards: no gradient
through a clamped x/z or y/z, through the depth of a culled Gaussian, through a clamped
determinant, or through a Mip-filter compensation at its floor.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from cubecloud_cli.jit import PRANGE_ONLY
from cubecloud_cli.raster.constants import (
    EIGENVALUE_FLOOR,
    FRUSTUM_CLAMP,
    MIN_COMPENSATION,
    MIN_DETERMINANT,
    MIN_QUATERNION_NORM,
)


@njit(cache=True)
def _rotation(qw, qx, qy, qz):
    return (
        1 - 2 * (qy * qy + qz * qz),
        2 * (qx * qy - qw * qz),
        2 * (qx * qz + qw * qy),
        2 * (qx * qy + qw * qz),
        1 - 2 * (qx * qx + qz * qz),
        2 * (qy * qz - qw * qx),
        2 * (qx * qz - qw * qy),
        2 * (qy * qz + qw * qx),
        1 - 2 * (qx * qx + qy * qy),
    )


@njit(cache=True)
def _unit_quaternion(quaternions, i):
    norm = math.sqrt(quaternions[i, 0] ** 2 + quaternions[i, 1] ** 2 + quaternions[i, 2] ** 2 + quaternions[i, 3] ** 2)
    scale = max(norm, MIN_QUATERNION_NORM)
    return (
        quaternions[i, 0] / scale,
        quaternions[i, 1] / scale,
        quaternions[i, 2] / scale,
        quaternions[i, 3] / scale,
        norm,
    )


@njit(cache=True)
def _camera(means, i, rotation, translation):
    cx = rotation[0, 0] * means[i, 0] + rotation[0, 1] * means[i, 1] + rotation[0, 2] * means[i, 2] + translation[0]
    cy = rotation[1, 0] * means[i, 0] + rotation[1, 1] * means[i, 1] + rotation[1, 2] * means[i, 2] + translation[1]
    cz = rotation[2, 0] * means[i, 0] + rotation[2, 1] * means[i, 1] + rotation[2, 2] * means[i, 2] + translation[2]
    return cx, cy, cz


@njit(cache=True)
def _footprint(rotation, s0, s1, s2, r, x_over_z, y_over_z, f_over_z):
    """T's rows t0, t1 (T = J·W, the image Jacobian times the camera rotation) and the footprint
    rows u0, u1 with u_j = (T r_j) s_j, r_j the Gaussian's j-th axis; all as tuples, because
    small arrays would be allocated per Gaussian."""
    t0 = (
        f_over_z * (rotation[0, 0] - x_over_z * rotation[2, 0]),
        f_over_z * (rotation[0, 1] - x_over_z * rotation[2, 1]),
        f_over_z * (rotation[0, 2] - x_over_z * rotation[2, 2]),
    )
    t1 = (
        f_over_z * (rotation[1, 0] - y_over_z * rotation[2, 0]),
        f_over_z * (rotation[1, 1] - y_over_z * rotation[2, 1]),
        f_over_z * (rotation[1, 2] - y_over_z * rotation[2, 2]),
    )
    u0 = (
        (t0[0] * r[0] + t0[1] * r[3] + t0[2] * r[6]) * s0,
        (t0[0] * r[1] + t0[1] * r[4] + t0[2] * r[7]) * s1,
        (t0[0] * r[2] + t0[1] * r[5] + t0[2] * r[8]) * s2,
    )
    u1 = (
        (t1[0] * r[0] + t1[1] * r[3] + t1[2] * r[6]) * s0,
        (t1[0] * r[1] + t1[1] * r[4] + t1[2] * r[7]) * s1,
        (t1[0] * r[2] + t1[1] * r[5] + t1[2] * r[8]) * s2,
    )
    return t0, t1, u0, u1


@njit(cache=True)
def _compensation_ratio(a, b, c, variance):
    """ρ² before its floor, det Σ₂ / det(Σ₂ + vI) = 1 − deficit, for the undilated footprint
    (a, b, c); the deficit (v(a + c) + v²) / det(Σ₂ + vI); and det(Σ₂ + vI), clamped away from 0.
    Written as ``projection.project`` writes it, so that both keep their digits when ρ ≈ 1."""
    blurred = max((a + variance) * (c + variance) - b * b, MIN_DETERMINANT)
    deficit = (variance * (a + c) + variance * variance) / blurred
    return 1.0 - deficit, deficit, blurred


@njit(parallel=PRANGE_ONLY, cache=True)
def project_forward(means, scales, quaternions, rotation, translation, focal, width, height, near, variance, antialias):
    """means2d (N, 2), conics (N, 3), covariances2d (N, 3), depths (N,), radii (N,) and the Mip
    filter's opacity factors (N,) (ones without ``antialias``) as ``project``; ``variance`` is the
    px² added to every footprint."""
    count = means.shape[0]
    real = means.dtype  # computed in float64, stored in the inputs' type: no conversion after
    means2d = np.empty((count, 2), dtype=real)
    conics = np.empty((count, 3), dtype=real)
    covariances2d = np.empty((count, 3), dtype=real)
    depths = np.empty(count, dtype=real)
    radii = np.zeros(count, dtype=np.int64)
    compensations = np.ones(count, dtype=real)
    limit_x = FRUSTUM_CLAMP * (width / 2.0) / focal
    limit_y = FRUSTUM_CLAMP * (height / 2.0) / focal
    for i in prange(count):
        cx, cy, depth = _camera(means, i, rotation, translation)
        depths[i] = depth
        in_front = depth > near
        z = depth if in_front else 1.0
        x_over_z = min(max(cx / z, -limit_x), limit_x)
        y_over_z = min(max(cy / z, -limit_y), limit_y)
        qw, qx, qy, qz, _ = _unit_quaternion(quaternions, i)
        r = _rotation(qw, qx, qy, qz)
        _, _, u0, u1 = _footprint(rotation, scales[i, 0], scales[i, 1], scales[i, 2], r, x_over_z, y_over_z, focal / z)
        a = u0[0] * u0[0] + u0[1] * u0[1] + u0[2] * u0[2]
        b = u0[0] * u1[0] + u0[1] * u1[1] + u0[2] * u1[2]
        c = u1[0] * u1[0] + u1[1] * u1[1] + u1[2] * u1[2]
        if antialias:
            ratio, _, _ = _compensation_ratio(a, b, c, variance)
            compensations[i] = math.sqrt(max(ratio, MIN_COMPENSATION * MIN_COMPENSATION))
        a += variance
        c += variance
        determinant = max(a * c - b * b, MIN_DETERMINANT)
        conic_a, conic_b, conic_c = c / determinant, -b / determinant, a / determinant
        conics[i, 0], conics[i, 1], conics[i, 2] = conic_a, conic_b, conic_c
        covariances2d[i, 0], covariances2d[i, 1], covariances2d[i, 2] = a, b, c
        u = focal * cx / z + width / 2.0
        v = focal * cy / z + height / 2.0
        means2d[i, 0], means2d[i, 1] = u, v
        middle = 0.5 * (a + c)
        largest = middle + math.sqrt(max(middle * middle - determinant, EIGENVALUE_FLOOR))
        finite = (
            np.isfinite(u)
            and np.isfinite(v)
            and np.isfinite(conic_a)
            and np.isfinite(conic_b)
            and np.isfinite(conic_c)
            and np.isfinite(largest)
            and largest < 1e36
        )  # ceil(3√λ) stays within int64
        if not (in_front and finite):
            continue  # tested before ceil: converting an infinite radius to an integer is undefined
        radius = math.ceil(3.0 * math.sqrt(largest))
        if u + radius > 0 and u - radius < width and v + radius > 0 and v - radius < height:
            radii[i] = np.int64(radius)
    return means2d, conics, covariances2d, depths, radii, compensations


@njit(parallel=PRANGE_ONLY, cache=True)
def project_backward(
    means,
    scales,
    quaternions,
    rotation,
    translation,
    focal,
    width,
    height,
    near,
    variance,
    antialias,
    grad_means2d,
    grad_conics,
    grad_compensations,
):
    """Gradients with respect to means (N, 3), scales (N, 3) and quaternions (N, 4). Gaussians
    whose incoming gradients are all zero are skipped: in a dense scene, many are.

    One body on purpose: it is the chain rule of ``projection.project`` written out step by step
    in the forward pass's order, checked against autograd in tests/test_raster_cpu.py; split up,
    one derivation would be scattered over functions passing a dozen partials around."""
    count = means.shape[0]
    real = means.dtype  # as the forward: float64 arithmetic, stored in the inputs' type
    grad_means = np.zeros((count, 3), dtype=real)
    grad_scales = np.zeros((count, 3), dtype=real)
    grad_quaternions = np.zeros((count, 4), dtype=real)
    limit_x = FRUSTUM_CLAMP * (width / 2.0) / focal
    limit_y = FRUSTUM_CLAMP * (height / 2.0) / focal
    for i in prange(count):
        g_compensation = grad_compensations[i] if antialias else 0.0
        if (
            grad_means2d[i, 0] == 0.0
            and grad_means2d[i, 1] == 0.0
            and grad_conics[i, 0] == 0.0
            and grad_conics[i, 1] == 0.0
            and grad_conics[i, 2] == 0.0
            and g_compensation == 0.0
        ):
            continue  # culled, hidden or off screen: nothing to propagate (and no 0·∞ to make NaN)
        cx, cy, depth = _camera(means, i, rotation, translation)
        in_front = depth > near
        z = depth if in_front else 1.0
        raw_x, raw_y = cx / z, cy / z
        x_over_z = min(max(raw_x, -limit_x), limit_x)
        y_over_z = min(max(raw_y, -limit_y), limit_y)
        f_over_z = focal / z
        qw, qx, qy, qz, norm = _unit_quaternion(quaternions, i)
        r = _rotation(qw, qx, qy, qz)
        s = (scales[i, 0], scales[i, 1], scales[i, 2])
        t0, t1, u0, u1 = _footprint(rotation, s[0], s[1], s[2], r, x_over_z, y_over_z, f_over_z)
        a0 = u0[0] * u0[0] + u0[1] * u0[1] + u0[2] * u0[2]
        b = u0[0] * u1[0] + u0[1] * u1[1] + u0[2] * u1[2]
        c0 = u1[0] * u1[0] + u1[1] * u1[1] + u1[2] * u1[2]
        a, c = a0 + variance, c0 + variance
        raw_determinant = a * c - b * b
        determinant = max(raw_determinant, MIN_DETERMINANT)
        # conics = (c, −b, a) / det
        g_conic_a, g_conic_b, g_conic_c = grad_conics[i, 0], grad_conics[i, 1], grad_conics[i, 2]
        g_det = -(g_conic_a * c - g_conic_b * b + g_conic_c * a) / (determinant * determinant)
        if raw_determinant < MIN_DETERMINANT:
            g_det = 0.0
        g_a = g_conic_c / determinant + g_det * c
        g_b = -g_conic_b / determinant - 2.0 * g_det * b
        g_c = g_conic_a / determinant + g_det * a
        if g_compensation != 0.0:
            ratio, deficit, blurred = _compensation_ratio(a0, b, c0, variance)
            if ratio > MIN_COMPENSATION * MIN_COMPENSATION:  # at the floor ρ is constant
                # ρ = √(1 − deficit), deficit = (v(a0 + c0) + v²) / blurred, blurred = a·c − b²:
                # d deficit / d a0 = (v − deficit·c) / blurred, likewise for c0; / d b = 2b·deficit / blurred.
                g_deficit = -g_compensation / (2.0 * math.sqrt(ratio) * blurred)
                g_a += g_deficit * (variance - deficit * c)
                g_c += g_deficit * (variance - deficit * a)
                g_b += g_deficit * 2.0 * b * deficit
        g_u0 = (2.0 * g_a * u0[0] + g_b * u1[0], 2.0 * g_a * u0[1] + g_b * u1[1], 2.0 * g_a * u0[2] + g_b * u1[2])
        g_u1 = (g_b * u0[0] + 2.0 * g_c * u1[0], g_b * u0[1] + 2.0 * g_c * u1[1], g_b * u0[2] + 2.0 * g_c * u1[2])
        for j in range(3):
            grad_scales[i, j] = g_u0[j] * (t0[0] * r[j] + t0[1] * r[3 + j] + t0[2] * r[6 + j]) + g_u1[j] * (
                t1[0] * r[j] + t1[1] * r[3 + j] + t1[2] * r[6 + j]
            )
        # u_j = (T r_j) s_j: gradients of T's rows and of the rotation matrix R(q) (row-major)
        w0, w1, w2 = g_u0[0] * s[0], g_u0[1] * s[1], g_u0[2] * s[2]
        v0, v1, v2 = g_u1[0] * s[0], g_u1[1] * s[1], g_u1[2] * s[2]
        g_t0 = (w0 * r[0] + w1 * r[1] + w2 * r[2], w0 * r[3] + w1 * r[4] + w2 * r[5], w0 * r[6] + w1 * r[7] + w2 * r[8])
        g_t1 = (v0 * r[0] + v1 * r[1] + v2 * r[2], v0 * r[3] + v1 * r[4] + v2 * r[5], v0 * r[6] + v1 * r[7] + v2 * r[8])
        g_r = (
            w0 * t0[0] + v0 * t1[0],
            w1 * t0[0] + v1 * t1[0],
            w2 * t0[0] + v2 * t1[0],
            w0 * t0[1] + v0 * t1[1],
            w1 * t0[1] + v1 * t1[1],
            w2 * t0[1] + v2 * t1[1],
            w0 * t0[2] + v0 * t1[2],
            w1 * t0[2] + v1 * t1[2],
            w2 * t0[2] + v2 * t1[2],
        )
        # rotation matrix entries → unit quaternion
        g_w = 2 * (-qz * g_r[1] + qy * g_r[2] + qz * g_r[3] - qx * g_r[5] - qy * g_r[6] + qx * g_r[7])
        g_x = 2 * (
            qy * g_r[1]
            + qz * g_r[2]
            + qy * g_r[3]
            - 2 * qx * g_r[4]
            - qw * g_r[5]
            + qz * g_r[6]
            + qw * g_r[7]
            - 2 * qx * g_r[8]
        )
        g_y = 2 * (
            -2 * qy * g_r[0]
            + qx * g_r[1]
            + qw * g_r[2]
            + qx * g_r[3]
            + qz * g_r[5]
            - qw * g_r[6]
            + qz * g_r[7]
            - 2 * qy * g_r[8]
        )
        g_z = 2 * (
            -2 * qz * g_r[0]
            - qw * g_r[1]
            + qx * g_r[2]
            + qw * g_r[3]
            - 2 * qz * g_r[4]
            + qy * g_r[5]
            + qx * g_r[6]
            + qy * g_r[7]
        )
        if norm >= MIN_QUATERNION_NORM:  # q / |q|: remove the radial part, divide by |q|
            radial = g_w * qw + g_x * qx + g_y * qy + g_z * qz
            g_w, g_x, g_y, g_z = g_w - radial * qw, g_x - radial * qx, g_y - radial * qy, g_z - radial * qz
        scale = max(norm, MIN_QUATERNION_NORM)
        grad_quaternions[i, 0], grad_quaternions[i, 1] = g_w / scale, g_x / scale
        grad_quaternions[i, 2], grad_quaternions[i, 3] = g_y / scale, g_z / scale
        # T rows: t0 = f/z (w0 − x/z w2), t1 = f/z (w1 − y/z w2)
        g_f_over_z = 0.0
        g_x_over_z = 0.0
        g_y_over_z = 0.0
        for k in range(3):
            g_f_over_z += g_t0[k] * (rotation[0, k] - x_over_z * rotation[2, k])
            g_f_over_z += g_t1[k] * (rotation[1, k] - y_over_z * rotation[2, k])
            g_x_over_z -= f_over_z * g_t0[k] * rotation[2, k]
            g_y_over_z -= f_over_z * g_t1[k] * rotation[2, k]
        g_u, g_v = grad_means2d[i, 0], grad_means2d[i, 1]
        g_cx = focal / z * g_u
        g_cy = focal / z * g_v
        g_z = -focal / (z * z) * g_f_over_z - focal * (cx * g_u + cy * g_v) / (z * z)
        if -limit_x <= raw_x <= limit_x:
            g_cx += g_x_over_z / z
            g_z -= g_x_over_z * cx / (z * z)
        if -limit_y <= raw_y <= limit_y:
            g_cy += g_y_over_z / z
            g_z -= g_y_over_z * cy / (z * z)
        if not in_front:
            g_z = 0.0
        for k in range(3):
            grad_means[i, k] = rotation[0, k] * g_cx + rotation[1, k] * g_cy + rotation[2, k] * g_z
    return grad_means, grad_scales, grad_quaternions
