"""The paper's own 3DGS baseline: a stack of parallel slices, every one seen from one camera pose.

The paper trained its 3DGS baseline on "2D images in the direction of a sagittal plane" with "the
identical camera pose in direction of z axis" for every image. ``stack`` reproduces that: ``views``
slices perpendicular to ``axis``, at the centres of ``views`` equal slabs across the cube, all
seen by one camera on that axis. No 3D scene can show different images from one pose, which is
the point of the baseline; it is an experiment, not a way to train a useful scene.
"""

from __future__ import annotations

import numpy as np

from cubecloud_cli.cameras.orbit import OrbitSpec, look_at_rotation, spec_focal
from cubecloud_cli.cameras.pinhole import PinholeCameras

# Where the one camera sits (a unit direction from the origin) and its image "up", per slice
# normal, in RAS world coordinates (+x is the patient's right): sagittal slices seen from the
# patient's left (anterior on the image left), coronal from the front and axial from the feet
# (the patient's right on the image left), as radiology displays them.
STACK_VIEWS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "lr": ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "ap": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "si": ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
}


def stack_offsets(views: int) -> np.ndarray:
    """Signed distances of the slice planes from the origin along the camera's optical axis: the
    centres of ``views`` equal slabs across [−1, 1], nearest the camera first."""
    return -1.0 + (2.0 * np.arange(views) + 1.0) / views


def stack_cameras(spec: OrbitSpec) -> PinholeCameras:
    """``spec.views`` copies of one camera on ``spec.axis`` at ``spec.radius`` from the origin."""
    spec.validate()
    direction, up = (np.asarray(v) for v in STACK_VIEWS[spec.axis])
    centre = spec.radius * direction
    rotation = look_at_rotation(centre, up)
    rotations = np.repeat(rotation[None], spec.views, axis=0)
    translations = np.repeat((-rotation @ centre)[None], spec.views, axis=0)
    focal = spec_focal(spec, rotations[:1], translations[:1])
    return PinholeCameras(rotations, translations, spec.resolution, spec.resolution, float(focal))
