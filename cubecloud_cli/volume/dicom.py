"""DICOM series folders: each slice where it was acquired, rescale, compressed pixel data, LPS -> RAS.

Real series are messy: files without extensions, empty UIDs, JPEG 2000 pixel data, slices in
arbitrary file order, per-slice rescale values, uneven steps, missing slices, overlapping slabs
and tilted gantries. This reader relies only on the geometry tags (ImagePositionPatient,
ImageOrientationPatient, PixelSpacing), never on file names or InstanceNumber, and places every
slice by its own position (volume/slice_stack.py): an ordinary series is copied as it is, any
other is resampled onto a regular grid and the notice says what was found.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cubecloud_cli.errors import CubecloudError
from cubecloud_cli.volume.scan import Scan
from cubecloud_cli.volume.slice_stack import PlacedSlice, StackPlan, plan_stack, resample_stack

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
GEOMETRY_TAGS = ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing")


@dataclass
class DicomImage:
    """One 2D image of a series: its file, where it lies, and how its stored values map to physical ones."""

    path: Path
    header: object  # the pydicom Dataset without pixels
    placed: PlacedSlice
    slope: float
    intercept: float


def _read_headers(folder: Path) -> list[tuple[Path, object]]:
    import pydicom
    from pydicom.errors import InvalidDicomError

    headers = []
    for path in sorted(p for p in folder.iterdir() if p.is_file()):
        try:
            header = pydicom.dcmread(path, stop_before_pixels=True)
        except (InvalidDicomError, OSError, ValueError, EOFError):
            continue
        if "PixelSpacing" in header or "ImagePositionPatient" in header or "Rows" in header:
            headers.append((path, header))
    return headers


def _series_key(header) -> tuple:
    # The UIDs may be empty (as in anonymised exports), so geometry also separates series.
    orientation = tuple(np.round(np.asarray(header.get("ImageOrientationPatient", [0] * 6), float), 4))
    return (str(header.get("SeriesInstanceUID", "")), orientation, header.get("Rows"), header.get("Columns"))


def _classic_image(path: Path, header) -> DicomImage:
    for tag in GEOMETRY_TAGS:
        if tag not in header:
            raise CubecloudError(
                f"{path} lacks {tag}, so the slices cannot be placed in space: "
                f"convert the series with a tool that knows its geometry"
            )
    orientation = np.asarray(header.ImageOrientationPatient, dtype=float)
    row_spacing, column_spacing = (float(v) for v in header.PixelSpacing)
    placed = PlacedSlice(
        np.asarray(header.ImagePositionPatient, dtype=float), orientation[:3], orientation[3:],
        row_spacing, column_spacing, int(header.Rows), int(header.Columns),
    )  # fmt: skip
    slope = float(header.get("RescaleSlope", 1) or 1)
    intercept = float(header.get("RescaleIntercept", 0) or 0)
    return DicomImage(path, header, placed, slope, intercept)


def _check_geometry(images: list[DicomImage]) -> None:
    for image in images:
        s = image.placed
        values = np.concatenate([s.position, s.row_direction, s.column_direction, [s.row_spacing, s.column_spacing]])
        directions_ok = all(abs(np.linalg.norm(d) - 1.0) < 0.01 for d in (s.row_direction, s.column_direction))
        if not np.all(np.isfinite(values)) or not directions_ok or min(s.row_spacing, s.column_spacing) <= 0:
            raise CubecloudError(
                f"{image.path} has a broken position, orientation or pixel spacing: the header is corrupt; "
                f"export the series again"
            )


def _pixels(image: DicomImage) -> np.ndarray:
    """The image's physical values as (columns, rows) float32, rescaled in float: uint16 pixels
    with intercept −1024 (or int16 with a large slope) overflow their own dtype."""
    import pydicom

    try:
        dataset = pydicom.dcmread(image.path)
    except Exception as exc:
        raise CubecloudError(f"cannot read {image.path} ({exc}): the file is corrupt or truncated") from None
    try:
        pixels = dataset.pixel_array
    except Exception as exc:  # decoder plugins raise many types; all mean "cannot decode"
        syntax = dataset.file_meta.get("TransferSyntaxUID", "unknown")
        raise CubecloudError(
            f"cannot decode the pixels of {image.path} (transfer syntax {syntax}: {exc}); "
            f"install a decoder, e.g. `pip install python-gdcm`"
        ) from None
    if pixels.shape != (image.placed.rows, image.placed.columns):
        raise CubecloudError(f"{image.path} has a different image size from the rest of its series")
    return (pixels.astype(np.float32) * image.slope + image.intercept).T


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


def read_dicom_series(folder: Path) -> Scan:
    """Read the largest series in ``folder`` as a Scan in RAS+ scanner millimetres."""
    headers = _read_headers(folder)
    if not headers:
        raise CubecloudError(
            f"{folder} holds no DICOM image files: point SCAN at a DICOM series folder, "
            f"a NIfTI (.nii/.nii.gz), NRRD (.nrrd) or .npy file"
        )
    groups: dict[tuple, list] = defaultdict(list)
    for path, header in headers:
        groups[_series_key(header)].append((path, header))
    series = max(groups.values(), key=len)
    notes = []
    if len(groups) > 1:
        notes.append(f"{folder} holds {len(groups)} series; using the largest ({len(series)} slices)")
    first = series[0][1]
    if int(first.get("NumberOfFrames", 1) or 1) > 1:
        raise CubecloudError(
            f"{series[0][0]} is a multi-frame (enhanced) DICOM, which cubecloud does not read yet: "
            f"convert it to NIfTI first (for example with dcm2niix)"
        )
    if len(series) < 2:
        raise CubecloudError(f"{folder} holds a single DICOM slice; cubecloud needs a 3D series of at least 2 slices")
    images = [_classic_image(path, header) for path, header in series]
    _check_geometry(images)
    return _stack_scan(images, first, notes)


def _stack_scan(images: list[DicomImage], first, notes: list[str]) -> Scan:
    slices = [image.placed for image in images]
    try:
        plan = plan_stack(slices)
    except ValueError:
        raise CubecloudError(
            f"every slice of {images[0].path.parent} lies at the same position: it holds one slice repeated, "
            f"not a 3D series"
        ) from None
    shared = plan.describe()["shared_positions"]
    if shared > len(plan.positions) // 4:
        raise CubecloudError(
            f"{images[0].path.parent} has {shared} slices at positions already taken: it mixes series "
            f"or repeats files; keep one series per folder"
        )
    if plan.regular:
        volume = np.empty(plan.shape, dtype=np.float32)
        for k, group in enumerate(plan.positions):
            volume[:, :, k] = _pixels(images[group[0]])
    else:
        notes.append(_notice(plan))
        volume = resample_stack(lambda i: _pixels(images[i]), slices, plan, fill=np.nan)
        outside = np.isnan(volume)
        if outside.any():  # beyond a slice's footprint (a tilted or shifted slab): air
            volume[outside] = np.nanmin(volume) if not outside.all() else 0.0
    acquisition = {**plan.describe(), "gantry_detector_tilt_deg": _float_or_none(first.get("GantryDetectorTilt"))}
    modality = str(first.get("Modality", "")).lower()
    return Scan(
        data=volume,
        affine=LPS_TO_RAS @ plan.affine(),
        source_format=f"DICOM series ({len(images)} slices)",
        modality=modality if modality in ("ct", "mr") else None,
        notes=notes,
        acquisition=acquisition,
    )


def _float_or_none(value) -> float | None:
    try:
        return float(value)
    except (TypeError, ValueError):
        return None
