"""The training SSIM's window as one numba kernel: a stack of images blurred along both axes by a
symmetric window with zero padding ("same" size).

The loss blurs five moment maps every iteration, and its backward blurs their gradients. As two
dense banded matrix products the blur costs size³ (the band is 11 wide, the product 512): at the
``detail`` preset's 512² views it took 134 of a splat iteration's ~290 ms on one core. Here it is
the 11 taps per axis it is, size².

The operator is symmetric (the window is, and zero padding keeps its matrix symmetric), so the
same kernel computes the backward: the gradient blurred as the images were.

Each output is summed over the taps in their order, whatever the thread count, so a run's bits
do not depend on the cores it had.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from cubecloud_cli.numerics.jit import EXACT_FASTMATH, PRANGE_ONLY


@njit(parallel=PRANGE_ONLY, cache=True, fastmath=EXACT_FASTMATH)
def blur_same_into(images, window, out) -> None:
    """out[n] = images[n] blurred by ``window`` along its rows, then down its columns, with zeros
    beyond the edges; ``window`` has an odd number of taps and the images' dtype."""
    count, height, width = images.shape
    taps = window.shape[0]
    radius = taps // 2
    for n in prange(count):
        # Each row is copied into a zero-padded line first: a sum over the line's taps with
        # fixed bounds vectorises, the same sum with bounds clipped at the edges did not (6× slower).
        line = np.zeros(width + 2 * radius, dtype=images.dtype)
        rows = np.empty((height, width), dtype=images.dtype)
        for i in range(height):
            for j in range(width):
                line[radius + j] = images[n, i, j]
            for j in range(width):
                rows[i, j] = 0.0
            for k in range(taps):  # j innermost: independent sums, vectorised without reordering any
                weight = window[k]
                for j in range(width):
                    rows[i, j] += weight * line[j + k]
        for i in range(height):
            for j in range(width):
                out[n, i, j] = 0.0
            for k in range(max(0, radius - i), min(taps, height + radius - i)):
                weight = window[k]
                source = i + k - radius
                for j in range(width):
                    out[n, i, j] += weight * rows[source, j]


def blur_same(images: np.ndarray, window: np.ndarray) -> np.ndarray:
    """The (N, H, W) stack ``images`` blurred along both image axes by the symmetric ``window``,
    zero-padded, in the images' dtype (float32 or float64)."""
    if window.shape[0] % 2 != 1 or not np.array_equal(window, window[::-1]):
        raise ValueError("the window must have an odd number of taps and be symmetric")
    images = np.ascontiguousarray(images)
    out = np.empty_like(images)
    blur_same_into(images, np.ascontiguousarray(window, dtype=images.dtype), out)
    return out
