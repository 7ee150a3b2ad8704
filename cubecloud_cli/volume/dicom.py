"""DICOM series folders: each slice where it was acquired, rescale, compressed pixel data, LPS -> RAS.

Real series are messy: files without extensions, empty UIDs, JPEG 2000 pixel data, slices in
arbitrary file order, per-slice rescale values, uneven steps, missing slices, overlapping slabs
and tilted gantries. This reader relies only on the geometry tags (ImagePositionPatient,
ImageOrientationPatient, PixelSpacing), never on file names or InstanceNumber, and places every
slice by its own position (volume/slice_stack.py): an ordinary series is copied as it is, any
other is resampled onto a regular grid and the notice says what was found.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.volume.dicom_images import DicomImage, PixelReader, read_images
from cubecloud_cli.volume.dicom_series import choose_stack, group_stacks
from cubecloud_cli.volume.scan import Scan
from cubecloud_cli.volume.slice_stack import StackPlan, plan_stack, resample_stack

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def _check_geometry(images: list[DicomImage]) -> None:
    for image in images:
        if image.placed is None:
            raise CubecloudError(
                f"{image.where} lacks {image.missing}, so the slices cannot be placed in space: "
                f"convert the series with a tool that knows its geometry"
            )
        s = image.placed
        values = np.concatenate([s.position, s.row_direction, s.column_direction, [s.row_spacing, s.column_spacing]])
        directions_ok = all(abs(np.linalg.norm(d) - 1.0) < 0.01 for d in (s.row_direction, s.column_direction))
        if not np.all(np.isfinite(values)) or not directions_ok or min(s.row_spacing, s.column_spacing) <= 0:
            raise CubecloudError(
                f"{image.where} has a broken position, orientation or pixel spacing: the header is corrupt; "
                f"export the series again"
            )


def _notice(plan: StackPlan) -> str:
    """One line on what was found in a series that is not a regular grid."""
    found = [f"slice steps {plan.steps.min():.3g}–{plan.steps.max():.3g} mm"]
    if plan.gaps:
        found.append(
            f"{len(plan.gaps)} gap(s) (a missing slice?), the first from {plan.gaps[0][0]:.1f} "
            f"to {plan.gaps[0][1]:.1f} mm along the slice normal"
        )
    shared = plan.describe()["shared_positions"]
    if shared:
        found.append(f"{shared} slice(s) at a position already taken (overlapping slabs), averaged")
    if plan.tilt_deg > 0.01:
        found.append(f"gantry tilt {plan.tilt_deg:.1f}°")
    grid = "×".join(f"{v:.3g}" for v in plan.spacing)
    return f"{', '.join(found)}: resampled from each slice's own position onto a {grid} mm grid"


def read_dicom_series(source: Path, series_uid: str | None = None) -> Scan:
    """Read a series as a Scan in RAS+ scanner millimetres: from a folder (the largest axial-like
    stack, or the series ``series_uid``), or from one enhanced multi-frame file."""
    source = Path(source)
    paths = sorted(p for p in source.iterdir() if p.is_file()) if source.is_dir() else [source]
    images = read_images(paths)
    if not images:
        raise CubecloudError(
            f"{source} holds no DICOM image files: point SCAN at a DICOM series folder, "
            f"a NIfTI (.nii/.nii.gz), NRRD (.nrrd) or .npy file"
        )
    stack, note = choose_stack(group_stacks(images), series_uid, source)
    if len(stack.images) < 2:
        raise CubecloudError(f"{source} holds a single DICOM image; cubecloud needs a 3D series of at least 2 slices")
    _check_geometry(stack.images)
    return _stack_scan(stack.images, source, [note] if note else [])


def read_dicom_file(path: Path, series_uid: str | None = None) -> Scan:
    """One DICOM file named as the scan: an enhanced file is the series; a classic one is read
    with the rest of its series from its folder."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    try:
        header = pydicom.dcmread(path, stop_before_pixels=True)
    except (InvalidDicomError, OSError, ValueError, EOFError) as exc:
        raise CubecloudError(f"cannot read {path} as DICOM ({exc}): the file is corrupt or not DICOM") from None
    if int(header.get("NumberOfFrames", 1) or 1) > 1:
        return read_dicom_series(path, series_uid)
    scan = read_dicom_series(path.parent, series_uid or str(header.get("SeriesInstanceUID", "")) or None)
    scan.notes.append(f"{path} is one file: read its series from the folder {path.parent}")
    return scan


def _stack_scan(images: list[DicomImage], source: Path, notes: list[str]) -> Scan:
    slices = [image.placed for image in images]
    try:
        plan = plan_stack(slices)
    except ValueError:
        raise CubecloudError(
            f"every slice of {source} lies at the same position: it holds one slice repeated, not a 3D series"
        ) from None
    shared = plan.describe()["shared_positions"]
    if shared > len(plan.positions) // 4:
        raise CubecloudError(
            f"{source} has {shared} slices at positions already taken: it mixes series "
            f"or repeats files; keep one series per folder"
        )
    pixels = PixelReader()
    if plan.regular:
        volume = np.empty(plan.shape, dtype=np.float32)
        for k, group in enumerate(plan.positions):
            volume[:, :, k] = pixels(images[group[0]])
    else:
        notes.append(_notice(plan))
        volume = resample_stack(lambda i: pixels(images[i]), slices, plan, fill=np.nan)
        outside = np.isnan(volume)
        if outside.any():  # beyond a slice's footprint (a tilted or shifted slab): air
            volume[outside] = np.nanmin(volume) if not outside.all() else 0.0
    first = images[0].header
    enhanced = images[0].frame is not None
    acquisition = {
        **plan.describe(),
        "series_uid": images[0].series_uid,
        "enhanced_multiframe": enhanced,
        "gantry_detector_tilt_deg": _float_or_none(first.get("GantryDetectorTilt")),
    }
    modality = str(first.get("Modality", "")).lower()
    return Scan(
        data=volume,
        affine=LPS_TO_RAS @ plan.affine(),
        source_format=f"DICOM {'enhanced multi-frame ' if enhanced else ''}series ({len(images)} slices)",
        modality=modality if modality in ("ct", "mr") else None,
        notes=notes,
        acquisition=acquisition,
    )


def _float_or_none(value) -> float | None:
    try:
        return float(value)
    except (TypeError, ValueError):
        return None
