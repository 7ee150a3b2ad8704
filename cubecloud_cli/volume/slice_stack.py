"""A stack of parallel image slices, each placed by its own position, resampled onto one regular grid.

Scanners do not promise a regular grid. A series may join a thin and a thick slab, miss a slice,
overlap two slabs, or be acquired with the gantry tilted: then each slice's origin moves along the
table, not along the slice normal, and stacking the slices along the normal shears the anatomy.
Here every slice keeps the place it was acquired at. The output grid's axes are the slices' row
and column directions and their normal; an output voxel takes its value from the two slices
around it along the normal (linear weights by distance), each sampled at the voxel's own in-plane
position (bilinear, which is an exact copy when the slices line up, as in an ordinary series).

All positions are in the scanner's LPS millimetres, as DICOM writes them; the caller converts the
affine to RAS.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

# Slices closer than this along the normal are one position (overlapping slabs, repeated files).
SAME_POSITION_MM = 1e-3
# Steps within this fraction of their mean count as one regular step.
REGULAR_STEP_TOLERANCE = 0.01
# A step this many times the output step is a gap (a missing slice, or two slabs apart).
GAP_FACTOR = 1.5
# Fractional pixel offsets below this are rounding in the header, not a shift.
WHOLE_PIXEL_TOLERANCE = 1e-4


@dataclass(frozen=True)
class PlacedSlice:
    """Where one image lies in the scanner: DICOM's ImagePositionPatient (the centre of the first
    pixel), ImageOrientationPatient (the row and column direction cosines) and PixelSpacing
    (between rows, between columns), with the image's size."""

    position: np.ndarray  # (3,) mm
    row_direction: np.ndarray  # (3,) along a row: the direction of increasing column index
    column_direction: np.ndarray  # (3,) down a column: the direction of increasing row index
    row_spacing: float  # mm between the centres of adjacent rows
    column_spacing: float  # mm between the centres of adjacent columns
    rows: int
    columns: int


@dataclass
class StackPlan:
    """The output grid of a stack and where each input slice lies in it."""

    axes: np.ndarray  # (3, 3): columns are the unit directions of array axes 0 (along rows), 1, 2 (normal)
    origin: np.ndarray  # (3,) mm: the centre of output voxel (0, 0, 0)
    spacing: np.ndarray  # (3,) mm
    shape: tuple[int, int, int]
    positions: list[list[int]]  # input slices at each distinct position along the normal, in order
    depths: np.ndarray  # (P,) mm along the normal of each distinct position, from output plane 0
    offsets: np.ndarray  # (N, 2) mm: each input slice's first pixel from the output origin, along axes 0 and 1
    steps: np.ndarray  # (P − 1,) mm between consecutive positions
    tilt_deg: float  # angle between the slice normal and the line through the slice origins
    gaps: list[tuple[float, float]] = field(default_factory=list)  # (from, to) mm along the normal

    @property
    def regular(self) -> bool:
        """Whether the output grid is the input's own: each output plane one input slice, copied."""
        planes = np.arange(self.shape[2]) * self.spacing[2]
        return (
            len(self.depths) == self.shape[2]
            and np.allclose(self.depths, planes, atol=SAME_POSITION_MM)
            and all(len(group) == 1 for group in self.positions)
            and np.allclose(self.offsets, self.offsets[0], atol=WHOLE_PIXEL_TOLERANCE * float(self.spacing[:2].min()))
        )

    def affine(self) -> np.ndarray:
        """Voxel index (i, j, k, 1) → scanner mm (LPS, like the input positions)."""
        affine = np.eye(4)
        affine[:3, :3] = self.axes * self.spacing
        affine[:3, 3] = self.origin
        return affine

    def describe(self) -> dict:
        """What was found, for the manifest."""
        return {
            "slices": int(sum(len(group) for group in self.positions)),
            "positions": len(self.positions),
            "step_mm": {
                "min": float(self.steps.min()),
                "max": float(self.steps.max()),
                "output": float(self.spacing[2]),
            },
            "tilt_deg": round(self.tilt_deg, 3),
            "gaps_mm": [[round(a, 3), round(b, 3)] for a, b in self.gaps],
            "shared_positions": int(sum(len(group) - 1 for group in self.positions)),
            "resampled": not self.regular,
        }


def stack_frame(slices: Sequence[PlacedSlice]) -> np.ndarray:
    """Orthonormal axes (3, 3) of the stack from its first slice: the row direction, the column
    direction made exactly perpendicular to it, and their cross product, the slice normal."""
    row = np.asarray(slices[0].row_direction, dtype=np.float64)
    row = row / np.linalg.norm(row)
    column = np.asarray(slices[0].column_direction, dtype=np.float64)
    column = column - (column @ row) * row
    column = column / np.linalg.norm(column)
    return np.stack([row, column, np.cross(row, column)], axis=1)


def output_step(steps: np.ndarray) -> float:
    """The step of the output grid: the steps' mean when they are all one step (so an ordinary
    series keeps its own slices), else their median, which a missing slice or a short second
    slab does not move."""
    mean = float(steps.mean())
    if np.max(np.abs(steps - mean)) <= REGULAR_STEP_TOLERANCE * mean + SAME_POSITION_MM:
        return mean
    return float(np.median(steps))


def tilt_angle_deg(positions: np.ndarray, normal: np.ndarray) -> float:
    """The angle between the slice normal and the line from the first slice origin to the last:
    0 for an ordinary series, the gantry tilt when the table moved along its own axis."""
    travel = positions[-1] - positions[0]
    length = float(np.linalg.norm(travel))
    if length <= SAME_POSITION_MM:
        return 0.0
    cosine = min(abs(float(travel @ normal)) / length, 1.0)
    return float(np.degrees(np.arccos(cosine)))


def plan_stack(slices: Sequence[PlacedSlice]) -> StackPlan:
    """The regular grid that holds every slice where it was acquired.

    Raises ValueError when the slices hold fewer than two distinct positions along their normal.
    """
    axes = stack_frame(slices)
    positions = np.array([s.position for s in slices], dtype=np.float64)
    coordinates = positions @ axes  # (N, 3): along rows, along columns, along the normal
    order = np.argsort(coordinates[:, 2], kind="stable")
    groups: list[list[int]] = []
    for index in order:
        if groups and coordinates[index, 2] - coordinates[groups[-1][0], 2] < SAME_POSITION_MM:
            groups[-1].append(int(index))
        else:
            groups.append([int(index)])
    if len(groups) < 2:
        raise ValueError("the slices lie at fewer than two distinct positions along their normal")
    depths = np.array([coordinates[group, 2].mean() for group in groups])
    steps = np.diff(depths)
    step = output_step(steps)
    count = int(np.floor((depths[-1] - depths[0]) / step + 1e-6)) + 1

    row_spacing = float(np.median([s.row_spacing for s in slices]))
    column_spacing = float(np.median([s.column_spacing for s in slices]))
    low = coordinates[:, :2].min(axis=0)
    high = np.max(coordinates[:, :2] + [[(s.columns - 1) * s.column_spacing, (s.rows - 1) * s.row_spacing]
                                        for s in slices], axis=0)  # fmt: skip
    in_plane = np.floor((high - low) / [column_spacing, row_spacing] + 1e-6).astype(int) + 1
    gaps = [(float(depths[k]), float(depths[k + 1])) for k in np.nonzero(steps > GAP_FACTOR * step)[0]]
    return StackPlan(
        axes=axes,
        origin=axes @ np.array([low[0], low[1], depths[0]]),
        spacing=np.array([column_spacing, row_spacing, step]),
        shape=(int(in_plane[0]), int(in_plane[1]), count),
        positions=groups,
        depths=depths - depths[0],
        offsets=coordinates[:, :2] - low,
        steps=steps,
        tilt_deg=tilt_angle_deg(positions[order], axes[:, 2]),
        gaps=gaps,
    )


def place_in_plane(
    image: np.ndarray, offset_mm: np.ndarray, spacing_mm: tuple[float, float], plan: StackPlan, fill: float
) -> np.ndarray:
    """One input image (columns, rows) sampled on the output grid's plane (shape[0], shape[1]):
    bilinear at each output pixel's position, ``fill`` outside the image. An image that lies on
    whole output pixels at the output's spacing is copied exactly."""
    from scipy import ndimage

    out_shape = plan.shape[:2]
    scale = plan.spacing[:2] / np.asarray(spacing_mm, dtype=np.float64)
    shift = np.asarray(offset_mm, dtype=np.float64) / plan.spacing[:2]  # where the image starts, in output pixels
    whole = np.round(shift)
    if np.allclose(scale, 1.0, atol=1e-9) and np.all(np.abs(shift - whole) < WHOLE_PIXEL_TOLERANCE):
        plane = np.full(out_shape, fill, dtype=np.float32)
        a, b = int(whole[0]), int(whole[1])
        width, height = min(image.shape[0], out_shape[0] - a), min(image.shape[1], out_shape[1] - b)
        plane[a : a + width, b : b + height] = image[:width, :height]
        return plane
    # input index = (output index − shift) × scale: what affine_transform maps output pixels through.
    return ndimage.affine_transform(
        image.astype(np.float32, copy=False), scale, offset=-shift * scale, output_shape=out_shape,
        order=1, mode="constant", cval=fill, output=np.float32,
    )  # fmt: skip


def resample_stack(
    image: Callable[[int], np.ndarray], slices: Sequence[PlacedSlice], plan: StackPlan, fill: float
) -> np.ndarray:
    """The stack on the plan's grid, (shape[0], shape[1], shape[2]) float32. ``image(i)`` gives
    input slice i as (columns, rows) physical values; each is read once. Slices at one position
    are averaged; an output plane between two positions blends them by distance."""
    volume = np.empty(plan.shape, dtype=np.float32)
    cache: dict[int, np.ndarray] = {}

    def position_plane(p: int) -> np.ndarray:
        if p not in cache:
            for passed in [q for q in cache if q < p - 1]:  # output planes move one way: p never comes back
                del cache[passed]
            planes = [place_in_plane(image(i), plan.offsets[i], (slices[i].column_spacing, slices[i].row_spacing),
                                     plan, fill) for i in plan.positions[p]]  # fmt: skip
            cache[p] = planes[0] if len(planes) == 1 else np.mean(planes, axis=0, dtype=np.float32)
        return cache[p]

    for k in range(plan.shape[2]):
        depth = k * plan.spacing[2]
        p = int(
            np.clip(np.searchsorted(plan.depths, depth + SAME_POSITION_MM, side="right") - 1, 0, len(plan.depths) - 2)
        )
        weight = (depth - plan.depths[p]) / max(plan.depths[p + 1] - plan.depths[p], SAME_POSITION_MM)
        if weight <= 1e-6:
            volume[:, :, k] = position_plane(p)
        elif weight >= 1.0 - 1e-6:
            volume[:, :, k] = position_plane(p + 1)
        else:
            volume[:, :, k] = (1.0 - weight) * position_plane(p) + weight * position_plane(p + 1)
    return volume
