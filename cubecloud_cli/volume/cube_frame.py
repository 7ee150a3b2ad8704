"""The cube that every stage works in, and its maps to voxels and to the scanner.

Three frames (docs/design.md §2):

* cube voxel index (i, j, k) of the S³ preprocessed volume, axes RAS;
* world: voxel centre (i, j, k) at ((2i+1)/S − 1, (2j+1)/S − 1, (2k+1)/S − 1), so the volume fills
  [−1, 1]³ centred at the origin;
* scanner: RAS+ millimetres of the original scan (the NIfTI convention).

``fit="pad"`` keeps the physical aspect ratio: the cube's side is the scan's longest physical
extent and the shorter axes are centred and padded with air, so voxels are isotropic.
``fit="stretch"`` maps each axis's full extent onto S voxels (the paper's plain resize), so voxels
are anisotropic in millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

Fit = Literal["pad", "stretch"]


@dataclass(frozen=True)
class CubeFrame:
    size: int
    fit: Fit
    index_scale: np.ndarray  # per axis: source-index step per cube voxel
    index_offset: np.ndarray  # per axis: see volume.resample (c = scale·(o+½) − ½ + offset)
    source_affine: np.ndarray  # source (RAS-reoriented) voxel index -> scanner mm

    @property
    def voxel_size_mm(self) -> np.ndarray:
        return self.index_scale * np.linalg.norm(self.source_affine[:3, :3], axis=0)

    @property
    def mm_per_world_unit(self) -> np.ndarray:
        # The world spans 2 units over S voxels.
        return self.voxel_size_mm * self.size / 2.0

    def voxel_to_source_index(self) -> np.ndarray:
        matrix = np.eye(4)
        matrix[:3, :3] = np.diag(self.index_scale)
        matrix[:3, 3] = 0.5 * self.index_scale - 0.5 + self.index_offset
        return matrix

    def voxel_to_scanner(self) -> np.ndarray:
        """The preprocessed volume's NIfTI affine: it lies exactly over the original scan."""
        return self.source_affine @ self.voxel_to_source_index()

    def voxel_to_world(self) -> np.ndarray:
        half = self.size / 2.0
        matrix = np.eye(4)
        matrix[:3, :3] = np.eye(3) / half
        matrix[:3, 3] = 1.0 / self.size - 1.0
        return matrix

    def world_to_scanner(self) -> np.ndarray:
        return self.voxel_to_scanner() @ np.linalg.inv(self.voxel_to_world())

    def describe(self) -> dict:
        """The mappings as plain lists, for manifest.json."""
        return {
            "size": self.size,
            "fit": self.fit,
            "voxel_size_mm": self.voxel_size_mm,
            "mm_per_world_unit": self.mm_per_world_unit,
            "voxel_to_world": self.voxel_to_world(),
            "voxel_to_scanner": self.voxel_to_scanner(),
            "world_to_scanner": self.world_to_scanner(),
            "voxel_to_source_index": self.voxel_to_source_index(),
        }


def plan_cube(shape: tuple[int, int, int], source_affine: np.ndarray, size: int, fit: Fit) -> CubeFrame:
    """Place a scan of ``shape`` voxels (already RAS-reoriented) in the S³ cube."""
    if size < 2:
        raise ValueError("the cube needs at least 2 voxels per side")
    counts = np.asarray(shape, dtype=float)
    spacing = np.linalg.norm(source_affine[:3, :3], axis=0)
    extent_mm = counts * spacing
    if fit == "pad":
        side_mm = extent_mm.max()
        scale = side_mm / size / spacing
        pad_mm = (side_mm - extent_mm) / 2.0
        offset = -pad_mm / spacing
    elif fit == "stretch":
        scale = counts / size
        offset = np.zeros(3)
    else:
        raise ValueError(f"unknown fit {fit!r}")
    return CubeFrame(size, fit, scale, offset, np.asarray(source_affine, dtype=float))
