"""Which voxels supervise the field, which are held out, and where the field can be skipped.

* Training voxels: every voxel of the preprocessed S³ volume, or with ``train_scale`` s > 1 only
  those whose indices are multiples of s on every axis (strided decimation, as CuNeRF's
  zero-shot super-resolution does, docs/cunerf.md §3.5), so the full-resolution volume can
  score the super-resolution.
* Validation: whole axial slices kept out of training. At s = 1 they are training slices set
  aside; at s > 1 they are full-resolution slices between the decimated ones.
* Batches: a share of each batch comes from body (non-air) voxels, the rest uniformly from all
  training voxels, so a scan that is mostly air still learns its body.
* Occupancy: blocks of the volume holding no non-zero training voxel (dilated by a block), which
  rendering may skip and report as air.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F


def voxel_centres(indices: torch.Tensor, size: int) -> torch.Tensor:
    """World coordinates of voxel indices (..., 3): ((2i + 1)/S − 1), docs/design.md §2."""
    return (2.0 * indices.to(torch.float32) + 1.0) / size - 1.0


def holdout_slices(volume: np.ndarray, count: int, train_scale: int) -> list[int]:
    """Up to ``count`` axial slice indices, evenly spread over the slices that hold body (or
    over all slices when none does). At ``train_scale`` 1 at most an eighth of those slices
    are held out; above it, held-out slices are never on the training lattice."""
    size = volume.shape[2]
    occupied = np.flatnonzero(volume.reshape(-1, size).max(axis=0) > 0)
    low, high = (int(occupied[0]), int(occupied[-1])) if occupied.size else (0, size - 1)
    candidates = [k for k in range(low, high + 1) if train_scale == 1 or k % train_scale != 0]
    if train_scale == 1:
        # Held-out slices are taken from training: never more than an eighth of the body's.
        count = min(count, len(candidates) // 8)
    if count <= 0 or not candidates:
        return []
    if count >= len(candidates):
        return candidates
    picks = np.linspace(0, len(candidates) - 1, count + 2)[1:-1]  # away from the ends
    return sorted({candidates[int(round(p))] for p in picks})


BODY_SLAB = 32  # x-slices per pass when the body voxels are listed


@dataclass
class TrainingVoxels:
    volume: torch.Tensor  # (S, S, S) float32 in [0, 1], on the training device
    train_scale: int
    held_out: list[int]  # axial slice indices kept out of training
    body_fraction: float

    def __post_init__(self) -> None:
        size = self.volume.shape[0]
        device = self.volume.device
        self.size = size
        lattice = torch.arange(0, size, self.train_scale, device=device)
        self.lattice = lattice
        keep = torch.ones(size, dtype=torch.bool, device=device)
        if self.held_out:
            keep[torch.as_tensor(self.held_out, device=device)] = False
        self.slices = lattice[keep[lattice]]  # training slice indices (axis 2)
        if self.slices.numel() == 0:
            raise ValueError("no slice is left for training: hold out fewer slices")
        n_xy, n_z = lattice.numel(), self.slices.numel()
        self.training_voxels = n_xy * n_xy * n_z

    def _body_slabs(self):
        """Each slab of BODY_SLAB lattice rows along x: its rows and the (x, y, z) lattice offsets of
        its body voxels, in the order of one pass over the training lattice."""
        lattice = self.lattice
        for start in range(0, lattice.numel(), BODY_SLAB):
            rows = lattice[start : start + BODY_SLAB]
            yield rows, self.volume[rows][:, lattice][:, :, self.slices] > 0

    @property
    def body_voxels(self) -> int:
        """Training voxels inside the body (above 0), counted without listing them."""
        cached = self.__dict__.get("_body_count")
        if cached is None:
            cached = sum(int(inside.sum()) for _, inside in self._body_slabs())
            self.__dict__["_body_count"] = cached
        return cached

    @property
    def body(self) -> torch.Tensor:
        """(N, 3) int32 (int64 from 2¹⁵ voxels a side) indices of the body voxels, listed at the first
        batch that draws from the body: 1.3 GB at 512³, which a fitted start that trains no
        iteration never needs. Written slab by slab into one tensor: int64 indices of every body
        voxel at once, or the slabs and their concatenation side by side, would take several GB."""
        cached = self.__dict__.get("_body")
        if cached is None:
            index_type = torch.int32 if self.size < 2**15 else torch.int64
            cached = torch.empty((self.body_voxels, 3), dtype=index_type, device=self.volume.device)
            filled = 0
            for rows, inside in self._body_slabs():
                local = torch.nonzero(inside)
                count = local.shape[0]
                cached[filled : filled + count, 0] = rows[local[:, 0]]
                cached[filled : filled + count, 1] = self.lattice[local[:, 1]]
                cached[filled : filled + count, 2] = self.slices[local[:, 2]]
                filled += count
            self.__dict__["_body"] = cached
        return cached

    def batch(self, count: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """(centres (B, 3) world, targets (B,)) for one iteration."""
        device = self.volume.device
        from_body = int(round(count * self.body_fraction)) if self.body_voxels else 0
        picks = []
        if from_body:
            rows = torch.randint(self.body_voxels, (from_body,), generator=generator, device=device)
            picks.append(self.body[rows].long())
        uniform = count - from_body
        if uniform:
            n = self.lattice.numel()
            ij = self.lattice[torch.randint(n, (uniform, 2), generator=generator, device=device)]
            k = self.slices[torch.randint(self.slices.numel(), (uniform,), generator=generator, device=device)]
            picks.append(torch.cat((ij, k[:, None]), dim=1))
        indices = torch.cat(picks)
        targets = self.volume[indices[:, 0], indices[:, 1], indices[:, 2]]
        return voxel_centres(indices, self.size), targets

    def occupancy(self, block: int = 4) -> "Occupancy":
        """Blocks that hold a non-zero *training* voxel, dilated by one block."""
        block = max(block, self.train_scale)
        mask = torch.zeros_like(self.volume, dtype=torch.bool)
        lattice, slices = self.lattice, self.slices
        mask[lattice[:, None, None], lattice[None, :, None], slices[None, None, :]] = (
            self.volume[lattice][:, lattice][:, :, slices] > 0
        )
        coarse = F.max_pool3d(mask[None, None].float(), block, block, ceil_mode=True)
        coarse = F.max_pool3d(coarse, 3, 1, padding=1)[0, 0] > 0
        return Occupancy(coarse, block, self.size)


@dataclass
class Occupancy:
    """A coarse grid of blocks; ``occupied(points)`` is False only deep in air."""

    blocks: torch.Tensor  # (B, B, B) bool
    block: int  # voxels per block
    size: int  # S

    def occupied(self, points: torch.Tensor) -> torch.Tensor:
        voxel = ((points + 1.0) * (0.5 * self.size)).floor().long()
        index = (voxel // self.block).clamp(0, self.blocks.shape[0] - 1)
        inside = ((points > -1.0) & (points < 1.0)).all(dim=-1)
        # Outside the volume there is no data to say "air", so nothing is skipped there.
        return ~inside | self.blocks[index[..., 0], index[..., 1], index[..., 2]]

    def fraction(self) -> float:
        return float(self.blocks.float().mean())
