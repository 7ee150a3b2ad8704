"""Scalar fields the renderer can march through: a voxel grid, or the CuNeRF field itself.

Both map world points (P, 3) in the cube [−1, 1]³ to intensities in [0, 1], and are 0 outside
the cube. Each also offers a coarse *support* mask: blocks of the cube where it may be non-zero,
which lets the renderer skip the air around the body without changing a single pixel.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np
import torch
import torch.nn.functional as F

SUPPORT_BLOCK = 8  # voxels per side of a support block


def _sample_grid(volume_zyx: torch.Tensor, points: torch.Tensor, mode: str) -> torch.Tensor:
    """``grid_sample`` of a (1, 1, D, H, W) volume at world points (P, 3), zero outside.

    On the CPU, torch parallelises 3D ``grid_sample`` over the batch only, so the points are
    split into one batch per thread against the same (expanded, not copied) volume.
    """
    count = points.shape[0]
    batches = torch.get_num_threads() if points.device.type == "cpu" and count >= 1 << 15 else 1
    padded = -(-count // batches) * batches
    grid = points.to(torch.float32)
    if padded != count:
        grid = torch.cat((grid, grid.new_zeros(padded - count, 3)))
    grid = grid.reshape(batches, 1, 1, -1, 3)
    values = F.grid_sample(
        volume_zyx.expand(batches, -1, -1, -1, -1), grid, mode=mode, padding_mode="zeros", align_corners=False
    )
    return values.reshape(-1)[:count]


@dataclass(frozen=True)
class Support:
    """Blocks of a regular grid where a field may exceed a threshold, with a margin.

    The grid's low corner is at ``origin`` (the same on every axis) and it spans ``extent``
    world units per axis. Build it with :meth:`from_blocks`, which adds the margin: every block
    next to a support block (across a face, edge or corner) is marked too, and the grid gets one
    extra layer of blocks on every side so that support touching the cube's faces has a margin
    outside it as well. Then any ray that meets the true support first crosses one block length
    of marked blocks, and a march at steps shorter than a block cannot miss it.
    """

    blocks: torch.Tensor  # (B, B, B) bool, margin included
    origin: float
    extent: float

    @classmethod
    def from_blocks(cls, blocks: torch.Tensor, extent: float = 2.0) -> "Support":
        """``blocks`` tile the cube from (−1, −1, −1) over ``extent`` world units per axis."""
        size = extent / blocks.shape[0]
        padded = F.pad(blocks.float()[None, None], (1, 1) * 3)
        dilated = F.max_pool3d(padded, 3, stride=1, padding=1)[0, 0] > 0
        return cls(dilated, -1.0 - size, extent + 2.0 * size)

    @classmethod
    def everywhere(cls, device: torch.device | str = "cpu") -> "Support":
        """Support that rules nothing out (for fields whose air is unknown)."""
        return cls.from_blocks(torch.ones((1, 1, 1), dtype=torch.bool, device=device))

    @property
    def block_size(self) -> float:
        """Side of a block in world units."""
        return self.extent / self.blocks.shape[0]

    def contains(self, points: torch.Tensor) -> torch.Tensor:
        """Whether each world point (P, 3) lies in a marked block (False outside the grid)."""
        # grid_sample's [−1, 1] spans the grid's extent.
        scaled = (points - self.origin) * (2.0 / self.extent) - 1.0
        return _sample_grid(self._zyx_float, scaled, "nearest") > 0.5

    @property
    def _zyx_float(self) -> torch.Tensor:
        cached = self.__dict__.get("_cached_zyx")
        if cached is None:
            cached = self.blocks.permute(2, 1, 0).contiguous().float()[None, None]
            object.__setattr__(self, "_cached_zyx", cached)
        return cached

    def bounds(self) -> tuple[torch.Tensor, torch.Tensor]:
        """World-space box around all marked blocks (an empty support gives an empty box)."""
        occupied = self.blocks.nonzero()
        if occupied.numel() == 0:
            zero = torch.zeros(3, device=self.blocks.device)
            return zero, zero
        size = self.block_size
        return occupied.amin(0).float() * size + self.origin, (occupied.amax(0).float() + 1.0) * size + self.origin


def support_of_volume(volume: torch.Tensor, threshold: float, block: int = SUPPORT_BLOCK) -> Support:
    """Blocks of ``volume`` (S³) where some voxel, or a neighbour a trilinear sample can reach,
    exceeds ``threshold``, with the margin of :meth:`Support.from_blocks`. One row of blocks at a
    time along x, so no volume-sized temporary is made (a float copy is 512 MB at 512³)."""
    size = volume.shape[0]
    count = max(1, -(-size // block))
    rows = []
    for row in range(count):
        # The row's voxels with a one-voxel halo on each side, zero beyond the volume.
        low, high = row * block - 1, (row + 1) * block + 1
        slab = (volume[max(low, 0) : min(high, size)] > threshold).float()
        padding = (1, count * block - size + 1) * 2 + (max(-low, 0), max(high - size, 0))
        padded = F.pad(slab[None, None], padding)
        # Each block with a one-voxel halo: a sample inside the block interpolates its neighbours.
        rows.append(F.max_pool3d(padded, kernel_size=block + 2, stride=block)[0, 0, :1, :count, :count])
    blocks = torch.cat(rows)
    return Support.from_blocks(blocks > 0, extent=2.0 * count * block / size)


class ScalarField(Protocol):
    resolution: int  # voxels per axis of the grid that sets the march step

    def __call__(self, points: torch.Tensor) -> torch.Tensor: ...

    def support(self, threshold: float) -> Support: ...


class GridField:
    """Trilinear interpolation of an S³ volume laid over [−1, 1]³ as docs/design.md §2 says: voxel
    (i, j, k) centred at ((2i+1)/S − 1, …). Beyond the outermost voxels the volume continues as
    air (0), so the field fades to 0 within half a voxel outside the cube.
    """

    def __init__(self, volume, device: torch.device | str = "cpu"):
        if isinstance(volume, np.ndarray) and volume.dtype == np.float32 and torch.device(device).type == "cpu":
            # Shared, not copied: a memory-mapped volume.npy stays on disk until a ray reads it.
            # Nothing writes to it, so torch's warning about read-only arrays does not apply.
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)
                volume = torch.from_numpy(volume)
        volume = torch.as_tensor(volume).to(device=device, dtype=torch.float32)  # float16 input too
        if volume.ndim != 3 or len(set(volume.shape)) != 1:
            raise ValueError(f"a GridField needs an S³ volume, got shape {tuple(volume.shape)}")
        self.volume = volume if volume.is_contiguous() else volume.contiguous()
        self.resolution = volume.shape[0]

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        return _sample_grid(self._zyx, points, "bilinear")

    @property
    def _zyx(self) -> torch.Tensor:
        """The volume as grid_sample reads it, made on first use: (x, y, z) coordinates index
        (W, H, D), and with align_corners=False its [−1, 1] spans the outer faces of the edge
        voxels, which is exactly our world cube. The fused march needs no such copy."""
        cached = self.__dict__.get("_cached_zyx")
        if cached is None:
            cached = self.volume.permute(2, 1, 0).contiguous()[None, None]
            self.__dict__["_cached_zyx"] = cached
        return cached

    def support(self, threshold: float) -> Support:
        return support_of_volume(self.volume, threshold)

    def clear_cells(self, low: float) -> np.ndarray:
        """The fused march's cells in which no sample exceeds ``low`` (``grid_march.clear_cells``),
        made once per transfer function."""
        from cubecloud_cli.render.grid_march import CELL_SHIFT, clear_cells

        cached = self.__dict__.setdefault("_cached_clear", {})
        if low not in cached:
            cached[low] = clear_cells(self.volume.numpy(), float(low), CELL_SHIFT)
        return cached[low]


class FunctionField:
    """Any callable field (for example CuNeRF's cube renders) with a given support."""

    def __init__(self, function: Callable[[torch.Tensor], torch.Tensor], resolution: int, support: Support):
        self.function = function
        self.resolution = resolution
        self._support = support

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        inside = (points.abs() <= 1.0).all(dim=1)
        values = torch.zeros(points.shape[0], device=points.device)
        if inside.any():
            values[inside] = self.function(points[inside]).to(values.dtype)
        return values

    def support(self, threshold: float) -> Support:
        # The function's values are unknown until queried: only the known support applies.
        return self._support
