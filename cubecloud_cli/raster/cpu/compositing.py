"""The fast CPU rasterizer: numba kernels, parallel over 16×16 tiles, with a hand-written backward.

Same rules and the same pairs as the PyTorch oracle (``pairs.py``): each splat covers the pixels
of its 3σ square, Gaussians are composited front to back in the oracle's depth order, α ≤ 0.99,
pairs with α < 1/255 are skipped, and a pixel stops before its transmittance would fall below
1e-4. Arithmetic is in the inputs' precision: float32 training tensors composite in float32, as
the reference CUDA rasterizer does; float64 inputs (the tests' oracle comparisons) in float64.

What makes them fast on two cores (``bench/raster.py``): within a tile each Gaussian visits only
the rows of its own box; each row is one fixed 16-pixel loop without branches (every test a
select), which LLVM turns into SIMD, 8 float32 lanes at a time on AVX2, or one 8-pixel loop
where the row's pixels to visit lie within 8 columns (NARROW). The exp is inline
arithmetic (a polynomial, then squarings), not a libm call; the polynomial, the power and the
sums are fused multiply-adds, written out (``cubecloud_cli.numerics.jit.fused_multiply_add``: 0.89 of the
forward's time and 0.87 of the backward's on the bench frame); rows whose pixels have all stopped
are skipped by a bit mask; the backward skips entries, and rows of entries, that blended nothing.
Which rows an entry visits, which of them blended and which entries the backward walks are bit
masks and lists, kept by stores and counts rather than by tests: such a test follows no pattern
a branch predictor learns, and each one it missed cost a row more than its pixels (docs/history/rasterizer-speed.md).
An entry's Gaussian is read at an index that follows no order in memory, so the Gaussian of the
entry four ahead is prefetched while the current one blends.

Backward walks each pixel's list back to front (as the reference CUDA code does), recovering the
transmittance before each Gaussian by division by (1 − α) ≥ 0.01. Gradients go into one row per
(tile, Gaussian) entry that blended, numbered from the forward's lists and grouped by Gaussian,
so threads never write the same memory and the per-Gaussian sums read only rows that hold a
value, in order.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange, types
from numba.cpython.unsafe.numbers import leading_zeros, trailing_zeros
from numba.extending import overload

from cubecloud_cli.numerics.jit import (
    FASTMATH,
    PRANGE_ONLY,
    as_real,
    fused_multiply_add,
    negative_lanes_8,
    negative_lanes_16,
    positive_lanes_8,
    positive_lanes_16,
    prefetch,
)
from cubecloud_cli.raster.constants import MAX_ALPHA, MIN_ALPHA, TILE, TRANSMITTANCE_STOP

# Pairs with power > ln(255·o) have α < 1/255; the margin leaves exact ties to the α test.
LEVEL_MARGIN = 1e-9
# exp(−p) = exp(−p/32)³²: the polynomial's argument stays below 6/32, where degree 9 is exact to
# float64 rounding. Powers above 6 are reached only by opacities above e⁶/255 ≈ 1.6, outside the
# [0, 1] contract; such a Gaussian takes libm's exp instead.
EXP_POLYNOMIAL_LIMIT = 6.0

# How the pixel loops stay SIMD (numba hands them to LLVM's loop vectorizer, which gives up on
# any of these): each loop runs over a constant count of pixels of a tile row (16, or NARROW),
# indexed by an unsigned index (a signed one, like window + i, is checked for wrap-around, a
# branch); every test is a select between values of the compute type or of int32 (int64 compares
# or counters halve the width); no call and no inner loop in the body; no Python division check
# (error_model="numpy": 1 − α ≥ 0.01); and few arrays written, each a plain 2D tile array, none
# passed to a helper (reference counting calls). The tile arrays a row loop reads and writes at
# [r, i] are views of one allocation at constant distances, so that LLVM knows they do not
# overlap: as separate arrays, each row paid about 25 instructions of run-time overlap checks
# (forward 0.87–0.88 and backward 0.89–0.91 of their time without them, the same bits). The
# backward's lane sums, indexed [term, i], stay apart: in the same allocation their distance
# from row r varies, and the row loop went scalar.
# Most rows a splat covers in a tile are narrow: at 50k Gaussians and 128², two in three of the
# rows with a live pixel lie within 8 columns, three in four once stopped pixels are left out.
# Such a row is one 8-lane loop, one AVX2 vector of float32, instead of two. LLVM's loop
# vectorizer leaves loops of under 16 iterations scalar unless told (cubecloud_cli/numerics/jit.py).
NARROW = 8


# 2^i for column i, as the backward's row loops test a column's bit of a mask: a module constant,
# which numba compiles into read-only data, so that LLVM knows no tile array overlaps it (a
# tile-local table cost the row loops a run-time overlap check each).
LANE_FLAGS = (1 << np.arange(TILE)).astype(np.int32)


# Entries ahead whose Gaussians are fetched into the cache while the current one blends: an
# entry takes a few hundred cycles, about as long as a read from the last-level cache.
PREFETCH_AHEAD = 4


@njit(cache=True, inline="always")
def prefetch_gaussian(g, bounds, means2d, conics, colours, opacities, levels):
    """Start reading Gaussian ``g``'s rows of the arrays an entry reads (tile lists index them in
    depth order, which is no order in memory)."""
    prefetch(bounds, g)
    prefetch(means2d, g)
    prefetch(conics, g)
    prefetch(colours, g)
    prefetch(opacities, g)
    prefetch(levels, g)


def single_precision(like):
    """Whether ``like`` (a float scalar) is float32: a constant of the compiled function."""
    return np.asarray(like).dtype == np.float32


@overload(single_precision)
def _single_precision(like):
    single = like == types.float32
    return lambda like: single


@njit(cache=True, fastmath=FASTMATH, inline="always")
def exp_negative(power):
    """exp(−power) for 0 ≤ power ≤ 6 in power's precision, without a branch or a table: Taylor's
    polynomial of exp(−power/32) in Estrin's form, squared five times; degree 9 in float64,
    degree 6 in float32, whose truncation (below 2e-9) is far under its rounding. Relative error
    below 1e-12 in float64; below 5e-6 in float32, where the squarings double the rounding error
    five times (far under the 1/255 steps that decide which pairs count)."""
    x = power * as_real(1.0 / 32.0, power)
    x2 = x * x
    x4 = x2 * x2
    low = fused_multiply_add(
        x2, fused_multiply_add(x, as_real(-1.0 / 6.0, power), as_real(0.5, power)), as_real(1.0, power) - x
    )
    middle = fused_multiply_add(x, as_real(-1.0 / 120.0, power), as_real(1.0 / 24.0, power))
    if single_precision(power):
        e = fused_multiply_add(x4, fused_multiply_add(x2, as_real(1.0 / 720.0, power), middle), low)
    else:
        middle = fused_multiply_add(
            x2, fused_multiply_add(x, as_real(-1.0 / 5040.0, power), as_real(1.0 / 720.0, power)), middle
        )
        high = fused_multiply_add(x, as_real(-1.0 / 362880.0, power), as_real(1.0 / 40320.0, power))
        e = fused_multiply_add(x4, fused_multiply_add(x4, high, middle), low)
    e = e * e  # written out, not a loop: an inner loop would keep the caller's loop from SIMD
    e = e * e
    e = e * e
    e = e * e
    return e * e


@njit(cache=True, inline="always")
def narrow_window(columns):
    """The first column of a NARROW-pixel window over every set bit of ``columns`` (a non-zero
    bit mask of a tile row of any integer type, bit i for column i), or −1 where they span more
    than NARROW columns."""
    columns = np.int64(columns)  # leading_zeros counts within the argument's own width
    lowest = trailing_zeros(columns)
    highest = 63 - leading_zeros(columns)
    return min(lowest, TILE - NARROW) if highest - lowest < NARROW else -1


# Each tile column as a float of either precision, read by the row loops from read-only data (as
# LANE_FLAGS is) for a pixel's dx = dx0 + column: one rounding in every row loop. A float counter
# stepped by one, as the loops kept before, is an induction that ``reassoc`` lets LLVM rewrite as
# (dx0 + window) + lane: two roundings where the window is not 0, which gave the 8-pixel loop
# other bits than the 16-pixel one (one ulp of dx, some thirty of a pair's weight through the
# exp's squarings). A conversion from int32 in each lane also gives one rounding, and made the
# kernels 4-6 % slower.
COLUMNS_32 = np.arange(TILE, dtype=np.float32)
COLUMNS_64 = np.arange(TILE, dtype=np.float64)


def column_offset(column, like):
    """Tile column ``column`` as a number of ``like``'s float type, exactly."""
    return np.asarray(like).dtype.type(column)


@overload(column_offset, inline="always")
def _column_offset(column, like):
    table = COLUMNS_32 if like == types.float32 else COLUMNS_64
    return lambda column, like: table[column]


@njit(cache=True, fastmath=FASTMATH, inline="always")
def polynomial_falloff(power):
    """exp(−power) of a pair, for Gaussians whose power level is within the polynomial's range."""
    return exp_negative(min(power, as_real(EXP_POLYNOMIAL_LIMIT, power)))


@njit(cache=True, fastmath=FASTMATH, inline="always")
def exact_falloff(power):
    """exp(−power) by libm, for the rare Gaussian beyond the polynomial's range. A separate
    function rather than a branch in the pixel loop: a call there would keep it from SIMD."""
    return np.exp(-power)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def quadratic_power(dx_dx, dx_dy, dy_dy, a, b, c):
    """½(a·dx² + c·dy²) + b·dx·dy, unclamped, from the three products: one expression for the
    forward's α and the backward's gradient gate, so that both read the same power."""
    return fused_multiply_add(as_real(0.5, dx_dx), fused_multiply_add(a, dx_dx, c * dy_dy), b * dx_dy)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def pair_alpha(dx, dy, a, b, c, opacity, falloff):
    """A pair's power (clamped at 0), Gaussian falloff exp(−power) and α = min(0.99, o·falloff)."""
    zero = as_real(0.0, dx)
    dx_dx, dx_dy, dy_dy = dx * dx, dx * dy, dy * dy
    power = max(quadratic_power(dx_dx, dx_dy, dy_dy, a, b, c), zero)
    gaussian = falloff(power)
    return power, gaussian, min(as_real(MAX_ALPHA, dx), opacity * gaussian)


@njit(cache=True, fastmath=FASTMATH, inline="always")
def blend_row(
    transmittance, colour, weights, r, window, lanes, low, high, dx0, dy, a, b, c, cut, opacity, colour_0, falloff
):  # fmt: skip
    """Blend one Gaussian into columns ``window`` to ``window + lanes − 1`` of row ``r`` of a tile,
    where its box spans dx ∈ [low, high]; ``lanes`` is a constant (TILE or NARROW).
    Channel 0 is blended here; ``weights[r]`` keeps each pixel's T·α (0 where not blended) for
    the caller's other channels and its mask of blended pixels. A pixel that stops keeps −T (its
    transmittance before the stop), so the sign says which pixels are live (``row_masks``)."""
    zero, one = as_real(0.0, dx0), as_real(1.0, dx0)
    min_alpha, stop_level = as_real(MIN_ALPHA, dx0), as_real(TRANSMITTANCE_STOP, dx0)
    for lane in range(lanes):
        i = np.uint64(window + lane)  # unsigned: no wrap-around test, which would keep the loop scalar
        dx = dx0 + column_offset(i, dx0)
        before = transmittance[r, i]
        power, _, alpha = pair_alpha(dx, dy, a, b, c, opacity, falloff)
        valid = (dx >= low) & (dx <= high) & (power <= cut) & (alpha >= min_alpha) & (before > zero)
        after = before * (one - alpha)
        stop = valid & (after < stop_level)
        blend = valid & (after >= stop_level)
        weight = before * alpha if blend else zero
        transmittance[r, i] = -before if stop else (after if blend else before)
        colour[r, i] = fused_multiply_add(weight, colour_0, colour[r, i])
        weights[r, i] = weight


@njit(cache=True, inline="always")
def row_masks(transmittance, weights, r, live):
    """After ``blend_row`` over a whole row: the bit masks of the columns that stopped (T now
    negative, among the ``live`` columns under the splat) and of those blended (T·α > 0).
    Taken from the row by a vector compare after the loop rather than summed inside it, which
    cost each row two horizontal reductions."""
    return negative_lanes_16(transmittance, r, 0) & live, positive_lanes_16(weights, r, 0)


@njit(cache=True, inline="always")
def narrow_row_masks(transmittance, weights, r, window, live):
    """``row_masks`` after ``blend_row`` over the NARROW columns from ``window``."""
    stopped = (negative_lanes_8(transmittance, r, window) << window) & live
    return stopped, positive_lanes_8(weights, r, window) << window


@njit(cache=True, fastmath=FASTMATH)
def blend_row_exactly(transmittance, colour, weights, r, low, high, dx0, dy, a, b, c, cut, opacity, colour_0):
    """``blend_row`` over the whole row with libm's exp, out of line: a second inlined copy of the
    row loop for a Gaussian outside the [0, 1] opacity contract would double the kernel's first
    compilation."""
    blend_row(
        transmittance, colour, weights, r, 0, TILE, low, high, dx0, dy, a, b, c, cut, opacity, colour_0, exact_falloff
    )  # fmt: skip


@njit(parallel=PRANGE_ONLY, cache=True, fastmath=FASTMATH)
def forward(offsets, entries, bounds, means2d, conics, colours, opacities, levels, background, width, height, tiles_x):
    """Gaussian-major within each tile: every entry, front to back, visits only the rows of its
    box, so the work follows the pair count rather than pixels × entries.

    ``blended_entries`` lists, per tile from its offset on, the entries that blended a pixel, front
    to back, ``blended_counts`` of them: the entries the backward walks, back to front, without a
    branch per entry (three in four blend nothing, in no order a predictor learns). An entry is
    listed by a store and a count, not a branch, too. ``blended_rows`` is, per entry, a bit per
    tile row where it blended a pixel (0: none), and ``blended_pixels[entry, row]`` that row's bit
    per blended column, written for the rows the entry visited and read only where the row's bit
    is: the pairs the backward undoes, exactly these.
    Recomputing them there instead let a pair at the α threshold round to the other side now and
    then, the two kernels being optimised apart (docs/history/rasterizer-speed.md).

    One body on purpose: the per-tile state (transmittance, the bit masks of live pixels) lives in
    the body of the parallel loop over tiles, which numba compiles as one kernel."""
    channels = colours.shape[1]
    real = conics.dtype
    image = np.zeros((height * width, channels), dtype=real)
    final_transmittance = np.ones(height * width, dtype=real)
    blended_entries = np.empty(entries.size, dtype=np.int32)
    blended_counts = np.zeros(offsets.size - 1, dtype=np.int64)
    blended_rows = np.zeros(entries.size, dtype=np.int32)
    blended_pixels = np.empty((entries.size, TILE), dtype=np.uint16)
    for tile in prange(offsets.size - 1):
        start, end = offsets[tile], offsets[tile + 1]
        ty, tx = tile // tiles_x, tile % tiles_x
        left, top = tx * TILE, ty * TILE
        right, bottom = min(width, left + TILE) - 1, min(height, top + TILE) - 1
        state = np.zeros((3 * TILE, TILE), dtype=real)  # the row loops' arrays: see "How the pixel loops stay SIMD"
        # > 0: live; < 0: stopped, holding −T before the stop; 0: beyond the image's edge.
        transmittance = state[:TILE]
        for r in range(bottom - top + 1):
            for i in range(right - left + 1):
                transmittance[r, i] = 1.0
        colour = state[TILE : 2 * TILE]  # channel 0; the others, rarely used, apart
        weights = state[2 * TILE :]  # by row, as the others: row r's lie a constant distance from its T
        other_colours = np.zeros((channels, TILE, TILE), dtype=real)
        live_columns = np.full(TILE, (1 << TILE) - 1, dtype=np.int64)  # per row, a bit per live pixel
        tile_pixels = alive = (right - left + 1) * (bottom - top + 1)
        listed = start  # where the next entry that blends is listed
        for k in range(start, end):
            if alive == 0:
                break
            prefetch_gaussian(
                entries[min(k + PREFETCH_AHEAD, end - 1)], bounds, means2d, conics, colours, opacities, levels
            )
            g = entries[k]
            cut = as_real(levels[g] + LEVEL_MARGIN, conics)
            u, v, opacity = means2d[g, 0], means2d[g, 1], as_real(opacities[g], conics)
            a, b, c, colour_0 = conics[g, 0], conics[g, 1], conics[g, 2], as_real(colours[g, 0], conics)
            first, final = max(left, bounds[g, 0]) - left, min(right, bounds[g, 1]) - left
            columns = ((1 << (final - first + 1)) - 1) << first
            dx0 = as_real(left + 0.5 - u, conics)
            # Half a pixel of slack: dx steps by 1, and its rounding must not drop an edge column.
            low, high = dx0 + as_real(first - 0.5, conics), dx0 + as_real(final + 0.5, conics)
            rows_blended = 0
            y_first, y_final = max(top, bounds[g, 2]) - top, min(bottom, bounds[g, 3]) - top
            # the rows of its box (none where the box misses the tile: never, as binned, but a
            # shift by a negative count is undefined)
            visit = ((1 << (y_final - y_first + 1)) - 1) << y_first if y_final >= y_first else 0
            if alive < tile_pixels:
                # Once pixels stop, only the rows with a live pixel under it, as a bit mask taken
                # without a branch a row (a row whose pixels have all stopped comes in no pattern
                # a predictor learns). A row's mask changes only while that row is blended.
                live_rows = 0
                for r in range(TILE):
                    live_rows |= np.int64(live_columns[r] & columns != 0) << r
                visit &= live_rows
            while visit:
                r = trailing_zeros(visit)
                visit &= visit - 1
                py = top + r
                live = live_columns[r] & columns
                dy = as_real(py + 0.5 - v, conics)
                window = narrow_window(live)
                if levels[g] > EXP_POLYNOMIAL_LIMIT:
                    blend_row_exactly(
                        transmittance, colour, weights, r, low, high, dx0, dy, a, b, c, cut, opacity, colour_0
                    )  # fmt: skip
                    stopped, blended = row_masks(transmittance, weights, r, live)
                elif window >= 0 and channels == 1:
                    blend_row(
                        transmittance, colour, weights, r, window, NARROW, low, high, dx0, dy, a, b, c, cut, opacity, colour_0, polynomial_falloff
                    )  # fmt: skip
                    stopped, blended = narrow_row_masks(transmittance, weights, r, window, live)
                else:
                    blend_row(
                        transmittance, colour, weights, r, 0, TILE, low, high, dx0, dy, a, b, c, cut, opacity, colour_0, polynomial_falloff
                    )  # fmt: skip
                    stopped, blended = row_masks(transmittance, weights, r, live)
                # without a branch: a row blends in no pattern a predictor learns (one in four)
                rows_blended |= (blended != 0) << r
                blended_pixels[k, r] = blended
                for ch in range(1, channels):
                    for i in range(TILE):
                        other_colours[ch, r, i] += weights[r, i] * colours[g, ch]
                if stopped:  # rare: each pixel stops once
                    live_columns[r] &= ~stopped
                while stopped:
                    stopped &= stopped - 1
                    alive -= 1
            blended_rows[k] = rows_blended
            blended_entries[listed] = k  # kept only if it blended: the next entry's overwrites it
            listed += rows_blended != 0
        blended_counts[tile] = listed - start
        for py in range(top, bottom + 1):
            for px in range(left, right + 1):
                r, i = py - top, px - left
                pixel = py * width + px
                remaining = abs(transmittance[r, i])
                image[pixel, 0] = colour[r, i] + remaining * background[0]
                for ch in range(1, channels):
                    image[pixel, ch] = other_colours[ch, r, i] + remaining * background[ch]
                final_transmittance[pixel] = remaining
    return image, final_transmittance, blended_entries, blended_counts, blended_rows, blended_pixels


@njit(cache=True, fastmath=FASTMATH, inline="always", error_model="numpy")
def unblend_pair(after, valid, dx, dy, a, b, c, opacity, falloff):
    """Undo one pair, back to front, from the pixel's T after it and whether the forward blended
    it: T before it and its weight T·α (both 0 if not blended), 1 / (1 − α), the Gaussian falloff
    and the unclamped o·falloff.
    Scalars in and out: an array passed to a helper inside the pixel loop costs reference counting
    calls there, and a call keeps the loop from SIMD."""
    zero, one = as_real(0.0, dx), as_real(1.0, dx)
    _, gaussian, alpha = pair_alpha(dx, dy, a, b, c, opacity, falloff)
    survive = one / (one - alpha)
    before = after * survive if valid else zero
    return before, before * alpha, survive, gaussian, opacity * gaussian


@njit(cache=True, fastmath=FASTMATH, inline="always")
def pair_power_gradient(grad_alpha, raw, dx_dx, dx_dy, dy_dy, a, b, c):
    """A pair's gradient with respect to its power, and with respect to its α where α moves
    (not clamped at 0.99), from the loss's gradient with respect to its α. Where the power is
    clamped at 0 the conic and mean do not move either."""
    zero = as_real(0.0, dx_dx)
    moving = grad_alpha if raw <= as_real(MAX_ALPHA, dx_dx) else zero
    return (-moving * raw if quadratic_power(dx_dx, dx_dy, dy_dy, a, b, c) > zero else zero), moving


@njit(cache=True, fastmath=FASTMATH, inline="always")
def pair_geometry_gradients(grad_alpha, gaussian, raw, dx, dy, a, b, c):
    """A pair's share of the gradients of mean2d (2), conic (3) and opacity, from the loss's
    gradient with respect to its α. The conic's a and c terms are twice theirs
    (∂power/∂a = dx²/2): the caller halves their sums once, exactly.

    Each conic term is a product of two values that have other uses (dx², dx·dy, dy² also make
    the power), which reassociation cannot regroup. As products of three or four factors, LLVM
    grouped them one way in the kernel numba compiles in the process and another way in the copy
    it loads from its cache, and a seeded run from an empty cache ended on other bits
    (cubecloud_cli/numerics/jit.py)."""
    dx_dx, dx_dy, dy_dy = dx * dx, dx * dy, dy * dy
    grad_power, moving = pair_power_gradient(grad_alpha, raw, dx_dx, dx_dy, dy_dy, a, b, c)
    return (
        -grad_power * fused_multiply_add(a, dx, b * dy),
        -grad_power * fused_multiply_add(c, dy, b * dx),
        grad_power * dx_dx,
        grad_power * dx_dy,
        grad_power * dy_dy,
        moving * gaussian,
    )


@njit(cache=True, fastmath=FASTMATH, inline="always")
def added(sums, terms):
    """Six running gradient sums plus one pair's six terms."""
    return (
        sums[0] + terms[0], sums[1] + terms[1], sums[2] + terms[2],
        sums[3] + terms[3], sums[4] + terms[4], sums[5] + terms[5],
    )  # fmt: skip


@njit(cache=True, fastmath=FASTMATH, inline="always", error_model="numpy")
def unblend_grey_row(transmittance, behind, tile_grad, r, pixels, dx0, dy, a, b, c, opacity, colour_0, falloff):
    """One Gaussian's gradients over row ``r`` of a tile of one channel, back to front, at the
    columns of the bit mask ``pixels`` (those it blended): the sums for mean2d (2), conic (3),
    opacity and colour. ``behind`` is the colour composited behind it."""
    zero = as_real(0.0, dx0)
    sums = (zero, zero, zero, zero, zero, zero)  # mean2d (2), conic (3), opacity
    g_colour = zero
    for i in range(TILE):
        dx = dx0 + column_offset(i, dx0)
        valid = pixels & LANE_FLAGS[i] != 0
        before, weight, survive, gaussian, raw = unblend_pair(
            transmittance[r, i], valid, dx, dy, a, b, c, opacity, falloff
        )
        transmittance[r, i] = before if valid else transmittance[r, i]
        grad = tile_grad[r, i]
        grad_alpha = grad * (before * colour_0 - behind[r, i] * survive) if valid else zero
        g_colour += weight * grad
        behind[r, i] += weight * colour_0
        sums = added(sums, pair_geometry_gradients(grad_alpha, gaussian, raw, dx, dy, a, b, c))
    return sums[0], sums[1], sums[2], sums[3], sums[4], sums[5], g_colour


@njit(cache=True, fastmath=FASTMATH, inline="always", error_model="numpy")
def unblend_grey_row_into_lanes(
    transmittance, behind, tile_grad, lanes, r, window, width, pixels, dx0, dy, a, b, c, opacity, colour_0
):  # fmt: skip
    """``unblend_grey_row`` with the polynomial exp over columns ``window`` to ``window + width − 1``
    (``width`` a constant, TILE or NARROW), adding each pixel's seven terms into its column's lane
    of ``lanes`` (7 × 16) instead of summing the row: the entry's sums are then taken across
    lanes once, after its last row, rather than seven times a row. A column's bit is tested in
    int32, as wide as a float32 lane."""
    zero = as_real(0.0, dx0)
    for lane in range(width):
        i = np.uint64(window + lane)  # unsigned: no wrap-around test, which would keep the loop scalar
        dx = dx0 + column_offset(i, dx0)
        valid = pixels & LANE_FLAGS[i] != 0
        before, weight, survive, gaussian, raw = unblend_pair(
            transmittance[r, i], valid, dx, dy, a, b, c, opacity, polynomial_falloff
        )  # fmt: skip
        transmittance[r, i] = before if valid else transmittance[r, i]
        grad = tile_grad[r, i]
        grad_alpha = grad * fused_multiply_add(before, colour_0, -behind[r, i] * survive) if valid else zero
        behind[r, i] = fused_multiply_add(weight, colour_0, behind[r, i])
        dx_dx, dx_dy, dy_dy = dx * dx, dx * dy, dy * dy
        grad_power, moving = pair_power_gradient(grad_alpha, raw, dx_dx, dx_dy, dy_dy, a, b, c)
        lanes[0, i] = fused_multiply_add(-grad_power, fused_multiply_add(a, dx, b * dy), lanes[0, i])
        lanes[1, i] = fused_multiply_add(-grad_power, fused_multiply_add(c, dy, b * dx), lanes[1, i])
        lanes[2, i] = fused_multiply_add(grad_power, dx_dx, lanes[2, i])
        lanes[3, i] = fused_multiply_add(grad_power, dx_dy, lanes[3, i])
        lanes[4, i] = fused_multiply_add(grad_power, dy_dy, lanes[4, i])
        lanes[5, i] = fused_multiply_add(moving, gaussian, lanes[5, i])
        lanes[6, i] = fused_multiply_add(weight, grad, lanes[6, i])


@njit(cache=True, fastmath=FASTMATH, error_model="numpy")
def unblend_grey_row_exactly(transmittance, behind, tile_grad, r, pixels, dx0, dy, a, b, c, opacity, colour_0):
    """``unblend_grey_row`` with libm's exp, out of line (as ``blend_row_exactly``)."""
    return unblend_grey_row(
        transmittance, behind, tile_grad, r, pixels, dx0, dy, a, b, c, opacity, colour_0, exact_falloff
    )  # fmt: skip


@njit(cache=True, fastmath=FASTMATH, error_model="numpy")
def unblend_colour_row(
    transmittance, behind, tile_grad, r, pixels, dx0, dy, a, b, c, opacity, colours, exact, colour_grad
):  # fmt: skip
    """``unblend_grey_row`` for several channels (``behind`` and ``tile_grad`` per channel first;
    the colour gradients added into ``colour_grad``; libm's exp where ``exact``). Scalar and out
    of line: RGB scenes are not CT's, and the kernel's first compilation stays short."""
    zero = as_real(0.0, dx0)
    sums = (zero, zero, zero, zero, zero, zero)  # mean2d (2), conic (3), opacity
    for i in range(TILE):
        dx = dx0 + column_offset(i, dx0)
        if pixels & LANE_FLAGS[i] == 0:
            continue
        if exact:
            before, weight, survive, gaussian, raw = unblend_pair(
                transmittance[r, i], True, dx, dy, a, b, c, opacity, exact_falloff
            )  # fmt: skip
        else:
            before, weight, survive, gaussian, raw = unblend_pair(
                transmittance[r, i], True, dx, dy, a, b, c, opacity, polynomial_falloff
            )  # fmt: skip
        transmittance[r, i] = before
        grad_alpha = zero
        for ch in range(colours.size):
            colour = as_real(colours[ch], dx)
            grad_alpha += tile_grad[ch, r, i] * (before * colour - behind[ch, r, i] * survive)
            colour_grad[ch] += weight * tile_grad[ch, r, i]
            behind[ch, r, i] += weight * colour
        sums = added(sums, pair_geometry_gradients(grad_alpha, gaussian, raw, dx, dy, a, b, c))
    return sums


@njit(cache=True)
def number_gradient_rows(offsets, entries, blended_entries, blended_counts, count):
    """Rows for the backward's per-entry gradients, one per entry that blended, grouped by
    Gaussian in index order: Gaussian g's rows are ``gaussian_rows[g]:gaussian_rows[g + 1]``, in the
    order of its tiles, and entry k's row is ``entry_rows[k]`` (entries that blended nothing have
    none). Numbered from the forward's lists of the entries that blended, so that the sums read
    only rows that hold a value, each Gaussian's in one stretch."""
    gaussian_rows = np.zeros(count + 1, dtype=np.int64)
    for tile in range(offsets.size - 1):
        for listed in range(offsets[tile], offsets[tile] + blended_counts[tile]):
            gaussian_rows[entries[blended_entries[listed]] + 1] += 1
    for g in range(count):
        gaussian_rows[g + 1] += gaussian_rows[g]
    fill = gaussian_rows[:-1].copy()
    entry_rows = np.empty(entries.size, dtype=np.int32)
    for tile in range(offsets.size - 1):
        for listed in range(offsets[tile], offsets[tile] + blended_counts[tile]):
            k = blended_entries[listed]
            g = entries[k]
            entry_rows[k] = fill[g]
            fill[g] += 1
    return gaussian_rows, entry_rows


@njit(parallel=PRANGE_ONLY, cache=True, fastmath=FASTMATH, error_model="numpy")
def backward(
    offsets,
    entries,
    bounds,
    means2d,
    conics,
    colours,
    opacities,
    levels,
    background,
    width,
    height,
    tiles_x,
    final_transmittance,
    blended_entries,
    blended_counts,
    blended_rows,
    blended_pixels,
    grad_image,
):
    """Per-entry gradients of the loss with respect to mean2d (2), conic (3), opacity (1) and
    colour (C), one row per entry that blended, grouped by Gaussian (``number_gradient_rows``),
    and each Gaussian's stretch of rows, to be summed per Gaussian afterwards. The entries that
    blended are walked back to front (``blended_entries``), each undoing the pairs the forward
    blended (``blended_rows``, ``blended_pixels``). An entry that blended nothing has no gradient
    and no row: in a dense view most entries are such (three in four at 50k Gaussians, 128²).
    With a row for every entry instead, numbered by the binning, the sums read four times the
    memory, most of it rows never written, and the frame was 3–7 % slower (docs/history/rasterizer-speed.md).

    One body on purpose, as ``forward``: the per-tile state lives in the parallel loop's body."""
    channels = colours.shape[1]
    real = conics.dtype
    gaussian_rows, entry_rows = number_gradient_rows(
        offsets, entries, blended_entries, blended_counts, means2d.shape[0]
    )
    row_grads = np.empty((gaussian_rows[-1], 6 + channels))
    for tile in prange(offsets.size - 1):
        start = offsets[tile]
        ty, tx = tile // tiles_x, tile % tiles_x
        left, top = tx * TILE, ty * TILE
        right, bottom = min(width, left + TILE) - 1, min(height, top + TILE) - 1
        # The row loops' arrays in one allocation, as in forward: T, then one channel's colour from
        # behind the current Gaussian, then its loss gradient (several channels' as 3D arrays apart).
        state = np.zeros((3 * TILE, TILE), dtype=real)
        transmittance = state[:TILE]
        behind = state[TILE : 2 * TILE]
        tile_grad = state[2 * TILE :]
        behind_channels = np.zeros((channels, TILE, TILE), dtype=real)
        grad_channels = np.zeros((channels, TILE, TILE), dtype=real)
        colour_grad = np.zeros(channels, dtype=real)
        lanes = np.zeros((7, TILE), dtype=real)  # an entry's per-pixel gradient terms, by lane
        for py in range(top, bottom + 1):
            for px in range(left, right + 1):
                r, i = py - top, px - left
                pixel = py * width + px
                transmittance[r, i] = final_transmittance[pixel]
                behind[r, i] = final_transmittance[pixel] * background[0]
                tile_grad[r, i] = grad_image[pixel, 0]
                for ch in range(channels if channels > 1 else 0):  # RGB rows read these instead
                    behind_channels[ch, r, i] = final_transmittance[pixel] * background[ch]
                    grad_channels[ch, r, i] = grad_image[pixel, ch]
        for listed in range(start + blended_counts[tile] - 1, start - 1, -1):
            k = blended_entries[listed]
            ahead = blended_entries[max(listed - PREFETCH_AHEAD, start)]
            prefetch_gaussian(entries[ahead], bounds, means2d, conics, colours, opacities, levels)
            rows = blended_rows[k]
            g = entries[k]
            u, v, opacity = means2d[g, 0], means2d[g, 1], as_real(opacities[g], conics)
            a, b, c, colour_0 = conics[g, 0], conics[g, 1], conics[g, 2], as_real(colours[g, 0], conics)
            dx0 = as_real(left + 0.5 - u, conics)
            exact = levels[g] > EXP_POLYNOMIAL_LIMIT
            first, final = max(left, bounds[g, 0]) - left, min(right, bounds[g, 1]) - left
            halves = 1 if final - first < NARROW else 2
            window = min(first, TILE - NARROW) if halves == 1 else 0
            # Sums over this entry's pixels, kept in registers and written to its row once.
            entry_sums = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # mean2d (2), conic (3), opacity
            g_colour_0 = 0.0
            colour_grad[:] = 0.0
            while rows:  # the rows where it blended a pixel in the forward, top to bottom
                r = trailing_zeros(rows)
                rows &= rows - 1
                py = top + r
                pixels = np.int32(blended_pixels[k, r])
                dy = as_real(py + 0.5 - v, conics)
                if channels > 1:
                    sums = unblend_colour_row(
                        transmittance, behind_channels, grad_channels, r, pixels, dx0, dy, a, b, c, opacity, colours[g], exact, colour_grad
                    )  # fmt: skip
                    entry_sums = added(entry_sums, sums)
                elif exact:
                    grey = unblend_grey_row_exactly(
                        transmittance, behind, tile_grad, r, pixels, dx0, dy, a, b, c, opacity, colour_0
                    )  # fmt: skip
                    entry_sums = added(entry_sums, grey)
                    g_colour_0 += grey[6]
                else:
                    for half in range(halves):  # as in forward: one inlined loop of NARROW pixels
                        unblend_grey_row_into_lanes(
                            transmittance, behind, tile_grad, lanes, r, window + half * NARROW, NARROW, pixels, dx0, dy, a, b, c, opacity, colour_0
                        )  # fmt: skip
            if channels == 1 and not exact:
                lane_sums = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
                for i in range(TILE):
                    lane_sums = added(
                        lane_sums, (lanes[0, i], lanes[1, i], lanes[2, i], lanes[3, i], lanes[4, i], lanes[5, i])
                    )
                    g_colour_0 += lanes[6, i]
                    for j in range(7):
                        lanes[j, i] = 0.0
                entry_sums = added(entry_sums, lane_sums)
            row = entry_rows[k]
            for j in range(6):
                row_grads[row, j] = entry_sums[j] * (0.5 if j == 2 or j == 4 else 1.0)  # see pair_geometry_gradients
            if channels == 1:
                row_grads[row, 6] = g_colour_0
            else:
                for ch in range(channels):
                    row_grads[row, 6 + ch] = colour_grad[ch]
    return row_grads, gaussian_rows
