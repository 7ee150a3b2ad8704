"""The bake of a grid field's test lattice on the CPU in one numba kernel.

``CunerfField.bake`` renders a cube at every voxel centre. Through torch that is a chain of
tensors per chunk of cubes: the lattice's points, three levels of lookup, the MLP, a sort, the
shells' scatters. At 512³ (134 M cubes of 8 points) the chain took 286 s of the detail preset's
cunerf stage. Here each cube's points, features, intensities and densities stay in registers.

It serves the case the CPU presets bake: a :class:`~cubecloud_cli.cunerf.fields.GridField`
without a fine pass, on the test lattice (``RenderConfig.official`` off). The lattice is the
same for every cube, so its radii, sort, shells, areas and δ come from
:func:`~cubecloud_cli.cunerf.rendering.render_cubes`'s own functions once, and only the part
that depends on the field (σ, colour, transmittance) runs per cube, in the same float32 steps as
torch. The two agree to float32 rounding (tests/test_grid_bake.py).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange

from cubecloud_cli.cunerf.fields import POINT_LIMIT, GridField
from cubecloud_cli.cunerf.grid_kernels import corner_base
from cubecloud_cli.cunerf.model import CubeModel
from cubecloud_cli.cunerf.rendering import MAX_DENSITY, shell_intervals
from cubecloud_cli.cunerf.sampling import cube_offsets
from cubecloud_cli.cunerf.supervision import Occupancy, voxel_centres
from cubecloud_cli.numerics.jit import EXACT_FASTMATH, PRANGE_ONLY

# torch's softplus returns its input above this (its default threshold).
SOFTPLUS_THRESHOLD = 20.0
# The kernel's first compilation takes about 10 s; smaller bakes take torch, which is as fast
# there (128³: 3.4 s through torch, 2.7 s through the compiled kernel; 512³: 278 s and 140 s).
MIN_SIZE = 256


def applies(model: CubeModel, device: torch.device, size: int = MIN_SIZE) -> bool:
    """Whether a size³ bake of this model goes through :func:`bake_lattice`, which renders what
    ``render_many`` would."""
    field, config = model.coarse, model.render_config
    coarse_only = config.importance <= 0 or config.samples_per_axis**3 < 3
    return (
        size >= MIN_SIZE
        and device.type == "cpu"
        and isinstance(field, GridField)
        and field.table.dtype == torch.float32
        and model.fine is None
        and coarse_only
        and not config.official
    )


def lattice_shells(model: CubeModel) -> dict[str, np.ndarray]:
    """The test lattice's offsets in their sorted order, and each sample's shell, area and δ."""
    config = model.render_config
    offsets = cube_offsets(1, config.samples_per_axis, "lattice", config.cube_half_size)
    radii = torch.linalg.vector_norm(offsets, dim=-1) / config.half_diagonal
    radii, order = torch.sort(radii, dim=1, stable=True)
    delta, shell = shell_intervals(radii, tie_aware=True)
    return {
        "offsets": offsets[0, order[0]].contiguous().numpy().astype(np.float32),
        "shell": shell[0].numpy().astype(np.int64),
        "area": (4.0 * math.pi * radii * radii)[0].numpy().astype(np.float32),
        "delta": delta[0].numpy().astype(np.float32),
    }


def keep_masks(axis: torch.Tensor, occupancy: Occupancy | None) -> tuple[np.ndarray, np.ndarray]:
    """Per axis coordinate: its occupancy block and whether it lies inside (−1, 1), as
    ``Occupancy.occupied`` computes them for a grid's points (blocks (1, 1, 1) of True without
    an occupancy grid, so every cube renders)."""
    if occupancy is None:
        return np.zeros(axis.shape[0], dtype=np.int64), np.ones((1, 1, 1), dtype=np.bool_)
    voxel = ((axis + 1.0) * (0.5 * occupancy.size)).floor().long()
    block = (voxel // occupancy.block).clamp(0, occupancy.blocks.shape[0] - 1)
    inside = (axis > -1.0) & (axis < 1.0)
    # A coordinate outside (−1, 1) makes its cubes render whatever the blocks say: block −1 marks it.
    block = torch.where(inside, block, torch.full_like(block, -1))
    return block.numpy().astype(np.int64), occupancy.blocks.cpu().numpy().astype(np.bool_)


@njit(cache=True, inline="always", fastmath=EXACT_FASTMATH)
def _cube_value(cx, cy, cz, offsets, shell, area, delta, table, resolutions, starts, w1t, b1, w2, b2, relu, encoded, h):
    """One cube's test render at centre (cx, cy, cz): ``render_cubes`` on the lattice's samples,
    bounded. ``encoded`` and ``h`` are scratch for one point's features and hidden units."""
    one, zero = np.float32(1.0), np.float32(0.0)
    limit = np.float32(POINT_LIMIT)
    features, levels, hidden = table.shape[1], resolutions.size, w1t.shape[1]
    total_depth = zero  # Σ area σ δ of the samples before this one
    shell_depth = zero  # that sum at the start of the current shell
    current_shell = -1
    weighted = zero
    weights = zero
    for s in range(offsets.shape[0]):
        x = min(max(cx + offsets[s, 0], -limit), limit)
        y = min(max(cy + offsets[s, 1], -limit), limit)
        z = min(max(cz + offsets[s, 2], -limit), limit)
        for level in range(levels):
            r = resolutions[level]
            base, fx, fy, fz = corner_base(x, y, z, r)
            base += starts[level]
            for f in range(features):
                encoded[level * features + f] = zero
            for corner in range(8):
                a, b, c = corner >> 2, (corner >> 1) & 1, corner & 1
                weight = ((fx if a else one - fx) * (fy if b else one - fy)) * (fz if c else one - fz)
                row = base + a * r * r + b * r + c
                for f in range(features):
                    encoded[level * features + f] += weight * table[row, f]
        for j in range(hidden):
            h[j] = b1[j]
        for i in range(encoded.size):
            value = encoded[i]
            for j in range(hidden):
                h[j] += w1t[i, j] * value
        raw_intensity, raw_density = b2[0], b2[1]
        for j in range(hidden):
            active = max(h[j], zero)
            raw_intensity += w2[0, j] * active
            raw_density += w2[1, j] * active
        # Sigmoid and softplus without overflow at either end.
        if raw_intensity >= zero:
            colour = one / (one + np.float32(math.exp(-raw_intensity)))
        else:
            e = np.float32(math.exp(raw_intensity))
            colour = e / (one + e)
        if relu:
            sigma = max(raw_density, zero)
        elif raw_density > np.float32(SOFTPLUS_THRESHOLD):
            sigma = raw_density
        else:
            sigma = np.float32(math.log1p(math.exp(raw_density)))
        sigma = min(max(sigma, zero), np.float32(MAX_DENSITY))
        if shell[s] != current_shell:
            current_shell, shell_depth = shell[s], total_depth
        total_depth += area[s] * sigma * delta[s]
        alpha = area[s] * np.float32(-math.expm1(-sigma * delta[s]))
        w = np.float32(math.exp(-max(shell_depth, zero))) * alpha
        weighted += w * colour
        weights += w
    return weighted / max(weights, one)


@njit(parallel=PRANGE_ONLY, cache=True, fastmath=EXACT_FASTMATH)
def _bake_slab(
    out, first, axis, block_of, blocks, offsets, shell, area, delta, table, resolutions, starts, w1t, b1, w2, b2, relu
):
    """Fill ``out`` (X, S, S) with the cubes at x = axis[first + i], y = axis[j], z = axis[k],
    clamped to [0, 1]; cubes deep in air (by ``blocks``) read 0, as ``render_many`` skips them."""
    count, size = out.shape[0], out.shape[1]
    for row in prange(count * size):
        i, j = row // size, row % size
        encoded = np.empty(resolutions.size * table.shape[1], dtype=np.float32)
        h = np.empty(w1t.shape[1], dtype=np.float32)
        bx, by = block_of[first + i], block_of[j]
        for k in range(size):
            bz = block_of[k]
            outside = bx < 0 or by < 0 or bz < 0
            if not outside and not blocks[max(bx, 0), max(by, 0), max(bz, 0)]:
                out[i, j, k] = 0.0
                continue
            value = _cube_value(
                axis[first + i], axis[j], axis[k], offsets, shell, area, delta,
                table, resolutions, starts, w1t, b1, w2, b2, relu, encoded, h,
            )  # fmt: skip
            out[i, j, k] = min(max(value, np.float32(0.0)), np.float32(1.0))


def bake_lattice(
    model: CubeModel, size: int, occupancy: Occupancy | None, volume: np.ndarray, on_progress=lambda fraction: None
) -> None:
    """Write the size³ bake of ``model`` into ``volume`` (size, size, size) float32, slab by slab."""
    field = model.coarse
    shells = lattice_shells(model)
    axis_tensor = voxel_centres(torch.arange(size), size)
    block_of, blocks = keep_masks(axis_tensor, occupancy)
    first_layer, last_layer = field.mlp[0], field.mlp[2]
    weights = [
        np.ascontiguousarray(t.detach().numpy(), dtype=np.float32)
        for t in (first_layer.weight.t(), first_layer.bias, last_layer.weight, last_layer.bias)
    ]
    table = field.table.detach().numpy()
    resolutions = np.asarray(field.config.resolutions, dtype=np.int64)
    starts = field.offsets.numpy().astype(np.int64)
    relu = field.config.density_activation == "relu"
    axis = axis_tensor.numpy()
    slab = max(1, (1 << 22) // (size * size))
    for first in range(0, size, slab):
        stop = min(size, first + slab)
        _bake_slab(
            volume[first:stop], first, axis, block_of, blocks, shells["offsets"], shells["shell"],
            shells["area"], shells["delta"], table, resolutions, starts, *weights, relu,
        )  # fmt: skip
        on_progress(stop / size)
