"""The grid field's multiresolution lookup as two numba kernels, for CPU tensors.

The same arithmetic as :func:`cubecloud_cli.cunerf.fields.trilinear_corners` followed by a
weighted sum of the 8 corner rows, but fused: the torch path builds (P, 8) index and weight
tensors per level and scatters a dense gradient with ``index_add_``, and at the fast preset's
32 768 points per iteration those ~30 small passes were two thirds of a CuNeRF iteration
(bench/cunerf.py). Here each point's corners, weights and features are computed in registers.

The forward runs in parallel over points. The backward adds into one dense gradient with each
thread owning a slab of rows, so every row is summed in the points' order and a seeded run gives
the same gradient bit for bit, on any number of threads (parallel scatter-adds would sum in an
order that depends on the threads' timing).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _corner_base(x, y, z, r):
    """The low corner's row and the fractions along x, y, z, as ``trilinear_corners``: vertex v
    at world (2v + 1)/r − 1, clamped to the outermost vertices, NaN read as the first vertex."""
    half = np.float32(0.5) * np.float32(r)
    top = np.float32(r - 1)
    cx = (x + np.float32(1.0)) * half - np.float32(0.5)
    cy = (y + np.float32(1.0)) * half - np.float32(0.5)
    cz = (z + np.float32(1.0)) * half - np.float32(0.5)
    # The lower bound first: a NaN fails it and becomes 0, as clamp then nan_to_num make it.
    cx = cx if cx >= np.float32(0.0) else np.float32(0.0)
    cy = cy if cy >= np.float32(0.0) else np.float32(0.0)
    cz = cz if cz >= np.float32(0.0) else np.float32(0.0)
    cx = cx if cx <= top else top
    cy = cy if cy <= top else top
    cz = cz if cz <= top else top
    lx, ly, lz = min(np.int64(cx), r - 2), min(np.int64(cy), r - 2), min(np.int64(cz), r - 2)
    base = (lx * r + ly) * r + lz
    return base, cx - np.float32(lx), cy - np.float32(ly), cz - np.float32(lz)


@njit(parallel=True, cache=True)
def encode_forward(points, table, resolutions, offsets, cells, fractions):
    """(P, 3) float32 points → (P, L·F) float32: each level's features, trilinearly interpolated.

    When ``cells`` (P, L, 2) and ``fractions`` (P, L, 3) have a row per point, each point's low
    corner per level (its table row and its x vertex) and its fractions are written there for
    :func:`encode_backward`; pass empty arrays when no gradient is wanted."""
    count, features, levels = points.shape[0], table.shape[1], resolutions.size
    keep = cells.shape[0] == count and fractions.shape[0] == count
    out = np.empty((count, levels * features), dtype=np.float32)
    one = np.float32(1.0)
    for p in prange(count):
        for level in range(levels):
            r = resolutions[level]
            base, fx, fy, fz = _corner_base(points[p, 0], points[p, 1], points[p, 2], r)
            if keep:
                cells[p, level, 0], cells[p, level, 1] = base + offsets[level], base // (r * r)
                fractions[p, level, 0], fractions[p, level, 1], fractions[p, level, 2] = fx, fy, fz
            base += offsets[level]
            for f in range(features):
                out[p, level * features + f] = 0.0
            for corner in range(8):
                a, b, c = corner >> 2, (corner >> 1) & 1, corner & 1
                weight = ((fx if a else one - fx) * (fy if b else one - fy)) * (fz if c else one - fz)
                row = base + a * r * r + b * r + c
                for f in range(features):
                    out[p, level * features + f] += weight * table[row, f]
    return out


@njit(parallel=True, cache=True)
def encode_backward(cells, fractions, grad_features, resolutions, offsets, rows, features, bands):
    """The dense (rows, F) float32 gradient of Σ grad_features · encode_forward(points) with
    respect to the table, from the ``cells`` and ``fractions`` the forward kept. Each of
    ``bands`` threads owns a slab of every level's vertices along x and walks every point,
    adding only into its slab: every row is summed in the points' order, so the gradient is the
    same bit for bit on any number of threads."""
    # Each band zeroes its own slabs (together they are every row): in parallel, and in cache.
    grad = np.empty((rows, features), dtype=np.float32)
    one = np.float32(1.0)
    levels = resolutions.size
    for band in prange(bands):
        first = np.empty(levels, dtype=np.int64)  # this band's x vertices per level: first..stop−1
        stop = np.empty(levels, dtype=np.int64)
        for level in range(levels):
            r = resolutions[level]
            first[level], stop[level] = r * band // bands, r * (band + 1) // bands
            grad[offsets[level] + first[level] * r * r : offsets[level] + stop[level] * r * r] = 0.0
        for p in range(cells.shape[0]):
            for level in range(levels):
                low_x = cells[p, level, 1]
                if low_x + 1 < first[level] or low_x >= stop[level]:
                    continue
                r = resolutions[level]
                base = cells[p, level, 0]
                fx, fy, fz = fractions[p, level, 0], fractions[p, level, 1], fractions[p, level, 2]
                for a in range(2):
                    if low_x + a < first[level] or low_x + a >= stop[level]:
                        continue
                    wx = fx if a else one - fx
                    for b in range(2):
                        wxy = wx * (fy if b else one - fy)
                        for c in range(2):
                            weight = wxy * (fz if c else one - fz)
                            row = base + a * r * r + b * r + c
                            for f in range(features):
                                grad[row, f] += weight * grad_features[p, level * features + f]
    return grad
