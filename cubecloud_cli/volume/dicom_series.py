"""Which images of a DICOM folder make the series to read: images grouped into stacks (one series,
one orientation, one image size), localizers and scouts set aside, and the largest axial-like
stack chosen unless the user names a series."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.volume.dicom_images import DicomImage

# A stack whose normal is within 45° of the table axis counts as axial (a tilted gantry included).
AXIAL_COSINE = float(np.cos(np.radians(45.0)))
LISTED_OTHERS = 3


@dataclass
class Stack:
    """Images of one series sharing an orientation and an image size."""

    series_uid: str
    normal: np.ndarray | None  # None when the images cannot be placed
    images: list[DicomImage]

    @property
    def plane(self) -> str:
        """axial, coronal or sagittal by the axis the slice normal is nearest, or unplaced."""
        if self.normal is None:
            return "unplaced"
        return ("sagittal", "coronal", "axial")[int(np.argmax(np.abs(self.normal)))]

    @property
    def localizer(self) -> bool:
        return any(image.localizer for image in self.images)

    @property
    def description(self) -> str:
        text = str(self.images[0].header.get("SeriesDescription", "") or "")
        kind = "localizer" if self.localizer else self.plane
        return f"{self.series_uid or 'no UID'} ({len(self.images)} images, {kind}{', ' + repr(text) if text else ''})"


def _normal(image: DicomImage) -> np.ndarray | None:
    if image.placed is None:
        return None
    normal = np.cross(image.placed.row_direction, image.placed.column_direction)
    length = float(np.linalg.norm(normal))
    return normal / length if np.isfinite(length) and length > 0 else None


def group_stacks(images: list[DicomImage]) -> list[Stack]:
    """Images grouped by series UID, orientation (to 1e-4) and image size. The UIDs may be empty
    (as in anonymised exports), so geometry also separates series."""
    groups: dict[tuple, list[DicomImage]] = defaultdict(list)
    for image in images:
        orientation = None
        if image.placed is not None:
            orientation = tuple(np.round(np.r_[image.placed.row_direction, image.placed.column_direction], 4))
        size = (image.header.get("Rows"), image.header.get("Columns"))
        groups[(image.series_uid, orientation, size)].append(image)
    return [Stack(key[0], _normal(members[0]), members) for key, members in groups.items()]


def _refuse_multi_stack_files(stack: Stack, stacks: list[Stack]) -> None:
    """An enhanced file whose frames fall into several stacks (an axial, a coronal and a sagittal
    reconstruction in one file) cannot be one volume."""
    for path in {image.path for image in stack.images if image.frame is not None}:
        sharing = [other for other in stacks if any(image.path == path for image in other.images)]
        if len(sharing) > 1:
            names = ", ".join(f"{other.plane} ({len(other.images)} frames)" for other in sharing)
            raise CubecloudError(
                f"{path} holds {len(sharing)} stacks of different orientation or size: {names}; cubecloud reads "
                f"one stack: save each to its own file (dcm2niix, for one, writes one NIfTI per stack)"
            )


def choose_stack(stacks: list[Stack], series_uid: str | None, where) -> tuple[Stack, str | None]:
    """The stack to read and, when the folder held others, one line saying which was taken.

    By default: the largest axial-like stack that is not a localizer (then the largest of any
    orientation); ``series_uid`` picks a series by its SeriesInstanceUID instead.
    """
    if series_uid is not None:
        chosen = [stack for stack in stacks if stack.series_uid == series_uid]
        if not chosen:
            available = "; ".join(stack.description for stack in sorted(stacks, key=lambda s: -len(s.images)))
            raise CubecloudError(f"--series {series_uid} is not in {where}, which holds {available}")
        candidates = chosen
    else:
        volumes = [stack for stack in stacks if not stack.localizer and len(stack.images) > 1]
        axial = [stack for stack in volumes if stack.normal is not None and abs(stack.normal[2]) >= AXIAL_COSINE]
        candidates = axial or volumes or stacks
    stack = max(candidates, key=lambda s: len(s.images))
    _refuse_multi_stack_files(stack, stacks)
    others = [other for other in stacks if other is not stack]
    if not others:
        return stack, None
    listed = "; ".join(other.description for other in others[:LISTED_OTHERS])
    more = f" and {len(others) - LISTED_OTHERS} more" if len(others) > LISTED_OTHERS else ""
    return stack, (
        f"{where} holds {len(stacks)} stacks: reading {stack.description}; the others: {listed}{more} "
        f"(pick a series with --series UID)"
    )
