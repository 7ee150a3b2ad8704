"""The grid field on CPU tensors as numba kernels: the multiresolution lookup, and the small MLP
after it (``mlp_forward``/``mlp_backward``, where torch's matrix products for 32 768 × 6 → 32 → 2
cost more than their arithmetic).

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

from cubecloud_cli.numerics.jit import EXACT_FASTMATH, PRANGE_ONLY


@njit(cache=True, inline="always")
def corner_base(x, y, z, r):
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


@njit(parallel=PRANGE_ONLY, cache=True)
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
            base, fx, fy, fz = corner_base(points[p, 0], points[p, 1], points[p, 2], r)
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


@njit(parallel=PRANGE_ONLY, cache=True)
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


# Points per block of the MLP's backward: each block sums its points' weight gradients in order,
# and the blocks are added in order, so the sums do not depend on the number of threads.
MLP_BLOCK = 2048


@njit(parallel=PRANGE_ONLY, cache=True, fastmath=EXACT_FASTMATH)
def mlp_forward(features, w1t, b1, w2, b2):
    """(P, I) features → (P, O) raw outputs of Linear(I, H) → ReLU → Linear(H, O); ``w1t`` is the
    first layer's (out, in) weight transposed to (I, H), so the inner loops run over the H
    hidden units in contiguous memory and become vector code. float32 in, float32 out."""
    count, inputs, hidden, outputs = features.shape[0], features.shape[1], w1t.shape[1], w2.shape[0]
    out = np.empty((count, outputs), dtype=np.float32)
    for p in prange(count):
        h = b1.copy()
        for i in range(inputs):
            x = features[p, i]
            for j in range(hidden):
                h[j] += w1t[i, j] * x
        for o in range(outputs):
            total = b2[o]
            for j in range(hidden):
                total += w2[o, j] * max(h[j], np.float32(0.0))
            out[p, o] = total
    return out


@njit(parallel=PRANGE_ONLY, cache=True, fastmath=EXACT_FASTMATH)
def mlp_backward(features, grad_out, w1t, b1, w2):
    """Gradients of Σ grad_out · mlp_forward(features): with respect to the features (P, I), and
    per block of MLP_BLOCK points the partial sums for w1 (transposed, as ``w1t``), b1, w2 and
    b2 (blocks, ...), which the caller adds in block order."""
    count, inputs, hidden, outputs = features.shape[0], features.shape[1], w1t.shape[1], w2.shape[0]
    blocks = (count + MLP_BLOCK - 1) // MLP_BLOCK
    grad_features = np.empty((count, inputs), dtype=np.float32)
    # Allocated empty and zeroed by the block that owns them: np.zeros here would be a parallel
    # loop of its own, which numba compiles separately (seconds at a new user's first run).
    grad_w1t = np.empty((blocks, inputs, hidden), dtype=np.float32)
    grad_b1 = np.empty((blocks, hidden), dtype=np.float32)
    grad_w2 = np.empty((blocks, outputs, hidden), dtype=np.float32)
    grad_b2 = np.empty((blocks, outputs), dtype=np.float32)
    for block in prange(blocks):
        h = np.empty(hidden, dtype=np.float32)
        grad_h = np.empty(hidden, dtype=np.float32)
        for j in range(hidden):
            grad_b1[block, j] = np.float32(0.0)
            for i in range(inputs):
                grad_w1t[block, i, j] = np.float32(0.0)
            for o in range(outputs):
                grad_w2[block, o, j] = np.float32(0.0)
        for o in range(outputs):
            grad_b2[block, o] = np.float32(0.0)
        for p in range(block * MLP_BLOCK, min(count, (block + 1) * MLP_BLOCK)):
            for j in range(hidden):
                h[j] = b1[j]
            for i in range(inputs):
                x = features[p, i]
                for j in range(hidden):
                    h[j] += w1t[i, j] * x
            for j in range(hidden):
                grad_h[j] = np.float32(0.0)
            for o in range(outputs):
                g = grad_out[p, o]
                grad_b2[block, o] += g
                for j in range(hidden):
                    grad_w2[block, o, j] += g * max(h[j], np.float32(0.0))
                    grad_h[j] += g * w2[o, j]
            for j in range(hidden):  # ReLU's gradient is 0 at and below 0, as torch's
                grad_h[j] = grad_h[j] if h[j] > 0.0 else np.float32(0.0)
                grad_b1[block, j] += grad_h[j]
            for i in range(inputs):
                x = features[p, i]
                total = np.float32(0.0)
                for j in range(hidden):
                    grad_w1t[block, i, j] += grad_h[j] * x
                    total += grad_h[j] * w1t[i, j]
                grad_features[p, i] = total
    return grad_features, grad_w1t, grad_b1, grad_w2, grad_b2
