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

import math
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


# The scan's own resolution (`--preset detail`): the cube side that keeps the finest voxel
# spacing, rounded up to what the 16-voxel cubes of the point sampling tile, and capped where a
# 2-core CPU still finishes the pipeline (docs/results.md, "The scan's own detail").
SIZE_MULTIPLE = 16
SCAN_SIZE_CAP = 512


def size_for_scan(
    shape: tuple[int, ...], spacing_mm: tuple[float, ...] | np.ndarray, fit: Fit, cap: int = SCAN_SIZE_CAP
) -> int:
    """The cube side S that keeps the scan's finest voxel spacing along its longest extent
    (``pad``) or its most finely sampled axis (``stretch``), rounded up to a multiple of 16 and
    capped at ``cap``."""
    counts = np.asarray(shape, dtype=float)
    spacing = np.asarray(spacing_mm, dtype=float)
    if counts.shape != (3,) or spacing.shape != (3,) or not np.all(np.isfinite(spacing)) or spacing.min() <= 0:
        raise ValueError(f"a 3D scan with positive spacing is needed, not shape {shape} and spacing {spacing_mm}")
    if fit == "pad":
        # 1e-6 keeps 512 × 0.57 mm / 0.57 mm at 512 whatever the rounding of the spacing.
        needed = float(np.max(counts * spacing) / spacing.min()) - 1e-6
    elif fit == "stretch":
        needed = float(counts.max())
    else:
        raise ValueError(f"unknown fit {fit!r}")
    multiple = SIZE_MULTIPLE * math.ceil(max(needed, 1.0) / SIZE_MULTIPLE)
    return int(min(multiple, cap))


MIN_VOXELS_ACROSS = 2.0  # fewer cube voxels across an axis and resampling at their centres may miss it


def voxels_across(shape: tuple[int, ...], spacing_mm, size: int, fit: Fit) -> np.ndarray:
    """(3,) how many cube voxels each axis of the scan spans: under ``pad`` the cube's side is the
    longest extent, so a thin axis spans S × its extent / the longest; under ``stretch`` every one
    spans all S."""
    extent = np.asarray(shape, dtype=float) * np.asarray(spacing_mm, dtype=float)
    if fit == "stretch" or not np.all(extent > 0):
        return np.full(3, float(size))
    return size * extent / extent.max()


def size_keeping(
    shape: tuple[int, ...], spacing_mm, minimum: float = MIN_VOXELS_ACROSS, cap: int = SCAN_SIZE_CAP
) -> int | None:
    """The smallest multiple of 16 that gives every axis at least ``minimum`` voxels under ``pad``,
    or None when none up to ``cap`` does."""
    extent = np.asarray(shape, dtype=float) * np.asarray(spacing_mm, dtype=float)
    if not np.all(extent > 0):
        return None
    # The slack keeps a ratio one rounding above a whole multiple (232 × 0.05 mm / 0.05 mm) on it.
    needed = SIZE_MULTIPLE * math.ceil(minimum * extent.max() / extent.min() / SIZE_MULTIPLE - 1e-9)
    return int(needed) if needed <= cap else None


def shear_degrees(affine: np.ndarray) -> float:
    """How far the angles between the affine's voxel axes are from 90°, the largest of the three
    (0 for any rotation and scaling; a gantry-tilted CT read as one volume is sheared)."""
    columns = np.asarray(affine, dtype=float)[:3, :3].T
    norms = np.linalg.norm(columns, axis=1)
    if not np.all(norms > 0):
        return 0.0
    unit = columns / norms[:, None]
    cosines = [abs(float(unit[a] @ unit[b])) for a, b in ((0, 1), (0, 2), (1, 2))]
    return float(max(math.degrees(math.asin(min(c, 1.0))) for c in cosines))


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
