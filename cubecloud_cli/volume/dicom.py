"""DICOM series folders: slice ordering, rescale, compressed pixel data, LPS -> RAS.

Real series are messy: files without extensions, empty UIDs, JPEG 2000 pixel data, slices in
arbitrary file order, per-slice rescale values. This reader relies only on the geometry tags
(ImagePositionPatient, ImageOrientationPatient, PixelSpacing) and sorts slices by their position
along the slice normal, never by file name or InstanceNumber.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np

from cubecloud_cli.errors import CubecloudError
from cubecloud_cli.volume.scan import Scan

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def _read_headers(folder: Path):
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
    for tag in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing"):
        if tag not in first:
            raise CubecloudError(
                f"{series[0][0]} lacks {tag}, so the slices cannot be placed in space: "
                f"convert the series with a tool that knows its geometry"
            )

    orientation = np.asarray(first.ImageOrientationPatient, dtype=float)
    row_direction, column_direction = orientation[:3], orientation[3:]
    normal = np.cross(row_direction, column_direction)
    positions = np.array([np.asarray(h.ImagePositionPatient, float) for _, h in series])
    along_normal = positions @ normal
    order = np.argsort(along_normal, kind="stable")
    series = [series[i] for i in order]
    along_normal = along_normal[order]

    steps = np.diff(along_normal)
    if np.any(steps < 1e-3):
        raise CubecloudError(
            f"{folder} has two slices at the same position: it mixes series or repeats files; "
            f"keep one series per folder"
        )
    slice_step = (along_normal[-1] - along_normal[0]) / (len(series) - 1)
    if np.max(np.abs(steps - slice_step)) > 0.01 * slice_step + 1e-3:
        notes.append(
            f"slice steps vary from {steps.min():.3g} to {steps.max():.3g} mm (a missing slice?); "
            f"using their mean, {slice_step:.4g} mm"
        )

    volume = np.empty((int(first.Columns), int(first.Rows), len(series)), dtype=np.float32)
    import pydicom

    for k, (path, _) in enumerate(series):
        try:
            dataset = pydicom.dcmread(path)
        except Exception as exc:
            raise CubecloudError(f"cannot read {path} ({exc}): the file is corrupt or truncated") from None
        try:
            pixels = dataset.pixel_array
        except Exception as exc:  # decoder plugins raise many types; all mean "cannot decode"
            syntax = dataset.file_meta.get("TransferSyntaxUID", "unknown")
            raise CubecloudError(
                f"cannot decode the pixels of {path} (transfer syntax {syntax}: {exc}); "
                f"install a decoder, e.g. `pip install python-gdcm`"
            ) from None
        if pixels.shape != (volume.shape[1], volume.shape[0]):
            raise CubecloudError(f"{path} has a different image size from the rest of its series")
        slope = float(dataset.get("RescaleSlope", 1) or 1)
        intercept = float(dataset.get("RescaleIntercept", 0) or 0)
        # Rescale in float: uint16 pixels with intercept -1024 (or int16 with a large slope)
        # overflow their own dtype.
        volume[:, :, k] = (pixels.astype(np.float32) * slope + intercept).T

    spacing = np.asarray(first.PixelSpacing, dtype=float)  # (between rows, between columns)
    affine_lps = np.eye(4)
    affine_lps[:3, 0] = row_direction * spacing[1]  # array axis 0 runs along a row: column index
    affine_lps[:3, 1] = column_direction * spacing[0]
    affine_lps[:3, 2] = normal * slice_step
    affine_lps[:3, 3] = np.asarray(series[0][1].ImagePositionPatient, float)
    modality = str(first.get("Modality", "")).lower()
    return Scan(
        data=volume,
        affine=LPS_TO_RAS @ affine_lps,
        source_format=f"DICOM series ({len(series)} slices)",
        modality=modality if modality in ("ct", "mr") else None,
        notes=notes,
    )
