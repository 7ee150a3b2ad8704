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
        index_type = torch.int32 if size < 2**15 else torch.int64
        # Slab by slab along x, in the same (x, y, z) order as one pass: int64 indices of every
        # body voxel at once would take several GB at 512³.
        parts = []
        for start in range(0, lattice.numel(), BODY_SLAB):
            rows = lattice[start : start + BODY_SLAB]
            local = torch.nonzero(self.volume[rows][:, lattice][:, :, self.slices] > 0)
            voxels = (rows[local[:, 0]], lattice[local[:, 1]], self.slices[local[:, 2]])
            parts.append(torch.stack(voxels, dim=1).to(index_type))
        self.body = torch.cat(parts) if len(parts) > 1 else parts[0]
        n_xy, n_z = lattice.numel(), self.slices.numel()
        self.training_voxels = n_xy * n_xy * n_z

    @property
    def body_voxels(self) -> int:
        return int(self.body.shape[0])

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
