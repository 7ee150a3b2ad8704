"""Read any supported scan file or folder into a :class:`Scan`.

Formats: NIfTI (.nii, .nii.gz; also Analyze .hdr/.img through nibabel), a DICOM series folder,
NRRD (.nrrd, .nhdr) and NumPy .npy (with ``spacing_mm``). Every reader returns physical values in
float32 and an affine to RAS+ scanner millimetres.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.volume.dicom import read_dicom_file, read_dicom_series
from cubecloud_cli.volume.scan import (
    Scan,
    check_affine,
    override_spacing,
    select_3d,
    voxel_spacing_affine,
)

# NIfTI xyzt_units other than mm, as factors to mm.
_NIFTI_UNIT_TO_MM = {"meter": 1000.0, "micron": 1e-3, "mm": 1.0, "unknown": 1.0}

# NRRD "space" values and the sign flips that take them to RAS.
_NRRD_SPACE_TO_RAS = {
    "right-anterior-superior": (1, 1, 1),
    "ras": (1, 1, 1),
    "left-posterior-superior": (-1, -1, 1),
    "lps": (-1, -1, 1),
    "left-anterior-superior": (-1, 1, 1),
    "las": (-1, 1, 1),
    "scanner-xyz": (1, 1, 1),
    "3d-right-handed": (1, 1, 1),
}

DICOM_SUFFIXES = ("", ".dcm", ".ima")
SUPPORTED = "NIfTI (.nii, .nii.gz), a DICOM series folder, NRRD (.nrrd) or .npy with --spacing"


def _suffix(path: Path) -> str:
    name = path.name.lower()
    for suffix in (".nii.gz", ".nii", ".hdr", ".img", ".nrrd", ".nhdr", ".npy"):
        if name.endswith(suffix):
            return suffix
    return path.suffix.lower()


def is_dicom_file(path: Path) -> bool:
    """Whether the file has DICOM's "DICM" marker after its 128-byte preamble (files named by their
    UID, 1.2.840.….dcm-less, have a numeric "suffix")."""
    try:
        with open(path, "rb") as file:
            return file.read(132)[128:] == b"DICM"
    except OSError:
        return False


def read_nifti(path: Path, volume_index: int | None) -> Scan:
    import nibabel as nib

    try:
        image = nib.load(str(path))
    except Exception as exc:  # nibabel raises ImageFileError, ValueError, OSError, ...
        raise CubecloudError(f"cannot read {path} as NIfTI ({exc}): the file is corrupt or not NIfTI") from None
    affine = np.asarray(image.affine, dtype=float)
    units = image.header.get_xyzt_units()[0] if hasattr(image.header, "get_xyzt_units") else "unknown"
    scale = _NIFTI_UNIT_TO_MM.get(units, 1.0)
    affine[:3, :] *= scale
    notes = [f"header gives voxel sizes in {units}; converted to mm"] if scale != 1.0 else []
    shape = image.shape
    pick_volume = volume_index is not None and len(shape) == 4 and shape[3] > 1
    if pick_volume and not 0 <= volume_index < shape[3]:
        raise CubecloudError(f"--volume-index {volume_index} is out of range: {path} has volumes 0..{shape[3] - 1}")
    try:
        # Physical values in float32 directly: nibabel applies scl_slope/scl_inter in float, so
        # an int16 scan with a large slope cannot overflow, and we never hold a float64 copy.
        if pick_volume:
            data = np.asarray(image.dataobj[..., volume_index], dtype=np.float32)
            volume_index = None
        else:
            data = np.asarray(image.dataobj, dtype=np.float32)
    except Exception as exc:  # truncated gzip: EOFError, zlib.error, OSError, ValueError
        raise CubecloudError(
            f"cannot read the voxels of {path} ({type(exc).__name__}: {exc}): the file is "
            f"truncated or corrupt; copy or export it again"
        ) from None
    return Scan(select_3d(data, volume_index, str(path)), affine, "NIfTI", None, notes)


def read_nrrd(path: Path, volume_index: int | None) -> Scan:
    import nrrd

    try:
        data, header = nrrd.read(str(path))
    except Exception as exc:
        raise CubecloudError(f"cannot read {path} as NRRD ({exc}): the file is corrupt or not NRRD") from None
    data = np.asarray(data)
    directions = header.get("space directions")
    if directions is not None:
        # Non-spatial axes (a list of components, time) have "none" directions.
        rows = [
            None if d is None or np.any(np.isnan(np.asarray(d, dtype=float))) else np.asarray(d, float)
            for d in directions
        ]
        spatial_axes = [i for i, row in enumerate(rows) if row is not None]
        extra_axes = [i for i in range(data.ndim) if i not in spatial_axes]
        data = np.moveaxis(data, extra_axes, list(range(len(spatial_axes), data.ndim)))
        matrix = np.stack([rows[i] for i in spatial_axes], axis=1)
    else:
        spacings = header.get("spacings", [1.0] * data.ndim)
        matrix = np.diag(np.asarray(spacings[:3], dtype=float))
    if matrix.shape != (3, 3):
        raise CubecloudError(f"{path} is not a 3D volume (its header has {matrix.shape[1]} spatial axes)")
    affine = np.eye(4)
    affine[:3, :3] = matrix
    affine[:3, 3] = np.asarray(header.get("space origin", np.zeros(3)), dtype=float)
    space = str(header.get("space", "right-anterior-superior")).lower()
    if space not in _NRRD_SPACE_TO_RAS:
        raise CubecloudError(f"{path} uses NRRD space {space!r}, which cubecloud cannot place; resave it in RAS or LPS")
    affine = np.diag([*_NRRD_SPACE_TO_RAS[space], 1.0]) @ affine
    data = select_3d(data, volume_index, str(path)).astype(np.float32, copy=False)
    return Scan(data, affine, "NRRD")


def read_npy(path: Path, volume_index: int | None, spacing_mm) -> Scan:
    if spacing_mm is None:
        raise CubecloudError(
            f"{path} is a bare array with no voxel size: pass --spacing X,Y,Z in mm "
            f"(axes in RAS order: left→right, posterior→anterior, inferior→superior)"
        )
    try:
        data = np.load(path, mmap_mode="r", allow_pickle=False)
    except Exception as exc:
        raise CubecloudError(f"cannot read {path} as .npy ({exc}): the file is corrupt or not .npy") from None
    if not np.issubdtype(data.dtype, np.number) or np.issubdtype(data.dtype, np.complexfloating):
        raise CubecloudError(f"{path} holds {data.dtype} values; cubecloud needs real numbers")
    data = select_3d(np.asarray(data), volume_index, str(path)).astype(np.float32)
    return Scan(data, voxel_spacing_affine(spacing_mm), "NumPy array (RAS order assumed)")


def read_scan(
    path: Path,
    *,
    spacing_mm: tuple[float, float, float] | None = None,
    volume_index: int | None = None,
    series_uid: str | None = None,
) -> Scan:
    """Read a scan from a file or DICOM folder, validate its geometry, return it in RAS mm.

    ``spacing_mm`` replaces the header's voxel size (and is required for .npy); the axis
    directions and origin of the header are kept. ``series_uid`` picks a DICOM series.
    """
    path = Path(path)
    if not path.exists():
        raise CubecloudError(f"{path} does not exist: check the path (expected {SUPPORTED})")
    if series_uid is not None and not (path.is_dir() or _suffix(path) in DICOM_SUFFIXES or is_dicom_file(path)):
        raise CubecloudError(f"--series picks a DICOM series, but {path} is not DICOM: leave it out")
    if path.is_dir():
        scan = read_dicom_series(path, series_uid)
        if volume_index not in (None, 0):
            raise CubecloudError(f"--volume-index {volume_index} given, but a DICOM series holds one volume")
    else:
        suffix = _suffix(path)
        if suffix in (".nii.gz", ".nii", ".hdr", ".img"):
            scan = read_nifti(path, volume_index)
        elif suffix in (".nrrd", ".nhdr"):
            scan = read_nrrd(path, volume_index)
        elif suffix == ".npy":
            scan = read_npy(path, volume_index, spacing_mm)
        elif suffix in DICOM_SUFFIXES or is_dicom_file(path):
            scan = read_dicom_file(path, series_uid)
        else:
            raise CubecloudError(f"{path} has an unknown file type {suffix!r}: cubecloud reads {SUPPORTED}")
    if not scan.data.flags.writeable:
        # Memory maps and decoded buffers can be read-only; later steps repair voxels in place.
        scan.data = scan.data.copy()
    if spacing_mm is not None:
        scan.affine = override_spacing(scan.affine, spacing_mm)
    check_affine(scan.affine, f"the header of {path}")
    return scan
