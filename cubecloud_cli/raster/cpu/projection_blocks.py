"""The projection of one block of Gaussians held by column (one array row per parameter), forward
and backward: the per-Gaussian arithmetic of :mod:`cubecloud_cli.raster.cpu.projection_kernels`, whose
parallel kernels cut the Gaussians into blocks and call these.

Each is one flat loop over the block's columns with every test a select, no call (the helpers
inline) and no division check (``error_model="numpy"``; every divisor is clamped away from zero),
which LLVM computes four Gaussians at a time once ``cubecloud_cli.numerics.jit`` has raised its limit on
run-time alias checks.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

import cubecloud_cli.numerics.jit  # noqa: F401  (its LLVM setting, before these compile)
from cubecloud_cli.raster.constants import (
    EIGENVALUE_FLOOR,
    FRUSTUM_CLAMP,
    MIN_COMPENSATION,
    MIN_DETERMINANT,
    MIN_QUATERNION_NORM,
)


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always", error_model="numpy")
def _unit_quaternion(w, x, y, z):
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    inverse = 1.0 / max(norm, MIN_QUATERNION_NORM)
    return w * inverse, x * inverse, y * inverse, z * inverse, norm, inverse


@njit(cache=True, inline="always")
def _camera(x, y, z, rotation, translation):
    cx = rotation[0, 0] * x + rotation[0, 1] * y + rotation[0, 2] * z + translation[0]
    cy = rotation[1, 0] * x + rotation[1, 1] * y + rotation[1, 2] * z + translation[1]
    cz = rotation[2, 0] * x + rotation[2, 1] * y + rotation[2, 2] * z + translation[2]
    return cx, cy, cz


@njit(cache=True, inline="always")
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


@njit(cache=True, inline="always", error_model="numpy")
def _compensation_ratio(a, b, c, variance):
    """ρ² before its floor, det Σ₂ / det(Σ₂ + vI) = 1 − deficit, for the undilated footprint
    (a, b, c); the deficit (v(a + c) + v²) / det(Σ₂ + vI); and det(Σ₂ + vI), clamped away from 0.
    Written as ``projection.project`` writes it, so that both keep their digits when ρ ≈ 1."""
    blurred = max((a + variance) * (c + variance) - b * b, MIN_DETERMINANT)
    deficit = (variance * (a + c) + variance * variance) / blurred
    return 1.0 - deficit, deficit, blurred


@njit(cache=True, error_model="numpy")
def project_block(means, scales, quaternions, rotation, translation, focal, width, height, near, variance, antialias, results, radii):  # fmt: skip
    """``projection_kernels.project_forward`` for one block of Gaussians held by column (``means`` (3, n), ``scales``
    (3, n), ``quaternions`` (4, n)): u, v, the conic (3), the covariance (3), the depth and the
    compensation into the rows of ``results`` (10, n), and ``radii``. One flat loop without a
    branch, a call or a division check, so that LLVM computes four or eight Gaussians at a time;
    the tests that a branch would make are selects, and a culled Gaussian's values are computed
    and then discarded."""
    limit_x = FRUSTUM_CLAMP * (width / 2.0) / focal
    limit_y = FRUSTUM_CLAMP * (height / 2.0) / focal
    for i in range(means.shape[1]):
        cx, cy, depth = _camera(means[0, i], means[1, i], means[2, i], rotation, translation)
        in_front = depth > near
        z = depth if in_front else 1.0
        inverse_z = 1.0 / z  # one division where there were three: a vector division costs many multiplies
        x_over_z = min(max(cx * inverse_z, -limit_x), limit_x)
        y_over_z = min(max(cy * inverse_z, -limit_y), limit_y)
        qw, qx, qy, qz, _, _ = _unit_quaternion(
            quaternions[0, i], quaternions[1, i], quaternions[2, i], quaternions[3, i]
        )
        r = _rotation(qw, qx, qy, qz)
        _, _, u0, u1 = _footprint(
            rotation, scales[0, i], scales[1, i], scales[2, i], r, x_over_z, y_over_z, focal * inverse_z
        )
        a = u0[0] * u0[0] + u0[1] * u0[1] + u0[2] * u0[2]
        b = u0[0] * u1[0] + u0[1] * u1[1] + u0[2] * u1[2]
        c = u1[0] * u1[0] + u1[1] * u1[1] + u1[2] * u1[2]
        ratio, _, _ = _compensation_ratio(a, b, c, variance)
        results[9, i] = math.sqrt(max(ratio, MIN_COMPENSATION * MIN_COMPENSATION)) if antialias else 1.0
        a += variance
        c += variance
        determinant = max(a * c - b * b, MIN_DETERMINANT)
        inverse_determinant = 1.0 / determinant
        conic_a, conic_b, conic_c = c * inverse_determinant, -b * inverse_determinant, a * inverse_determinant
        u = focal * (cx * inverse_z) + width / 2.0
        v = focal * (cy * inverse_z) + height / 2.0
        results[0, i], results[1, i] = u, v
        results[2, i], results[3, i], results[4, i] = conic_a, conic_b, conic_c
        results[5, i], results[6, i], results[7, i] = a, b, c
        results[8, i] = depth
        middle = 0.5 * (a + c)
        largest = middle + math.sqrt(max(middle * middle - determinant, EIGENVALUE_FLOOR))
        finite = (
            np.isfinite(u)
            & np.isfinite(v)
            & np.isfinite(conic_a)
            & np.isfinite(conic_b)
            & np.isfinite(conic_c)
            & np.isfinite(largest)
            & (largest < 1e36)
        )  # ceil(3√λ) stays within int64
        kept = in_front & finite
        # tested before ceil: converting an infinite radius to an integer is undefined
        radius = math.ceil(3.0 * math.sqrt(largest if kept else 0.0))
        on_screen = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
        radii[i] = np.int64(radius) if kept & on_screen else 0


@njit(cache=True, error_model="numpy")
def project_block_backward(
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
    results,
):
    """``projection_kernels.project_backward`` for one block held by column (as ``project_block``; the incoming
    gradients too): the gradients of means (rows 0–2), scales (3–5) and quaternions (6–9) into
    ``results`` (10, n). The caller passes only Gaussians with an incoming gradient; the others
    keep zero gradients there (and make no 0·∞ here).

    One body on purpose: it is the chain rule of ``projection.project`` written out step by step
    in the forward pass's order, checked against autograd in tests/test_raster_cpu.py; split up,
    one derivation would be scattered over functions passing a dozen partials around. Every test
    is a select, as in the forward, so that the loop stays a vector loop."""
    limit_x = FRUSTUM_CLAMP * (width / 2.0) / focal
    limit_y = FRUSTUM_CLAMP * (height / 2.0) / focal
    for i in range(means.shape[1]):
        g_compensation = grad_compensations[i] if antialias else 0.0
        g_u, g_v = grad_means2d[0, i], grad_means2d[1, i]
        g_conic_a, g_conic_b, g_conic_c = grad_conics[0, i], grad_conics[1, i], grad_conics[2, i]
        cx, cy, depth = _camera(means[0, i], means[1, i], means[2, i], rotation, translation)
        in_front = depth > near
        z = depth if in_front else 1.0
        inverse_z = 1.0 / z  # z, the determinant and |q| are each divided by once, as in the forward
        raw_x, raw_y = cx * inverse_z, cy * inverse_z
        x_over_z = min(max(raw_x, -limit_x), limit_x)
        y_over_z = min(max(raw_y, -limit_y), limit_y)
        f_over_z = focal * inverse_z
        qw, qx, qy, qz, norm, inverse_norm = _unit_quaternion(
            quaternions[0, i], quaternions[1, i], quaternions[2, i], quaternions[3, i]
        )
        r = _rotation(qw, qx, qy, qz)
        s = (scales[0, i], scales[1, i], scales[2, i])
        t0, t1, u0, u1 = _footprint(rotation, s[0], s[1], s[2], r, x_over_z, y_over_z, f_over_z)
        a0 = u0[0] * u0[0] + u0[1] * u0[1] + u0[2] * u0[2]
        b = u0[0] * u1[0] + u0[1] * u1[1] + u0[2] * u1[2]
        c0 = u1[0] * u1[0] + u1[1] * u1[1] + u1[2] * u1[2]
        a, c = a0 + variance, c0 + variance
        raw_determinant = a * c - b * b
        determinant = max(raw_determinant, MIN_DETERMINANT)
        # conics = (c, −b, a) / det; no gradient through a clamped determinant
        inverse_determinant = 1.0 / determinant
        g_det = -(g_conic_a * c - g_conic_b * b + g_conic_c * a) * (inverse_determinant * inverse_determinant)
        g_det = 0.0 if raw_determinant < MIN_DETERMINANT else g_det
        g_a = g_conic_c * inverse_determinant + g_det * c
        g_b = -g_conic_b * inverse_determinant - 2.0 * g_det * b
        g_c = g_conic_a * inverse_determinant + g_det * a
        # ρ = √(1 − deficit), deficit = (v(a0 + c0) + v²) / blurred, blurred = a·c − b²:
        # d deficit / d a0 = (v − deficit·c) / blurred, likewise for c0; / d b = 2b·deficit / blurred.
        # At the floor ρ is constant.
        ratio, deficit, blurred = _compensation_ratio(a0, b, c0, variance)
        compensating = (g_compensation != 0.0) & (ratio > MIN_COMPENSATION * MIN_COMPENSATION)
        g_deficit = -g_compensation / (2.0 * math.sqrt(max(ratio, 0.0)) * blurred)
        g_a = g_a + g_deficit * (variance - deficit * c) if compensating else g_a
        g_c = g_c + g_deficit * (variance - deficit * a) if compensating else g_c
        g_b = g_b + g_deficit * 2.0 * b * deficit if compensating else g_b
        g_u0 = (2.0 * g_a * u0[0] + g_b * u1[0], 2.0 * g_a * u0[1] + g_b * u1[1], 2.0 * g_a * u0[2] + g_b * u1[2])
        g_u1 = (g_b * u0[0] + 2.0 * g_c * u1[0], g_b * u0[1] + 2.0 * g_c * u1[1], g_b * u0[2] + 2.0 * g_c * u1[2])
        for j in range(3):
            g_scale = g_u0[j] * (t0[0] * r[j] + t0[1] * r[3 + j] + t0[2] * r[6 + j]) + g_u1[j] * (
                t1[0] * r[j] + t1[1] * r[3 + j] + t1[2] * r[6 + j]
            )
            results[3 + j, i] = g_scale
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
        g_qw = 2 * (-qz * g_r[1] + qy * g_r[2] + qz * g_r[3] - qx * g_r[5] - qy * g_r[6] + qx * g_r[7])
        g_qx = 2 * (
            qy * g_r[1]
            + qz * g_r[2]
            + qy * g_r[3]
            - 2 * qx * g_r[4]
            - qw * g_r[5]
            + qz * g_r[6]
            + qw * g_r[7]
            - 2 * qx * g_r[8]
        )
        g_qy = 2 * (
            -2 * qy * g_r[0]
            + qx * g_r[1]
            + qw * g_r[2]
            + qx * g_r[3]
            + qz * g_r[5]
            - qw * g_r[6]
            + qz * g_r[7]
            - 2 * qy * g_r[8]
        )
        g_qz = 2 * (
            -2 * qz * g_r[0]
            - qw * g_r[1]
            + qx * g_r[2]
            + qw * g_r[3]
            - 2 * qz * g_r[4]
            + qy * g_r[5]
            + qx * g_r[6]
            + qy * g_r[7]
        )
        # q / |q|: remove the radial part, then divide by |q| (a zero quaternion: by its floor only)
        normed = norm >= MIN_QUATERNION_NORM
        radial = g_qw * qw + g_qx * qx + g_qy * qy + g_qz * qz
        g_qw = g_qw - radial * qw if normed else g_qw
        g_qx = g_qx - radial * qx if normed else g_qx
        g_qy = g_qy - radial * qy if normed else g_qy
        g_qz = g_qz - radial * qz if normed else g_qz
        results[6, i] = g_qw * inverse_norm
        results[7, i] = g_qx * inverse_norm
        results[8, i] = g_qy * inverse_norm
        results[9, i] = g_qz * inverse_norm
        # T rows: t0 = f/z (w0 − x/z w2), t1 = f/z (w1 − y/z w2)
        g_f_over_z = 0.0
        g_x_over_z = 0.0
        g_y_over_z = 0.0
        for k in range(3):
            g_f_over_z += g_t0[k] * (rotation[0, k] - x_over_z * rotation[2, k])
            g_f_over_z += g_t1[k] * (rotation[1, k] - y_over_z * rotation[2, k])
            g_x_over_z -= f_over_z * g_t0[k] * rotation[2, k]
            g_y_over_z -= f_over_z * g_t1[k] * rotation[2, k]
        inverse_z2 = inverse_z * inverse_z
        g_cx = f_over_z * g_u
        g_cy = f_over_z * g_v
        g_z = -(focal * inverse_z2) * g_f_over_z - focal * (cx * g_u + cy * g_v) * inverse_z2
        # no gradient through a clamped x/z or y/z, nor through the depth of a culled Gaussian
        inside_x = (-limit_x <= raw_x) & (raw_x <= limit_x)
        inside_y = (-limit_y <= raw_y) & (raw_y <= limit_y)
        g_cx = g_cx + g_x_over_z * inverse_z if inside_x else g_cx
        g_z = g_z - g_x_over_z * cx * inverse_z2 if inside_x else g_z
        g_cy = g_cy + g_y_over_z * inverse_z if inside_y else g_cy
        g_z = g_z - g_y_over_z * cy * inverse_z2 if inside_y else g_z
        g_z = g_z if in_front else 0.0
        for k in range(3):
            g_mean = rotation[0, k] * g_cx + rotation[1, k] * g_cy + rotation[2, k] * g_z
            results[k, i] = g_mean
