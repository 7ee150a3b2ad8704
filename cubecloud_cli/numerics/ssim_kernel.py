"""The SSIM of a stack of slices on the CPU in one numba kernel, parallel over the slices.

A volume's 3D SSIM is the mean 2D SSIM of its slices along all three axes (``metrics.py``):
at 512³ that is 1536 slices of 512², and scipy's single-threaded 1D passes, with numpy's
float64 temporaries between them, took 85–134 s of the detail preset's cunerf stage. Here each
slice is blurred and scored in one pass over it: the four windowed sums SSIM needs (x, y,
x² + y² and x·y) along the rows, then down the columns, then the SSIM formula per pixel, summed
over the slice and over its body pixels. No SSIM map is kept.

Sums are float64 whatever the input, as the scipy path's are; they are added in another order,
so the two agree to rounding (tests/test_ssim_kernel.py), not to the bit.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from cubecloud_cli.numerics.jit import EXACT_FASTMATH, PRANGE_ONLY

# The blurred quantities, in the kernel's buffers' first axis.
MEAN_X, MEAN_Y, MEAN_SQUARES, MEAN_PRODUCT = 0, 1, 2, 3


@njit(cache=True, fastmath=EXACT_FASTMATH)
def _blur_rows(reference, estimate, n, window, rows) -> None:
    """rows[q, i, j] = Σ_k window[k] · quantity_q[n, i, j + k] for each row i of slice n."""
    height, width = reference.shape[1], reference.shape[2]
    taps, out_width = window.shape[0], rows.shape[2]
    line = np.empty((4, width))
    for i in range(height):
        for j in range(width):
            a = np.float64(reference[n, i, j])
            b = np.float64(estimate[n, i, j])
            line[MEAN_X, j] = a
            line[MEAN_Y, j] = b
            line[MEAN_SQUARES, j] = a * a + b * b
            line[MEAN_PRODUCT, j] = a * b
        for q in range(4):
            for j in range(out_width):
                rows[q, i, j] = 0.0
            for k in range(taps):  # j innermost: independent sums, vectorised without reordering any
                weight = window[k]
                for j in range(out_width):
                    rows[q, i, j] += weight * line[q, j + k]


@njit(parallel=PRANGE_ONLY, cache=True, fastmath=EXACT_FASTMATH)
def slice_ssim_sums(reference, estimate, body, window, c1, c2, sums, body_sums, body_counts) -> None:
    """For each slice n of the (N, H, W) stacks: the sum of its SSIM map (the pixels whose
    window lies inside the slice, (H − 2r)(W − 2r) of them) into ``sums[n]``, and the sum and
    count over those pixels where ``body`` is set into ``body_sums[n]`` and ``body_counts[n]``."""
    slices, height, width = reference.shape
    taps = window.shape[0]
    radius = taps // 2
    out_height, out_width = height - 2 * radius, width - 2 * radius
    for n in prange(slices):
        rows = np.empty((4, height, out_width))
        _blur_rows(reference, estimate, n, window, rows)
        blurred = np.empty((4, out_width))
        total, inside_total, inside_count = 0.0, 0.0, 0
        for i in range(out_height):
            for q in range(4):
                for j in range(out_width):
                    blurred[q, j] = 0.0
                for k in range(taps):
                    weight = window[k]
                    for j in range(out_width):
                        blurred[q, j] += weight * rows[q, i + k, j]
            for j in range(out_width):
                mean_x, mean_y = blurred[MEAN_X, j], blurred[MEAN_Y, j]
                mean_xy = mean_x * mean_y
                mean_sq = mean_x * mean_x + mean_y * mean_y
                covariance = blurred[MEAN_PRODUCT, j] - mean_xy
                # var_x + var_y ≥ 0 by Jensen; rounding may take it below, and c2 > 0 then keeps
                # the denominator ≥ c1 · c2 > 0.
                variance_sum = max(blurred[MEAN_SQUARES, j] - mean_sq, 0.0)
                value = (2.0 * mean_xy + c1) * (2.0 * covariance + c2) / ((mean_sq + c1) * (variance_sum + c2))
                total += value
                if body[n, i + radius, j + radius]:
                    inside_total += value
                    inside_count += 1
        sums[n] = total
        body_sums[n] = inside_total
        body_counts[n] = inside_count


def stack_ssim_sums(
    reference: np.ndarray, estimate: np.ndarray, body: np.ndarray, window: np.ndarray, c1: float, c2: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per slice of three (N, H, W) stacks: the SSIM map's sum, and its sum and pixel count
    inside ``body``. float32 inputs are read as they are; others as float64."""
    dtype = np.float32 if reference.dtype == estimate.dtype == np.float32 else np.float64
    reference = np.ascontiguousarray(reference, dtype=dtype)
    estimate = np.ascontiguousarray(estimate, dtype=dtype)
    body = np.ascontiguousarray(body, dtype=np.bool_)
    slices = reference.shape[0]
    sums, body_sums = np.zeros(slices), np.zeros(slices)
    body_counts = np.zeros(slices, dtype=np.int64)
    slice_ssim_sums(
        reference, estimate, body, np.ascontiguousarray(window, dtype=np.float64), c1, c2, sums, body_sums, body_counts
    )
    return sums, body_sums, body_counts
