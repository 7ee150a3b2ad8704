"""The 2D images in DICOM files, each with where it lies and how its stored values become physical
ones: one per classic file, one per frame of an enhanced (multi-frame) file, whose per-frame
functional groups carry each frame's position, orientation, pixel spacing and rescale, and whose
shared functional groups carry whatever all frames have in common."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.volume.slice_stack import PlacedSlice

GEOMETRY_TAGS = ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing")


@dataclass
class DicomImage:
    """One 2D image: its file (and frame, in a multi-frame file), where it lies, and its rescale."""

    path: Path
    frame: int | None  # index in a multi-frame file; None for a classic one-image file
    header: object  # the file's pydicom Dataset, without pixels
    placed: PlacedSlice | None  # None when the header cannot place it
    missing: str | None  # the geometry tag it lacks, when ``placed`` is None
    slope: float
    intercept: float

    @property
    def series_uid(self) -> str:
        return str(self.header.get("SeriesInstanceUID", ""))

    @property
    def localizer(self) -> bool:
        return "LOCALIZER" in [str(v).upper() for v in (self.header.get("ImageType") or [])]

    @property
    def where(self) -> str:
        return str(self.path) if self.frame is None else f"{self.path} (frame {self.frame + 1})"


def _placed(position, orientation, spacing, rows, columns) -> PlacedSlice:
    orientation = np.asarray(orientation, dtype=float)
    row_spacing, column_spacing = (float(v) for v in spacing)
    return PlacedSlice(np.asarray(position, dtype=float), orientation[:3], orientation[3:],
                       row_spacing, column_spacing, int(rows), int(columns))  # fmt: skip


def _rescale(group) -> tuple[float, float]:
    return float(group.get("RescaleSlope", 1) or 1), float(group.get("RescaleIntercept", 0) or 0)


def classic_image(path: Path, header) -> DicomImage:
    missing = next((tag for tag in GEOMETRY_TAGS if tag not in header), None)
    placed = None
    if missing is None:
        placed = _placed(header.ImagePositionPatient, header.ImageOrientationPatient, header.PixelSpacing,
                         header.Rows, header.Columns)  # fmt: skip
    return DicomImage(path, None, header, placed, missing, *_rescale(header))


def _functional_item(frame_groups, shared_groups, sequence: str):
    """The first item of a functional-group sequence for one frame: its own, else the shared one."""
    for groups in (frame_groups, shared_groups):
        items = groups.get(sequence) if groups is not None else None
        if items:
            return items[0]
    return None


def enhanced_images(path: Path, header) -> list[DicomImage]:
    """One image per frame of an enhanced (multi-frame) file."""
    count = int(header.get("NumberOfFrames", 1) or 1)
    shared = header.SharedFunctionalGroupsSequence[0] if "SharedFunctionalGroupsSequence" in header else None
    per_frame = header.get("PerFrameFunctionalGroupsSequence") or []
    if len(per_frame) not in (0, count):
        raise CubecloudError(
            f"{path} has {count} frames but {len(per_frame)} per-frame functional groups: the header is corrupt"
        )
    images = []
    for frame in range(count):
        own = per_frame[frame] if per_frame else None
        plane = _functional_item(own, shared, "PlanePositionSequence")
        orientation = _functional_item(own, shared, "PlaneOrientationSequence")
        measures = _functional_item(own, shared, "PixelMeasuresSequence")
        values = _functional_item(own, shared, "PixelValueTransformationSequence")
        found = {
            "ImagePositionPatient": plane.get("ImagePositionPatient") if plane is not None else None,
            "ImageOrientationPatient": orientation.get("ImageOrientationPatient") if orientation is not None else None,
            "PixelSpacing": measures.get("PixelSpacing") if measures is not None else None,
        }
        missing = next((tag for tag, value in found.items() if value is None), None)
        placed = None if missing else _placed(*found.values(), header.Rows, header.Columns)
        rescale = _rescale(values if values is not None else header)
        images.append(DicomImage(path, frame, header, placed, missing, *rescale))
    return images


def read_images(paths) -> list[DicomImage]:
    """The images in the DICOM files among ``paths``; other files are skipped."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    images: list[DicomImage] = []
    for path in paths:
        try:
            header = pydicom.dcmread(path, stop_before_pixels=True)
        except (InvalidDicomError, OSError, ValueError, EOFError):
            continue
        if not ("PixelSpacing" in header or "ImagePositionPatient" in header or "Rows" in header):
            continue
        if int(header.get("NumberOfFrames", 1) or 1) > 1 or "PerFrameFunctionalGroupsSequence" in header:
            images.extend(enhanced_images(path, header))
        else:
            images.append(classic_image(path, header))
    return images


class PixelReader:
    """Physical values of images as (columns, rows) float32, rescaled in float: uint16 pixels with
    intercept −1024 (or int16 with a large slope) overflow their own dtype. A multi-frame file is
    decoded once and kept while its frames are read."""

    def __init__(self) -> None:
        self._frames: tuple[Path, np.ndarray] | None = None

    def __call__(self, image: DicomImage) -> np.ndarray:
        if image.frame is None:
            pixels = self._decode(image.path)
        else:
            if self._frames is None or self._frames[0] != image.path:
                decoded = self._decode(image.path)
                self._frames = (image.path, decoded if decoded.ndim == 3 else decoded[None])
            pixels = self._frames[1][image.frame]
        if pixels.shape != (image.placed.rows, image.placed.columns):
            raise CubecloudError(f"{image.where} has a different image size from the rest of its series")
        return (pixels.astype(np.float32) * image.slope + image.intercept).T

    @staticmethod
    def _decode(path: Path) -> np.ndarray:
        import pydicom

        try:
            dataset = pydicom.dcmread(path)
        except Exception as exc:
            raise CubecloudError(f"cannot read {path} ({exc}): the file is corrupt or truncated") from None
        try:
            return dataset.pixel_array
        except Exception as exc:  # decoder plugins raise many types; all mean "cannot decode"
            syntax = dataset.file_meta.get("TransferSyntaxUID", "unknown")
            raise CubecloudError(
                f"cannot decode the pixels of {path} (transfer syntax {syntax}: {exc}); "
                f"install a decoder, e.g. `pip install python-gdcm`"
            ) from None
