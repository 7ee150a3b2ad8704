"""DICOM series written with pydicom from a phantom defined in scanner space, so that every pixel
holds the phantom's value at its own position, whatever the series' geometry.

The phantom (LPS millimetres): air (−1000 HU) around an ellipsoidal body of soft tissue (40 HU,
rising 4 HU per mm along the table) with a dense ball (1500 HU) at MARK and a bony bar along the
table; every edge is a smooth step 6 mm wide, as a scanner resolves it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

MARK = np.array([12.0, -8.0, 30.0])
MARK_RADIUS = 9.0
MARK_HU, BODY_HU, AIR_HU, BONE_HU = 1500.0, 40.0, -1000.0, 700.0
BODY_GRADIENT = 4.0  # HU per mm along the table
EDGE_MM = 3.0  # half the width of every edge
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
ENHANCED_CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2.1"


def smooth_inside(signed_distance: np.ndarray, width: float = EDGE_MM) -> np.ndarray:
    """1 inside, 0 outside, a smooth (C1) step across ±``width`` mm of the boundary: an edge as a
    scanner resolves it, so that two grids sampling it differ only by their sampling."""
    t = np.clip(0.5 - signed_distance / (2.0 * width), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def phantom_hu(points: np.ndarray) -> np.ndarray:
    """HU at LPS points (..., 3)."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    ellipsoid = np.sqrt((x / 70.0) ** 2 + (y / 50.0) ** 2 + ((z - 30.0) / 60.0) ** 2)
    body = smooth_inside((ellipsoid - 1.0) * 50.0)
    values = AIR_HU + body * (BODY_HU + BODY_GRADIENT * z - AIR_HU)  # along the table: a misplaced slice shows
    bar = body * smooth_inside(np.hypot(x + 30.0, y - 20.0) - 8.0)
    values = values + bar * (BONE_HU - values)
    ball = smooth_inside(np.linalg.norm(points - MARK, axis=-1) - MARK_RADIUS)
    return values + ball * (MARK_HU - values)


def slice_geometry(z: float, tilt_deg: float, rows: int, columns: int, spacing: tuple[float, float]):
    """Position and orientation of an axial slice acquired at table position ``z`` with the gantry
    tilted by ``tilt_deg`` about the patient's left–right axis: the rows lean, the origin stays on
    the table's path (as scanners write it)."""
    angle = math.radians(tilt_deg)
    row_direction = np.array([1.0, 0.0, 0.0])
    column_direction = np.array([0.0, math.cos(angle), math.sin(angle)])
    centre_offset = (columns - 1) / 2 * spacing[1] * row_direction + (rows - 1) / 2 * spacing[0] * column_direction
    position = np.array([0.0, 0.0, z]) - centre_offset
    return position, row_direction, column_direction


def slice_pixels_hu(position, row_direction, column_direction, rows, columns, spacing) -> np.ndarray:
    """The phantom sampled at each pixel centre: (rows, columns) HU."""
    row, column = np.meshgrid(np.arange(rows), np.arange(columns), indexing="ij")
    points = (position + column[..., None] * spacing[1] * row_direction
              + row[..., None] * spacing[0] * column_direction)  # fmt: skip
    return phantom_hu(points)


def _base_dataset(sop_class: str, series_uid: str, study_uid: str):
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    meta = FileMetaDataset()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = generate_uid()
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, meta.MediaStorageSOPInstanceUID
    ds.StudyInstanceUID, ds.SeriesInstanceUID = study_uid, series_uid
    ds.PatientName, ds.PatientID, ds.StudyDate, ds.SeriesNumber = "PHANTOM", "0", "20260101", 2
    ds.Modality = "CT"
    ds.FrameOfReferenceUID = generate_uid()
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
    ds.PixelRepresentation = 1
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    return ds


def write_series(
    folder: Path,
    table_positions,
    *,
    tilt_deg: float = 0.0,
    rows: int = 48,
    columns: int = 56,
    spacing: tuple[float, float] = (3.0, 3.0),
    thickness: float | None = None,
    series_uid: str | None = None,
    description: str = "phantom",
    image_type: tuple[str, ...] = ("ORIGINAL", "PRIMARY", "AXIAL"),
) -> Path:
    """A classic CT series, one file per slice (files in shuffled order), int16 with intercept −1024."""
    from pydicom.uid import generate_uid

    folder.mkdir(parents=True, exist_ok=True)
    series_uid = series_uid or generate_uid()
    study_uid = generate_uid()
    order = np.random.default_rng(len(table_positions)).permutation(len(table_positions))
    for number, k in enumerate(order):
        position, row_direction, column_direction = slice_geometry(table_positions[k], tilt_deg, rows, columns, spacing)
        ds = _base_dataset(CT_IMAGE_STORAGE, series_uid, study_uid)
        ds.SeriesDescription = description
        ds.ImageType = list(image_type)
        ds.InstanceNumber, ds.AcquisitionNumber = int(k) + 1, 1  # spatial, as scanners number them
        ds.ImagePositionPatient = [round(float(v), 6) for v in position]
        ds.ImageOrientationPatient = [round(float(v), 8) for v in (*row_direction, *column_direction)]
        ds.PixelSpacing = list(spacing)
        ds.SliceThickness = thickness if thickness is not None else 2.5
        # The sign dcm2niix estimates from these slice vectors (the tag itself is nominal).
        ds.GantryDetectorTilt = -tilt_deg
        ds.PatientPosition = "HFS"
        ds.Rows, ds.Columns = rows, columns
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        hu = slice_pixels_hu(position, row_direction, column_direction, rows, columns, spacing)
        ds.PixelData = np.round(hu + 1024).astype(np.int16).tobytes()
        ds.save_as(folder / f"IM{series_uid[-4:]}{number:05d}", enforce_file_format=True)  # series may share a folder
    return folder


def _item(**tags):
    from pydicom.dataset import Dataset

    item = Dataset()
    for name, value in tags.items():
        setattr(item, name, value)
    return item


def write_enhanced(
    path: Path,
    table_positions,
    *,
    tilt_deg: float = 0.0,
    rows: int = 48,
    columns: int = 56,
    spacing: tuple[float, float] = (3.0, 3.0),
    extra_stack: str | None = None,
    varying_rescale: bool = True,
) -> Path:
    """An enhanced CT file: one frame per table position, each frame's position, orientation,
    pixel spacing and rescale in its own functional groups (with ``varying_rescale``, odd frames
    stored at half scale with slope 2, so a reader that ignores the per-frame rescale is caught). ``extra_stack="coronal"``
    appends frames of a second orientation, as some scanners put several reconstructions in one file."""
    from pydicom.sequence import Sequence
    from pydicom.uid import generate_uid

    ds = _base_dataset(ENHANCED_CT_IMAGE_STORAGE, generate_uid(), generate_uid())
    ds.ImageType = ["ORIGINAL", "PRIMARY", "VOLUME", "NONE"]
    ds.Rows, ds.Columns = rows, columns
    ds.SharedFunctionalGroupsSequence = Sequence([_item(CTExposureSequence=Sequence([_item(CTDIvol=10.0)]))])
    frames, pixels = [], []
    geometries = [slice_geometry(z, tilt_deg, rows, columns, spacing) for z in table_positions]
    if extra_stack == "coronal":
        for y in (-10.0, 0.0, 10.0):
            geometries.append((np.array([-80.0, y, -20.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])))
    for number, (position, row_direction, column_direction) in enumerate(geometries):
        slope, intercept = (2.0, -1024.0) if number % 2 and varying_rescale else (1.0, -1024.0)
        hu = slice_pixels_hu(position, row_direction, column_direction, rows, columns, spacing)
        pixels.append(np.round((hu - intercept) / slope).astype(np.int16))
        frames.append(_item(
            PlanePositionSequence=Sequence([_item(ImagePositionPatient=[round(float(v), 6) for v in position])]),
            PlaneOrientationSequence=Sequence([_item(ImageOrientationPatient=[
                round(float(v), 8) for v in (*row_direction, *column_direction)])]),
            PixelMeasuresSequence=Sequence([_item(PixelSpacing=list(spacing), SliceThickness=2.5)]),
            PixelValueTransformationSequence=Sequence([_item(RescaleSlope=slope, RescaleIntercept=intercept,
                                                             RescaleType="HU")]),
            FrameContentSequence=Sequence([_item(InStackPositionNumber=number + 1)]),
        ))  # fmt: skip
    ds.PerFrameFunctionalGroupsSequence = Sequence(frames)
    ds.NumberOfFrames = len(frames)
    ds.PixelData = np.stack(pixels).tobytes()
    path.parent.mkdir(parents=True, exist_ok=True)
    ds.save_as(path, enforce_file_format=True)
    return path


LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def correlation_with_nifti(scan, nifti_path: Path, body_hu: float = -500.0) -> float:
    """Pearson r between ``scan`` and a NIfTI on the scan's body voxels, the NIfTI sampled at the
    same scanner positions through its own affine (nearest voxel); positions outside it are left out."""
    import nibabel as nib

    image = nib.load(str(nifti_path))
    theirs = np.asarray(image.dataobj, dtype=np.float32).reshape(image.shape[:3])
    index = np.argwhere(scan.data > body_hu)
    ras = scan.affine @ np.c_[index, np.ones(len(index))].T
    nearest = np.round(np.linalg.solve(image.affine, ras)[:3].T).astype(int)
    inside = np.all((nearest >= 0) & (nearest < theirs.shape), axis=1)
    ours = scan.data[tuple(index[inside].T)]
    return float(np.corrcoef(ours, theirs[tuple(nearest[inside].T)])[0, 1])


def correlation_with_phantom(scan) -> float:
    """Pearson r between ``scan`` and the phantom at every voxel centre (the ground truth)."""
    index = np.stack(np.meshgrid(*[np.arange(n) for n in scan.data.shape], indexing="ij"), -1).reshape(-1, 3)
    lps = (LPS_TO_RAS @ scan.affine @ np.c_[index, np.ones(len(index))].T)[:3].T
    return float(np.corrcoef(scan.data.reshape(-1), phantom_hu(lps))[0, 1])


def dcm2niix_volume(source: Path, out: Path) -> Path:
    """dcm2niix's conversion of ``source``: its corrected file (_Tilt, _Eq) when it writes one."""
    import subprocess

    out.mkdir(parents=True, exist_ok=True)
    subprocess.run(["dcm2niix", "-z", "y", "-o", str(out), "-f", "series", str(source)],
                   capture_output=True, check=True, timeout=120)  # fmt: skip
    written = sorted(out.glob("series*.nii.gz"))
    corrected = [path for path in written if "_Tilt" in path.name or "_Eq" in path.name]
    return (corrected or written)[-1]
