"""Which Gaussians touch which 16×16 tile, front to back: the setup of the CPU kernels.

Two compiled calls do what :func:`cubecloud_cli.raster.pairs.pixel_bounds` and a sort do for the
oracle. :func:`splat_boxes`, in parallel, computes each splat's pixel box (its 3σ square shrunk
to where α ≥ 1/255). :func:`bin_tiles`, on one thread, reads the boxes once for the tiles each
spans and the count of boxes per tile, sorts the Gaussians with a box by depth (a stable radix
sort), and writes each one's entries, front to back, straight into its tiles' lists (CSR). Every
part is linear and branch-light, which matters because at 50k Gaussians this setup once cost a
quarter of a frame."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros

from cubecloud_cli.numerics.jit import PRANGE_ONLY, fused_multiply_add, prefetch
from cubecloud_cli.raster.constants import ALPHA_LEVEL_SCALE, TILE_SHIFT

# A radix sort pass sorts on up to this many bits: its 4096 counts (int32) stay in the L1 cache,
# and the 23 bits in which float32 depths differ take two passes rather than three of 11 bits.
RADIX_BITS = 12

# How many ranks ahead bin_tiles asks for a Gaussian's tile span: about the memory latency over
# one Gaussian's scatter.
SPANS_AHEAD = 16


@njit(cache=True)
def stable_depth_order(candidates, depths):
    """``candidates`` sorted by depth, ties kept in their order: an LSD radix sort on the float64
    bits (sign-flipped so that integer order is float order), linear in the count. Only the bits
    that differ between keys are sorted on, in as few passes of up to RADIX_BITS as they need:
    float32 depths leave the low 29 bits zero, and nearby depths share their sign and exponent.
    Where the candidates' indices fit in the low bits that every key shares, they ride there,
    and each pass moves one array instead of two."""
    count = candidates.size
    if count < 2:
        return candidates.copy()
    keys = np.empty(count, dtype=np.uint64)
    sign = np.uint64(1) << np.uint64(63)
    any_bits, all_bits = np.uint64(0), ~np.uint64(0)
    any_index_bits = np.uint64(0)
    for i in range(count):
        value = depths[candidates[i]] + 0.0  # turns −0 into +0, which compares equal to it
        bits = np.float64(value).view(np.uint64)
        key = ~bits if bits & sign else bits | sign
        keys[i] = key
        any_bits |= key
        all_bits &= key
        any_index_bits |= np.uint64(candidates[i])
    varying = any_bits ^ all_bits  # bits set in some keys and clear in others
    if varying == 0:
        return candidates.copy()  # one key: the order stays
    lowest = trailing_zeros(varying)
    span = 64 - leading_zeros(varying) - lowest
    passes = -(-span // RADIX_BITS)
    digit_bits = -(-span // passes)
    digit_mask = np.uint64((1 << digit_bits) - 1)
    shared_low = (np.uint64(1) << np.uint64(lowest)) - np.uint64(1)
    packed = any_index_bits & shared_low == any_index_bits  # every index fits where the keys do not differ
    if packed:
        for i in range(count):
            keys[i] = (keys[i] & ~shared_low) | np.uint64(candidates[i])
    # Each pass's digit counts in a loop of its own over the keys, through a 1D view: one loop
    # for all passes, with the pass as an inner loop over a 2D array, took 3.4 times as long.
    counts = np.zeros((passes, (1 << digit_bits) + 1), dtype=np.int32)
    for p in range(passes):
        pass_counts = counts[p]
        shift = np.uint64(lowest + p * digit_bits)
        for i in range(count):
            pass_counts[((keys[i] >> shift) & digit_mask) + 1] += 1
    order = candidates[: 0 if packed else count].copy()
    scratch_keys = np.empty_like(keys)
    scratch_order = np.empty_like(order)
    for p in range(passes):
        pass_counts = counts[p]
        shift = np.uint64(lowest + p * digit_bits)
        for b in range(1 << digit_bits):
            pass_counts[b + 1] += pass_counts[b]
        for i in range(count):
            digit = (keys[i] >> shift) & digit_mask
            position = pass_counts[digit]
            scratch_keys[position] = keys[i]
            if not packed:
                scratch_order[position] = order[i]
            pass_counts[digit] = position + 1
        keys, scratch_keys = scratch_keys, keys
        order, scratch_order = scratch_order, order
    if not packed:
        return order
    result = np.empty(count, dtype=np.int64)
    for i in range(count):
        result[i] = np.int64(keys[i] & shared_low)
    return result


# ln 2 in two parts (fdlibm's): the high part has its low 21 bits zero, so that e · LN2_HIGH is
# exact for any exponent e of a float64 (|e| < 2¹¹), and the low part carries the rest.
LN2_HIGH = 0.6931471803691238
LN2_LOW = 1.9082149292705877e-10


@njit(cache=True, inline="always")
def natural_log(x):
    """ln x of a float64 without a libm call, so that a loop over many stays SIMD: the binary
    exponent e and mantissa m ∈ [√½, √2) from the bits, then e·ln 2 + 2·atanh((m − 1)/(m + 1))
    by its series. Within an ulp of libm's log for positive normal x (tests/test_raster_cpu.py);
    +inf and NaN come back as they are. Zero, negative and subnormal x are not handled: callers
    pass x ≥ 1e-30."""
    bits = np.float64(x).view(np.uint64)
    exponent = np.int64((bits >> np.uint64(52)) & np.uint64(0x7FF)) - 1023
    mantissa = (bits & np.uint64(0xFFFFFFFFFFFFF)) | np.uint64(0x3FF0000000000000)
    m = np.uint64(mantissa).view(np.float64)
    high = m > 1.4142135623730951
    m = m * 0.5 if high else m
    e = np.float64(exponent + 1 if high else exponent)
    f = m - 1.0  # exact
    s = f / (2.0 + f)  # ln(1 + f) = 2·atanh(s)
    z = s * s
    # Horner's form written out: a loop here, even of a constant count, would be the innermost
    # loop LLVM's vectorizer looks at, and the caller's loop would stay scalar
    tail = fused_multiply_add(z, 2.0 / 23.0, 2.0 / 21.0)
    tail = fused_multiply_add(z, tail, 2.0 / 19.0)
    tail = fused_multiply_add(z, tail, 2.0 / 17.0)
    tail = fused_multiply_add(z, tail, 2.0 / 15.0)
    tail = fused_multiply_add(z, tail, 2.0 / 13.0)
    tail = fused_multiply_add(z, tail, 2.0 / 11.0)
    tail = fused_multiply_add(z, tail, 2.0 / 9.0)
    tail = fused_multiply_add(z, tail, 2.0 / 7.0)
    tail = fused_multiply_add(z, tail, 2.0 / 5.0)
    tail = fused_multiply_add(z, tail, 2.0 / 3.0)
    tail *= z  # 2·Σ zᵏ/(2k + 1), k ≥ 1
    # ln(1 + f) = f − (f²/2 − s·(f²/2 + tail)), as fdlibm's log orders it: f²/2 leads the
    # correction, and the rounding errors stay below an ulp of the result
    half_square = 0.5 * f * f
    result = e * LN2_HIGH - ((half_square - (s * (half_square + tail) + e * LN2_LOW)) - f)
    return result if x < np.inf else x


@njit(cache=True, inline="always")
def alpha_level(opacity):
    """ln(255·o), floored at 0: the power below which a pair's α = o·exp(−power) ≥ 1/255."""
    level = natural_log(max(ALPHA_LEVEL_SCALE * opacity, 1e-30))
    return level if level > 0.0 else 0.0


# error_model="numpy": natural_log divides by 2 + f ≥ 1.7, and a division that checks for zero
# (Python's model) is a branch that keeps its loop scalar.
@njit(parallel=PRANGE_ONLY, cache=True, error_model="numpy")
def splat_boxes(means2d, covariances2d, radii, opacities, width, height):
    """Per Gaussian: the inclusive pixel box (x0, x1, y0, y1) as ``pixel_bounds`` with opacities
    computes it (empty, (0, −1, 0, −1), where culled), and the power level ln(255·o) ≥ 0 below
    which α ≥ 1/255. Opacities are in [0, 1]; a NaN or infinite one culls its Gaussian.

    The arithmetic is float64. ``pixel_bounds`` on float32 tensors rounds in float32, so where
    u ± r − ½ lands within float32 rounding of an integer, a box edge can differ by one pixel:
    the box here is the exact one, and the forward and backward kernels use the same."""
    count = means2d.shape[0]
    bounds = np.empty((count, 4), dtype=np.int64)
    levels = np.empty(count)
    # Two loops: the log alone in the first, where it runs as SIMD (natural_log); the box loop
    # after it has no branch (a culled box is a select), which a culled Gaussian in no order a
    # predictor learns would miss.
    for i in prange(count):
        levels[i] = alpha_level(opacities[i])
    for i in prange(count):
        level, u, v, radius = levels[i], means2d[i, 0], means2d[i, 1], np.float64(radii[i])
        half_x = min(radius, math.sqrt(2.0 * level * covariances2d[i, 0]))
        half_y = min(radius, math.sqrt(2.0 * level * covariances2d[i, 2]))
        finite = np.isfinite(half_x) & np.isfinite(half_y) & np.isfinite(u) & np.isfinite(v) & np.isfinite(level)
        # numba's min/max drop a NaN rather than propagate it, so a NaN opacity is culled by name
        kept = (radii[i] > 0) & finite & (opacities[i] >= 0.0)
        x0 = min(max(math.ceil(u - half_x - 0.5), 0.0), width)
        x1 = min(max(math.floor(u + half_x - 0.5), -1.0), width - 1.0)
        y0 = min(max(math.ceil(v - half_y - 0.5), 0.0), height)
        y1 = min(max(math.floor(v + half_y - 0.5), -1.0), height - 1.0)
        bounds[i, 0] = np.int64(x0 if kept else 0.0)
        bounds[i, 1] = np.int64(x1 if kept else -1.0)
        bounds[i, 2] = np.int64(y0 if kept else 0.0)
        bounds[i, 3] = np.int64(y1 if kept else -1.0)
    return bounds, levels


@njit(cache=True)
def _spans_and_offsets(bounds, tiles_x, tiles_y):
    """In one pass over the boxes: per Gaussian, the first tile its box touches (row-major
    index), how many tile columns it spans and how many tiles in all (0 for an empty box); the
    Gaussians with a non-empty box, in index order; and the CSR offsets of the per-tile lists.
    The offsets come without a loop over each box's tiles: a box adds one over a rectangle of
    tiles, four updates of a difference array whose 2D prefix sum is the counts."""
    count = bounds.shape[0]
    corner = np.empty(count, dtype=np.int64)
    columns = np.empty(count, dtype=np.int64)
    tiles = np.empty(count, dtype=np.int64)
    nonempty = np.empty(count, dtype=np.int64)
    kept = 0
    difference = np.zeros((tiles_y + 1, tiles_x + 1), dtype=np.int64)
    for g in range(count):
        x0, x1 = bounds[g, 0] >> TILE_SHIFT, bounds[g, 1] >> TILE_SHIFT
        y0, y1 = bounds[g, 2] >> TILE_SHIFT, bounds[g, 3] >> TILE_SHIFT
        filled = (bounds[g, 1] >= bounds[g, 0]) & (bounds[g, 3] >= bounds[g, 2])
        corner[g] = y0 * tiles_x + x0
        columns[g] = x1 - x0 + 1
        tiles[g] = columns[g] * (y1 - y0 + 1) if filled else 0
        nonempty[kept] = g
        kept += filled
        # an empty box adds zero, at corners clamped into the array
        step = np.int64(filled)
        x0, x1, y0, y1 = max(x0, 0), max(x1 + 1, 0), max(y0, 0), max(y1 + 1, 0)
        difference[y0, x0] += step
        difference[y0, x1] -= step
        difference[y1, x0] -= step
        difference[y1, x1] += step
    offsets = np.empty(tiles_x * tiles_y + 1, dtype=np.int64)
    offsets[0] = 0
    column_sums = np.zeros(tiles_x, dtype=np.int64)  # each column's prefix over the rows so far
    for ty in range(tiles_y):
        running = 0
        for tx in range(tiles_x):
            running += difference[ty, tx]
            column_sums[tx] += running
            offsets[ty * tiles_x + tx + 1] = offsets[ty * tiles_x + tx] + column_sums[tx]
    return corner, columns, tiles, nonempty[:kept], offsets


@njit(cache=True)
def bin_tiles(bounds, depths, tiles_x, tiles_y):
    """Per-tile lists of the Gaussians with a non-empty box, front to back (CSR: offsets, entries),
    ties in depth kept in index order.

    Serial: on two threads, each of these passes measured slower than on one, the second
    thread's wake and cold caches costing more than half of a pass (docs/results.md, "Binning stays serial")."""
    corner, columns, tiles, nonempty, offsets = _spans_and_offsets(bounds, tiles_x, tiles_y)
    kept = nonempty.size
    order = stable_depth_order(nonempty, depths)
    # Gaussians front to back, each one's tiles row by row, straight into their tiles' lists:
    # every list comes out front to back. The wrap to the next tile row is a select (two
    # nested loops of one or two trips each are a branch miss apiece).
    fill = offsets[:-1].copy()
    # int32 entries: half the memory the kernels move (a frame holds far fewer than 2³¹
    # entries: 111k at 50k Gaussians and 128²)
    entries = np.empty(offsets[-1], dtype=np.int32)
    for rank in range(kept):
        g = order[rank]
        # the spans are read in depth order, which the hardware prefetcher cannot follow
        ahead = order[min(rank + SPANS_AHEAD, kept - 1)]
        prefetch(tiles, ahead)
        prefetch(columns, ahead)
        prefetch(corner, ahead)
        width, row_start, column = columns[g], corner[g], 0
        for _ in range(tiles[g]):
            tile = row_start + column
            at = fill[tile]
            entries[at] = g
            fill[tile] = at + 1
            wrap = column + 1 == width
            column = 0 if wrap else column + 1
            row_start = row_start + tiles_x if wrap else row_start
    return offsets, entries


@njit(parallel=PRANGE_ONLY, cache=True)
def sum_per_gaussian(row_grads, gaussian_rows, means2d_grad, conics_grad, opacities_grad, colours_grad):
    """Each Gaussian's sums of its rows ``gaussian_rows[g]:gaussian_rows[g + 1]`` of the
    (rows, 6 + C) ``row_grads``: the compositing backward's columns mean2d (2), conic (3), opacity,
    colour (C), each group into its own output, (count, 2), (count, 3), (count,) and (count, C),
    every Gaussian's row written (0 where it has none). The sums are taken in float64, row by row,
    and stored in the outputs' type: the gradients come out as the contiguous arrays autograd
    takes, without a copy per column group. In parallel over Gaussians by index: the rows and the
    outputs are read and written in order, each thread its own stretch."""
    for g in prange(means2d_grad.shape[0]):
        mean_x = mean_y = conic_a = conic_b = conic_c = opacity = colour_0 = 0.0
        for e in range(gaussian_rows[g], gaussian_rows[g + 1]):
            mean_x += row_grads[e, 0]
            mean_y += row_grads[e, 1]
            conic_a += row_grads[e, 2]
            conic_b += row_grads[e, 3]
            conic_c += row_grads[e, 4]
            opacity += row_grads[e, 5]
            colour_0 += row_grads[e, 6]
        means2d_grad[g, 0], means2d_grad[g, 1] = mean_x, mean_y
        conics_grad[g, 0], conics_grad[g, 1], conics_grad[g, 2] = conic_a, conic_b, conic_c
        opacities_grad[g] = opacity
        colours_grad[g, 0] = colour_0
        for ch in range(1, colours_grad.shape[1]):
            total = 0.0
            for e in range(gaussian_rows[g], gaussian_rows[g + 1]):
                total += row_grads[e, 6 + ch]
            colours_grad[g, ch] = total
