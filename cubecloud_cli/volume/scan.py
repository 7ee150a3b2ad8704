"""A scan as read from disk: voxels, their placement in the scanner frame, and what it is."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cubecloud_cli.core.errors import CubecloudError

# Voxel sizes outside this range are header errors, not scans: 1 µm covers micro-CT, and no
# clinical CT or MR has 5 cm voxels.
SPACING_RANGE_MM = (1e-3, 50.0)


@dataclass
class Scan:
    """A 3D scan in its file's array order.

    ``affine`` maps a voxel index (i, j, k, 1) to scanner RAS+ millimetres, as in NIfTI; every
    reader converts its format's convention (DICOM and NRRD are often LPS) to this one.
    ``data`` holds the physical values (HU for CT, after any rescale slope/intercept) as float32.
    """

    data: np.ndarray
    affine: np.ndarray
    source_format: str
    modality: str | None = None  # "ct" or "mr" when the file says so, else None
    notes: list[str] = field(default_factory=list)
    acquisition: dict = field(default_factory=dict)  # what the reader found of the slice geometry (DICOM)

    @property
    def spacing_mm(self) -> np.ndarray:
        return np.linalg.norm(self.affine[:3, :3], axis=0)


def voxel_spacing_affine(spacing_mm: tuple[float, float, float]) -> np.ndarray:
    """Affine of an array already in RAS order with the given voxel size, origin at voxel 0."""
    affine = np.eye(4)
    affine[:3, :3] = np.diag(spacing_mm)
    return affine


def override_spacing(affine: np.ndarray, spacing_mm: tuple[float, float, float]) -> np.ndarray:
    """Keep the axis directions and origin of ``affine`` but set the voxel size."""
    check_spacing(np.asarray(spacing_mm, dtype=float), source="--spacing")
    affine = np.array(affine, dtype=float)
    norms = np.linalg.norm(affine[:3, :3], axis=0)
    directions = np.where(norms > 0, affine[:3, :3] / np.where(norms > 0, norms, 1), np.eye(3))
    affine[:3, :3] = directions * np.asarray(spacing_mm, dtype=float)
    return affine


def check_spacing(spacing_mm: np.ndarray, source: str) -> None:
    low, high = SPACING_RANGE_MM
    text = "×".join(f"{s:g}" for s in spacing_mm)
    if not np.all(np.isfinite(spacing_mm)) or np.any(spacing_mm <= 0):
        raise CubecloudError(
            f"voxel size {text} mm from {source} is zero, negative or not a number: "
            f"pass the true size with --spacing X,Y,Z (mm)"
        )
    if np.any(spacing_mm < low) or np.any(spacing_mm > high):
        raise CubecloudError(
            f"voxel size {text} mm from {source} is outside {low:g}–{high:g} mm and cannot be "
            f"right: pass the true size with --spacing X,Y,Z (mm)"
        )


def check_affine(affine: np.ndarray, source: str) -> None:
    if affine.shape != (4, 4) or not np.all(np.isfinite(affine)):
        raise CubecloudError(f"the orientation matrix in {source} holds NaN or Inf: the header is corrupt")
    check_spacing(np.linalg.norm(affine[:3, :3], axis=0), source)
    # Near-parallel axes make a collapsed grid; the determinant of the direction matrix is the
    # volume of the unit voxel's parallelepiped relative to a cube.
    directions = affine[:3, :3] / np.linalg.norm(affine[:3, :3], axis=0)
    if abs(np.linalg.det(directions)) < 1e-3:
        raise CubecloudError(
            f"the axes in {source} are parallel (singular orientation matrix): the header is "
            f"corrupt; fix it or pass the array as .npy with --spacing"
        )


def select_3d(data: np.ndarray, volume_index: int | None, source: str) -> np.ndarray:
    """Reduce a scan array to 3D: drop trailing singleton axes, pick one volume of a 4D series."""
    while data.ndim > 3 and data.shape[-1] == 1 and volume_index is None:
        data = data[..., 0]
    shape_text = "×".join(str(n) for n in data.shape)
    if data.ndim == 4:
        count = data.shape[3]
        if volume_index is None:
            raise CubecloudError(
                f"{source} is 4D ({shape_text}, {count} volumes): pick one with --volume-index 0..{count - 1}"
            )
        if not 0 <= volume_index < count:
            raise CubecloudError(f"--volume-index {volume_index} is out of range: {source} has volumes 0..{count - 1}")
        data = data[..., volume_index]
    elif volume_index not in (None, 0):
        raise CubecloudError(f"--volume-index {volume_index} given, but {source} holds one volume")
    if data.ndim == 2:
        raise CubecloudError(f"{source} is a 2D image ({shape_text}); cubecloud needs a 3D volume (a CT or MR series)")
    if data.ndim != 3:
        raise CubecloudError(f"{source} has {data.ndim} dimensions ({shape_text}); cubecloud needs a 3D volume")
    if min(data.shape) < 2:
        raise CubecloudError(
            f"{source} is a 2D image ({shape_text}); cubecloud needs a 3D volume with at least 2 voxels along each axis"
        )
    return data
