"""Cameras over the whole sphere of directions (docs/design.md §2): the scene is trained from every side it
will be seen from, not only from one ring.

``views`` directions on a spherical Fibonacci lattice (heights 1 − (2k+1)/N along the pole axis,
azimuths k × the golden angle): every direction gets an equal share of the sphere, no two are
close, and none sits exactly on a pole. Each camera looks at the origin from ``radius``. Image
"up" is the pole axis as the orbit has it (superior for ``si``), except within
:data:`POLE_CONE_DEG` of a pole, where that axis points almost at the camera and its projection
would spin with the azimuth; there "up" is the direction a radiologist expects on that view:
anterior when looking along the long axis (as an axial image), superior otherwise.
"""

from __future__ import annotations

import math

import numpy as np

from cubecloud_cli.cameras.orbit import ORBIT_AXES, OrbitSpec, look_at_rotation, spec_focal
from cubecloud_cli.cameras.pinhole import PinholeCameras

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))
# Within this angle of a pole the axis's projection is shorter than sin(20°) ≈ 0.34 of a unit
# vector: still defined, but a small change of direction would turn the image a lot.
POLE_CONE_DEG = 20.0
# Image "up" near a pole, per pole axis (RAS): anterior for views along the long axis, superior
# for views from the front, back or sides.
POLE_UP: dict[str, tuple[float, float, float]] = {
    "si": (0.0, 1.0, 0.0),
    "ap": (0.0, 0.0, 1.0),
    "lr": (0.0, 0.0, 1.0),
}


def fibonacci_directions(count: int, axis: np.ndarray, first: np.ndarray) -> np.ndarray:
    """(count, 3) unit vectors spread evenly over the sphere: from near +``axis`` (k = 0) to near
    −``axis``, azimuth measured from ``first`` counter-clockwise about ``axis``."""
    k = np.arange(count, dtype=np.float64)
    height = 1.0 - (2.0 * k + 1.0) / count
    ring = np.sqrt(np.clip(1.0 - height * height, 0.0, None))
    azimuth = k * GOLDEN_ANGLE
    second = np.cross(axis, first)
    return (
        (ring * np.cos(azimuth))[:, None] * first + (ring * np.sin(azimuth))[:, None] * second + height[:, None] * axis
    )


def image_up(direction: np.ndarray, axis: np.ndarray, pole_up: np.ndarray) -> np.ndarray:
    """The "up" hint of a camera at ``direction`` from the origin (see the module docstring)."""
    near_pole = abs(float(np.dot(direction, axis))) > math.cos(math.radians(POLE_CONE_DEG))
    return pole_up if near_pole else axis


def poses_looking_at_origin(
    directions: np.ndarray, radius: float, axis: np.ndarray, pole_up: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera rotations (N, 3, 3) and translations (N, 3) of cameras at ``radius`` along
    each unit direction, looking at the origin."""
    rotations, translations = [], []
    for direction in directions:
        centre = radius * direction
        rotation = look_at_rotation(centre, image_up(direction, axis, pole_up))
        rotations.append(rotation)
        translations.append(-rotation @ centre)
    return np.stack(rotations), np.stack(translations)


def sphere_cameras(spec: OrbitSpec) -> PinholeCameras:
    """``spec.views`` cameras over the sphere about ``spec.axis``, at ``spec.radius``, with
    ``spec.fov`` or the field of view that holds the whole cube in every one of them."""
    spec.validate()
    axis, first = (np.asarray(v, dtype=np.float64) for v in ORBIT_AXES[spec.axis])
    directions = fibonacci_directions(spec.views, axis, first)
    rotations, translations = poses_looking_at_origin(directions, spec.radius, axis, np.asarray(POLE_UP[spec.axis]))
    return PinholeCameras(
        rotations, translations, spec.resolution, spec.resolution, spec_focal(spec, rotations, translations)
    )
