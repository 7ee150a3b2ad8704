"""The fast CPU rasterizer: numba kernels, parallel over 16×16 tiles, with a hand-written backward.

Same rules and the same pairs as the PyTorch oracle (``pairs.py``): each splat covers the pixels
of its 3σ square, Gaussians are composited front to back in the oracle's depth order, α ≤ 0.99,
pairs with α < 1/255 are skipped, and a pixel stops before its transmittance would fall below
1e-4. Arithmetic is float64 inside the kernels; inputs may be float32 or float64.

What makes them fast on two cores (``bench/raster.py``): within a tile each Gaussian visits only
its own pixels (work ∝ pairs, not pixels × Gaussians); a pair beyond the α = 1/255 ellipse is
rejected before any exp, and the exp is inline (a table and a short polynomial, not a libm
call); rows whose pixels have all stopped are skipped by a bit mask; the backward skips entries
that blended nothing.

Backward walks each pixel's list back to front (as the reference CUDA code does), recovering the
transmittance before each Gaussian by division by (1 − α) ≥ 0.01. Gradients go into one row per
(tile, Gaussian) entry, numbered Gaussian-major by the binning, so threads never write the same
memory and the per-Gaussian sums read contiguous rows.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from cubecloud_cli.jit import PRANGE_ONLY
from cubecloud_cli.raster.constants import MAX_ALPHA, MIN_ALPHA, TILE, TRANSMITTANCE_STOP

# Pairs with power > ln(255·o) have α < 1/255; the margin leaves exact ties to the α test.
LEVEL_MARGIN = 1e-9


# exp(−i/16) for the table-driven exp below; powers beyond ln 255 < 6 are never evaluated.
EXP_STEPS_PER_UNIT = 16
EXP_TABLE_LIMIT = 6.0
EXP_TABLE = np.exp(-np.arange(int(EXP_TABLE_LIMIT) * EXP_STEPS_PER_UNIT + 2) / EXP_STEPS_PER_UNIT)


@njit(cache=True, fastmath=True, inline="always")
def pair_gaussian(power):
    """exp(−power) for the kernels' pairs: inline below 6, libm beyond (reached only with
    opacities above e⁶/255 ≈ 1.6, outside the [0, 1] contract, but then still right)."""
    return exp_negative(power) if power <= EXP_TABLE_LIMIT else np.exp(-power)


@njit(cache=True, fastmath=True, inline="always")
def exp_negative(power):
    """exp(−power) for 0 ≤ power ≤ 6: exp(−i/16) from a table times exp(−r), r < 1/16, by a
    degree-6 polynomial in Estrin's form (relative error below 1e-12). Inline arithmetic with a
    short dependency chain instead of a libm call, which was the largest cost of a pair."""
    scaled = power * EXP_STEPS_PER_UNIT
    index = np.int64(scaled)
    r = (scaled - index) * (1.0 / EXP_STEPS_PER_UNIT)
    r2 = r * r
    tail = (1.0 / 24.0 - r * (1.0 / 120.0)) + r2 * (1.0 / 720.0)
    polynomial = (1.0 - r) + r2 * ((0.5 - r * (1.0 / 6.0)) + r2 * tail)
    return EXP_TABLE[index] * polynomial


@njit(parallel=PRANGE_ONLY, cache=True, fastmath=True)
def forward(offsets, entries, bounds, means2d, conics, colours, opacities, levels, background, width, height, tiles_x):
    """Gaussian-major within each tile: every entry, front to back, visits only the tile's pixels
    inside its square, so the work is the pair count rather than pixels × entries.

    ``last`` is, per pixel, the entry where the backward pass starts: the entry at which the pixel
    stopped (not blended), else the tile's end. Any entry before it with α ≥ 1/255 was blended.

    One body on purpose: the per-tile state (transmittance, the bit masks of live pixels) lives in
    the body of the parallel loop over tiles, which numba compiles as one kernel."""
    channels = colours.shape[1]
    image = np.zeros((height * width, channels))
    final_transmittance = np.ones(height * width)
    last = np.zeros(height * width, dtype=np.int64)
    blended = np.zeros(entries.size, dtype=np.bool_)  # entries that blended any pixel
    for tile in prange(offsets.size - 1):
        start, end = offsets[tile], offsets[tile + 1]
        ty, tx = tile // tiles_x, tile % tiles_x
        left, top = tx * TILE, ty * TILE
        right, bottom = min(width, left + TILE) - 1, min(height, top + TILE) - 1
        # live_transmittance is 0 once a pixel has stopped; its final value is kept apart.
        live_transmittance = np.ones(TILE * TILE)
        stopped_transmittance = np.zeros(TILE * TILE)
        colour = np.zeros((TILE * TILE, channels))
        last_entry = np.full(TILE * TILE, end)  # where the backward pass starts, per pixel
        live_columns = np.full(TILE, (1 << TILE) - 1, dtype=np.int64)  # per row, a bit per live pixel
        alive = (right - left + 1) * (bottom - top + 1)
        for k in range(start, end):
            if alive == 0:
                break
            g = entries[k]
            u, v, opacity = means2d[g, 0], means2d[g, 1], opacities[g]
            a, b, c, level = conics[g, 0], conics[g, 1], conics[g, 2], levels[g]
            colour_0 = colours[g, 0]
            x0, x1 = max(left, bounds[g, 0]), min(right, bounds[g, 1])
            columns = ((1 << (x1 - x0 + 1)) - 1) << (x0 - left)
            for py in range(max(top, bounds[g, 2]), min(bottom, bounds[g, 3]) + 1):
                if live_columns[py - top] & columns == 0:
                    continue  # every pixel of this row under the splat has stopped
                dy = py + 0.5 - v
                row = (py - top) * TILE - left
                for px in range(x0, x1 + 1):
                    local = row + px
                    before = live_transmittance[local]
                    if before == 0.0:
                        continue
                    dx = px + 0.5 - u
                    power = max(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy, 0.0)
                    if power > level + LEVEL_MARGIN:
                        continue
                    alpha = min(MAX_ALPHA, opacity * pair_gaussian(power))
                    if alpha < MIN_ALPHA:
                        continue
                    after = before * (1.0 - alpha)
                    if after < TRANSMITTANCE_STOP:
                        stopped_transmittance[local] = before
                        live_transmittance[local] = 0.0
                        last_entry[local] = k
                        live_columns[py - top] &= ~(1 << (px - left))
                        alive -= 1
                        continue
                    weight = before * alpha
                    blended[k] = True
                    if channels == 1:
                        colour[local, 0] += weight * colour_0
                    else:
                        for ch in range(channels):
                            colour[local, ch] += weight * colours[g, ch]
                    live_transmittance[local] = after
        for py in range(top, bottom + 1):
            for px in range(left, right + 1):
                local = (py - top) * TILE + (px - left)
                pixel = py * width + px
                transmittance = live_transmittance[local] + stopped_transmittance[local]
                for ch in range(channels):
                    image[pixel, ch] = colour[local, ch] + transmittance * background[ch]
                final_transmittance[pixel] = transmittance
                last[pixel] = last_entry[local]
    return image, final_transmittance, last, blended


@njit(parallel=PRANGE_ONLY, cache=True, fastmath=True)
def backward(
    offsets,
    entries,
    slots,
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
    last,
    blended,
    grad_image,
):
    """Per-entry gradients of the loss with respect to mean2d (2), conic (3), opacity (1) and
    colour (C), summed per Gaussian afterwards. Entries are walked back to front; each pixel
    starts at its last blended entry.

    One body on purpose, as ``forward``: the per-tile state lives in the parallel loop's body."""
    channels = colours.shape[1]
    slot_grads = np.zeros((entries.size, 6 + channels))
    for tile in prange(offsets.size - 1):
        start = offsets[tile]
        ty, tx = tile // tiles_x, tile % tiles_x
        left, top = tx * TILE, ty * TILE
        right, bottom = min(width, left + TILE) - 1, min(height, top + TILE) - 1
        transmittance = np.ones(TILE * TILE)
        behind = np.zeros((TILE * TILE, channels))  # colour from behind the current Gaussian
        last_entry = np.zeros(TILE * TILE, dtype=np.int64)
        tile_grad = np.zeros((TILE * TILE, channels))
        colour_grad = np.zeros(channels)
        for py in range(top, bottom + 1):
            for px in range(left, right + 1):
                local = (py - top) * TILE + (px - left)
                pixel = py * width + px
                transmittance[local] = final_transmittance[pixel]
                last_entry[local] = last[pixel]
                for ch in range(channels):
                    behind[local, ch] = final_transmittance[pixel] * background[ch]
                    tile_grad[local, ch] = grad_image[pixel, ch]
        row_latest = np.zeros(TILE, dtype=np.int64)  # per row, the largest last_entry
        for local in range(TILE * TILE):
            row_latest[local // TILE] = max(row_latest[local // TILE], last_entry[local])
        latest = start
        for r in range(TILE):
            latest = max(latest, row_latest[r])
        for k in range(latest - 1, start - 1, -1):
            if not blended[k]:  # its gradients are all zero
                continue
            g = entries[k]
            u, v, opacity = means2d[g, 0], means2d[g, 1], opacities[g]
            a, b, c, level = conics[g, 0], conics[g, 1], conics[g, 2], levels[g]
            colour_0 = colours[g, 0]
            x0, x1 = max(left, bounds[g, 0]), min(right, bounds[g, 1])
            # Sums over this entry's pixels, kept in registers and written to its slot once.
            g_u = g_v = g_a = g_b = g_c = g_opacity = g_colour_0 = 0.0
            colour_grad[:] = 0.0
            for py in range(max(top, bounds[g, 2]), min(bottom, bounds[g, 3]) + 1):
                if k >= row_latest[py - top]:
                    continue  # every pixel of this row stopped before this entry
                dy = py + 0.5 - v
                row = (py - top) * TILE - left
                for px in range(x0, x1 + 1):
                    local = row + px
                    if k >= last_entry[local]:
                        continue
                    dx = px + 0.5 - u
                    raw_power = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                    power = max(raw_power, 0.0)
                    if power > level + LEVEL_MARGIN:
                        continue
                    gaussian = pair_gaussian(power)
                    raw = opacity * gaussian
                    alpha = min(MAX_ALPHA, raw)
                    if alpha < MIN_ALPHA:
                        continue
                    survive = 1.0 / (1.0 - alpha)
                    before = transmittance[local] * survive
                    transmittance[local] = before
                    weight = before * alpha
                    if channels == 1:
                        grad_alpha = tile_grad[local, 0] * (before * colour_0 - behind[local, 0] * survive)
                        g_colour_0 += weight * tile_grad[local, 0]
                        behind[local, 0] += weight * colour_0
                    else:
                        grad_alpha = 0.0
                        for ch in range(channels):
                            grad_alpha += tile_grad[local, ch] * (before * colours[g, ch] - behind[local, ch] * survive)
                            colour_grad[ch] += weight * tile_grad[local, ch]
                            behind[local, ch] += weight * colours[g, ch]
                    if raw <= MAX_ALPHA:  # above it α is clamped and does not move
                        g_opacity += grad_alpha * gaussian
                        if raw_power > 0.0:
                            grad_power = -grad_alpha * raw
                            g_u -= grad_power * (a * dx + b * dy)
                            g_v -= grad_power * (c * dy + b * dx)
                            g_a += grad_power * 0.5 * dx * dx
                            g_b += grad_power * dx * dy
                            g_c += grad_power * 0.5 * dy * dy
            slot = slots[k]
            slot_grads[slot, 0], slot_grads[slot, 1], slot_grads[slot, 2] = g_u, g_v, g_a
            slot_grads[slot, 3], slot_grads[slot, 4], slot_grads[slot, 5] = g_b, g_c, g_opacity
            if channels == 1:
                colour_grad[0] = g_colour_0
            for ch in range(channels):
                slot_grads[slot, 6 + ch] = colour_grad[ch]
    return slot_grads
