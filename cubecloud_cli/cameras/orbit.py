"""The orbit of views that `export` renders (docs/design.md §2).

``views`` cameras evenly spaced over 360° about a volume axis, at ``radius`` world units from the
origin (the volume fills [−1, 1]³), all looking at the origin with image "up" along the orbit
axis, optionally raised by ``elevation`` degrees out of the orbit plane. The first camera looks
at the patient as a radiologist would: from the front for ``si`` (patient's left on the image
right), from the feet for ``ap`` (the axial viewing convention), from the front for ``lr``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cubecloud_cli.cameras.pinhole import PinholeCameras
from cubecloud_cli.core.errors import CubecloudError

# Orbit axis and the direction of the first camera from the origin, in RAS world coordinates.
ORBIT_AXES: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "si": ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),  # about the long axis, head up, first view anterior
    "ap": ((0.0, 1.0, 0.0), (0.0, 0.0, -1.0)),  # the paper's: about the sagittal axis, first view from the feet
    "lr": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),  # about the left-right axis, first view anterior
}
# The cube's bounding sphere: a camera inside it would sit in or too near the volume.
CUBE_RADIUS = math.sqrt(3.0)
MAX_ELEVATION_DEG = 85.0  # at 90° the orbit collapses onto the axis and "up" is undefined
FOV_MARGIN = 1.02  # the cube's silhouette plus 2%, so its corners are not cut at the border
# Far beyond this the volume shrinks below float32 resolution in the rays (they are float32).
MAX_RADIUS = 1e4


@dataclass(frozen=True)
class OrbitSpec:
    views: int = 60
    axis: str = "si"
    radius: float = 4.0
    resolution: int = 256
    elevation: float = 0.0  # degrees
    fov: float | None = None  # degrees; None fits the whole cube in every view

    def validate(self) -> None:
        if self.views < 2:
            raise CubecloudError(f"--views {self.views}: an orbit needs at least 2 views (the paper uses 60)")
        if self.axis not in ORBIT_AXES:
            raise CubecloudError(f"--axis {self.axis!r} must be one of {', '.join(ORBIT_AXES)}")
        if math.isfinite(self.radius) and self.radius > MAX_RADIUS:
            raise CubecloudError(
                f"--radius {self.radius:g} is beyond {MAX_RADIUS:g} world units: use e.g. 4 (a narrow --fov zooms)"
            )
        if not math.isfinite(self.radius) or self.radius <= CUBE_RADIUS * 1.01:
            raise CubecloudError(
                f"--radius {self.radius:g} puts the cameras inside the volume (it fills [-1, 1]^3, "
                f"corners at {CUBE_RADIUS:.3f} from the centre): use a radius of at least 1.75, e.g. 4"
            )
        if self.resolution < 1:
            raise CubecloudError(f"--resolution {self.resolution} must be a positive number of pixels, e.g. 256")
        if not math.isfinite(self.elevation) or abs(self.elevation) > MAX_ELEVATION_DEG:
            raise CubecloudError(f"--elevation {self.elevation:g} must be within ±{MAX_ELEVATION_DEG:g} degrees")
        if self.fov is not None and not (math.isfinite(self.fov) and 1.0 <= self.fov <= 170.0):
            raise CubecloudError(f"--fov {self.fov:g} must be between 1 and 170 degrees (or left out to fit the cube)")


def look_at_rotation(centre: np.ndarray, up: np.ndarray) -> np.ndarray:
    """World-to-camera rotation of a camera at ``centre`` looking at the origin, image up ≈ ``up``."""
    forward = -centre / np.linalg.norm(centre)
    down = -(up - np.dot(up, forward) * forward)
    norm = np.linalg.norm(down)
    if norm < 1e-9:
        raise ValueError("the view direction is parallel to the up vector")
    down /= norm
    right = np.cross(down, forward)  # x = y × z in a right-handed camera frame
    return np.stack((right, down, forward))


def orbit_poses(spec: OrbitSpec) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera rotations (N, 3, 3) and translations (N, 3) of the orbit."""
    axis, first = (np.asarray(v) for v in ORBIT_AXES[spec.axis])
    second = np.cross(axis, first)  # right-handed: angles grow counter-clockwise about the axis
    elevation = math.radians(spec.elevation)
    rotations, translations = [], []
    for k in range(spec.views):
        theta = 2.0 * math.pi * k / spec.views
        direction = math.cos(elevation) * (math.cos(theta) * first + math.sin(theta) * second)
        centre = spec.radius * (direction + math.sin(elevation) * axis)
        rotation = look_at_rotation(centre, axis)
        rotations.append(rotation)
        translations.append(-rotation @ centre)
    return np.stack(rotations), np.stack(translations)


def fitting_focal(rotations: np.ndarray, translations: np.ndarray, resolution: int) -> float:
    """The focal length (pixels) at which every corner of [−1, 1]³ falls inside every view."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    camera = np.einsum("nij,cj->nci", rotations, corners) + translations[:, None, :]
    # Cameras are outside the bounding sphere, so every corner has depth ≥ radius − √3 > 0.
    tangent = np.max(np.abs(camera[..., :2]) / camera[..., 2:3])
    return resolution / (2.0 * tangent * FOV_MARGIN)


def spec_focal(spec: OrbitSpec, rotations: np.ndarray, translations: np.ndarray) -> float:
    """The focal length (pixels) of ``spec.fov``, or the one that fits the cube in every pose."""
    if spec.fov is None:
        return fitting_focal(rotations, translations, spec.resolution)
    return spec.resolution / (2.0 * math.tan(math.radians(spec.fov) / 2.0))


def orbit_cameras(spec: OrbitSpec) -> PinholeCameras:
    spec.validate()
    rotations, translations = orbit_poses(spec)
    return PinholeCameras(
        rotations, translations, spec.resolution, spec.resolution, spec_focal(spec, rotations, translations)
    )
