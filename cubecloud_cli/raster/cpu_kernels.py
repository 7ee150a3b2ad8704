"""The fast CPU rasterizer: numba kernels, parallel over 16×16 tiles, with a hand-written backward.

Same rules and the same pairs as the PyTorch oracle (``pairs.py``): each splat covers the pixels
of its 3σ square, Gaussians are composited front to back in the oracle's depth order, α ≤ 0.99,
pairs with α < 1/255 are skipped, and a pixel stops before its transmittance would fall below
1e-4. Arithmetic is float64 inside the kernels.

Backward walks each pixel's list back to front (as the reference CUDA code does), recovering the
transmittance before each Gaussian by division by (1 − α) ≥ 0.01. Gradients go into one slot per
(tile, Gaussian) entry, so threads never write the same memory, and are summed per Gaussian
afterwards.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

TILE = 16
MAX_ALPHA = 0.99
MIN_ALPHA = 1.0 / 255.0
TRANSMITTANCE_STOP = 1e-4


@njit(cache=True)
def stable_depth_order(candidates, depths):
    """``candidates`` sorted by depth, ties kept in index order: an LSD radix sort on the float64
    bits (sign-flipped so that integer order is float order), linear in the count."""
    count = candidates.size
    keys = np.empty(count, dtype=np.uint64)
    sign = np.uint64(1) << np.uint64(63)
    for i in range(count):
        value = depths[candidates[i]] + 0.0  # turns −0 into +0, which compares equal to it
        bits = np.float64(value).view(np.uint64)
        keys[i] = ~bits if bits & sign else bits | sign
    order = candidates.copy()
    scratch_keys = np.empty_like(keys)
    scratch_order = np.empty_like(order)
    counts = np.zeros(2049, dtype=np.int64)
    for shift in range(0, 64, 11):  # six passes of 11 bits
        counts[:] = 0
        for i in range(count):
            counts[((keys[i] >> np.uint64(shift)) & np.uint64(0x7FF)) + 1] += 1
        for b in range(2048):
            counts[b + 1] += counts[b]
        for i in range(count):
            digit = (keys[i] >> np.uint64(shift)) & np.uint64(0x7FF)
            position = counts[digit]
            scratch_keys[position] = keys[i]
            scratch_order[position] = order[i]
            counts[digit] = position + 1
        keys, scratch_keys = scratch_keys, keys
        order, scratch_order = scratch_order, order
    return order


@njit(cache=True)
def bin_tiles(candidates, bounds, depths, tiles_x, tiles_y):
    """Per-tile lists of Gaussians, front to back (CSR: offsets, entries). ``candidates`` are in
    index order; filling the tiles in stable depth order leaves every list sorted."""
    order = stable_depth_order(candidates, depths)
    counts = np.zeros(tiles_x * tiles_y + 1, dtype=np.int64)
    for g in order:
        x0, x1, y0, y1 = bounds[g, 0], bounds[g, 1], bounds[g, 2], bounds[g, 3]
        for ty in range(y0 // TILE, y1 // TILE + 1):
            for tx in range(x0 // TILE, x1 // TILE + 1):
                counts[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(counts)
    entries = np.empty(offsets[-1], dtype=np.int64)
    fill = offsets[:-1].copy()
    for g in order:
        x0, x1, y0, y1 = bounds[g, 0], bounds[g, 1], bounds[g, 2], bounds[g, 3]
        for ty in range(y0 // TILE, y1 // TILE + 1):
            for tx in range(x0 // TILE, x1 // TILE + 1):
                tile = ty * tiles_x + tx
                entries[fill[tile]] = g
                fill[tile] += 1
    return offsets, entries


@njit(parallel=True, cache=True, fastmath=True)
def forward(offsets, entries, bounds, means2d, conics, colours, opacities, background, width, height, tiles_x):
    """Gaussian-major within each tile: every entry, front to back, visits only the tile's pixels
    inside its square, so the work is the pair count rather than pixels × entries."""
    channels = colours.shape[1]
    image = np.zeros((height * width, channels))
    final_transmittance = np.ones(height * width)
    last = np.zeros(height * width, dtype=np.int64)
    for tile in prange(offsets.size - 1):
        start, end = offsets[tile], offsets[tile + 1]
        ty, tx = tile // tiles_x, tile % tiles_x
        left, top = tx * TILE, ty * TILE
        right, bottom = min(width, left + TILE) - 1, min(height, top + TILE) - 1
        transmittance = np.ones(TILE * TILE)
        colour = np.zeros((TILE * TILE, channels))
        done = np.zeros(TILE * TILE, dtype=np.bool_)
        last_entry = np.full(TILE * TILE, start)
        alive = (right - left + 1) * (bottom - top + 1)
        for k in range(start, end):
            if alive == 0:
                break
            g = entries[k]
            u, v, opacity = means2d[g, 0], means2d[g, 1], opacities[g]
            a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
            for py in range(max(top, bounds[g, 2]), min(bottom, bounds[g, 3]) + 1):
                dy = py + 0.5 - v
                for px in range(max(left, bounds[g, 0]), min(right, bounds[g, 1]) + 1):
                    local = (py - top) * TILE + (px - left)
                    if done[local]:
                        continue
                    dx = px + 0.5 - u
                    power = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                    alpha = min(MAX_ALPHA, opacity * np.exp(-max(power, 0.0)))
                    if alpha < MIN_ALPHA:
                        continue
                    after = transmittance[local] * (1.0 - alpha)
                    if after < TRANSMITTANCE_STOP:
                        done[local] = True
                        alive -= 1
                        continue
                    weight = transmittance[local] * alpha
                    for ch in range(channels):
                        colour[local, ch] += weight * colours[g, ch]
                    transmittance[local] = after
                    last_entry[local] = k + 1
        for py in range(top, bottom + 1):
            for px in range(left, right + 1):
                local = (py - top) * TILE + (px - left)
                pixel = py * width + px
                for ch in range(channels):
                    image[pixel, ch] = colour[local, ch] + transmittance[local] * background[ch]
                final_transmittance[pixel] = transmittance[local]
                last[pixel] = last_entry[local]
    return image, final_transmittance, last


@njit(parallel=True, cache=True, fastmath=True)
def backward(offsets, entries, bounds, means2d, conics, colours, opacities, background, width, height, tiles_x,
             final_transmittance, last, grad_image):
    """Per-entry gradients of the loss with respect to mean2d (2), conic (3), opacity (1) and
    colour (C), summed per Gaussian afterwards. Entries are walked back to front; each pixel
    starts at its last blended entry."""
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
        for py in range(top, bottom + 1):
            for px in range(left, right + 1):
                local = (py - top) * TILE + (px - left)
                pixel = py * width + px
                transmittance[local] = final_transmittance[pixel]
                last_entry[local] = last[pixel]
                for ch in range(channels):
                    behind[local, ch] = final_transmittance[pixel] * background[ch]
        latest = start
        for local in range(TILE * TILE):
            latest = max(latest, last_entry[local])
        for k in range(latest - 1, start - 1, -1):
            g = entries[k]
            u, v, opacity = means2d[g, 0], means2d[g, 1], opacities[g]
            a, b, c = conics[g, 0], conics[g, 1], conics[g, 2]
            for py in range(max(top, bounds[g, 2]), min(bottom, bounds[g, 3]) + 1):
                dy = py + 0.5 - v
                for px in range(max(left, bounds[g, 0]), min(right, bounds[g, 1]) + 1):
                    local = (py - top) * TILE + (px - left)
                    if k >= last_entry[local]:
                        continue
                    dx = px + 0.5 - u
                    power = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                    gaussian = np.exp(-max(power, 0.0))
                    raw = opacity * gaussian
                    alpha = min(MAX_ALPHA, raw)
                    if alpha < MIN_ALPHA:
                        continue
                    pixel = py * width + px
                    before = transmittance[local] / (1.0 - alpha)
                    transmittance[local] = before
                    weight = before * alpha
                    grad_alpha = 0.0
                    for ch in range(channels):
                        grad_alpha += grad_image[pixel, ch] * (before * colours[g, ch] - behind[local, ch] / (1.0 - alpha))
                        slot_grads[k, 6 + ch] += weight * grad_image[pixel, ch]
                        behind[local, ch] += weight * colours[g, ch]
                    if raw <= MAX_ALPHA:  # above it α is clamped and does not move
                        slot_grads[k, 5] += grad_alpha * gaussian
                        if power > 0.0:
                            grad_power = -grad_alpha * raw
                            slot_grads[k, 0] += grad_power * -(a * dx + b * dy)
                            slot_grads[k, 1] += grad_power * -(c * dy + b * dx)
                            slot_grads[k, 2] += grad_power * 0.5 * dx * dx
                            slot_grads[k, 3] += grad_power * dx * dy
                            slot_grads[k, 4] += grad_power * 0.5 * dy * dy
    return slot_grads


@njit(cache=True)
def sum_per_gaussian(entries, slot_grads, count):
    grads = np.zeros((count, slot_grads.shape[1]))
    for k in range(entries.size):
        g = entries[k]
        for j in range(slot_grads.shape[1]):
            grads[g, j] += slot_grads[k, j]
    return grads
