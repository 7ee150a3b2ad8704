"""Where the viewer's context layers sit in the world: the volume's slices as textured planes and
the export's cameras as frustums, placed exactly where the voxels and views are (docs/design.md §2).

The viewer draws an image on a plane in its local x–y frame, column u along +x and row v along
+y, with the plane's centre at the local origin (the OpenCV image convention, as viser does). A
slice is drawn with its columns along its first free RAS axis and its rows along its second, so
pixel (v, u) lands on the centre of the voxel it came from.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.scene.quaternions import rotation_to_quaternion
from cubecloud_cli.view.splats import CLIP_AXES

# The two RAS axes a slice spans, (columns, rows), ordered so that columns × rows points along
# the fixed axis (sagittal: y × z = +x, axial: x × y = +z) or against it (coronal: x × z = −y);
# either way the frame is a rotation, which is all the viewer needs.
SLICE_FREE_AXES: dict[str, tuple[int, int]] = {"sagittal": (1, 2), "coronal": (0, 2), "axial": (0, 1)}


def voxel_centre(index: int, size: int) -> float:
    """World coordinate of voxel ``index``'s centre on a cube of ``size`` voxels in [−1, 1]."""
    return (2.0 * index + 1.0) / size - 1.0


def slice_index(volume_size: int, position: float) -> int:
    """The voxel index whose centre is nearest the world coordinate ``position``, clamped to the
    volume (±inf to its ends, NaN to its middle)."""
    if np.isnan(position):
        return volume_size // 2
    inside = min(max(float(position), -1.0), 1.0)  # before scaling, so a huge one cannot overflow
    return min(max(int(np.floor((inside + 1.0) * volume_size / 2.0)), 0), volume_size - 1)


def slice_image(volume: np.ndarray, axis: str, index: int, opacity: float = 1.0) -> np.ndarray:
    """Slice ``index`` across ``axis`` of a [0, 1] volume as an (rows, columns, 4) uint8 RGBA grey
    image, rows along the second free axis and columns along the first (SLICE_FREE_AXES). Values
    outside [0, 1] (and NaN) are clamped, so a stray voxel cannot wrap around in 8 bits."""
    plane = np.take(volume, index, axis=CLIP_AXES[axis])  # (first free, second free)
    grey = np.round(np.clip(np.nan_to_num(plane.T, nan=0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
    opacity = float(np.clip(np.nan_to_num(opacity, nan=0.0), 0.0, 1.0))
    alpha = np.full_like(grey, int(round(opacity * 255.0)))
    return np.stack([grey, grey, grey, alpha], axis=-1)


def slice_rotation(axis: str) -> np.ndarray:
    """The plane's local-to-world rotation: local x along the columns' axis, local y along the rows'."""
    columns, rows = SLICE_FREE_AXES[axis]
    rotation = np.zeros((3, 3))
    rotation[columns, 0] = 1.0
    rotation[rows, 1] = 1.0
    rotation[:, 2] = np.cross(rotation[:, 0], rotation[:, 1])
    return rotation


def slice_pose(axis: str, index: int, volume_size: int) -> tuple[np.ndarray, np.ndarray]:
    """The plane of slice ``index`` across ``axis``: its quaternion (w, x, y, z) and its centre in
    world units. The plane is 2 world units on a side, so its S pixels fall on the S voxel centres."""
    position = np.zeros(3)
    position[CLIP_AXES[axis]] = voxel_centre(index, volume_size)
    return rotation_to_quaternion(slice_rotation(axis)), position


def slice_pixel_world(axis: str, index: int, volume_size: int, row: int, column: int) -> np.ndarray:
    """The world position where the viewer draws the centre of pixel (row, column) of a slice: the
    plane's rotation applied to the pixel's offset from the plane's centre (what viser does)."""
    _, centre = slice_pose(axis, index, volume_size)
    local = np.array([voxel_centre(column, volume_size), voxel_centre(row, volume_size), 0.0])
    return slice_rotation(axis) @ local + centre


def camera_poses(cameras: PinholeCameras) -> tuple[np.ndarray, np.ndarray]:
    """Each camera's camera-to-world rotation as a quaternion (w, x, y, z) and its centre, in the
    OpenCV frame the viewer's frustums use (x right, y down, z forward), like our cameras."""
    camera_to_world = cameras.camera_to_world()
    return rotation_to_quaternion(camera_to_world[:, :3, :3]), camera_to_world[:, :3, 3]


SLICE_AXES = ("axial", "coronal", "sagittal")


class SliceLayer:
    """The three slice planes' state: which voxel each shows, whether it is shown, and one opacity."""

    def __init__(self, volume: np.ndarray | None, opacity: float = 1.0):
        self.volume = volume
        self.size = 0 if volume is None else volume.shape[0]
        self.index = {axis: self.size // 2 for axis in SLICE_AXES}
        self.visible = {axis: False for axis in SLICE_AXES}
        self.opacity = opacity

    def update(self, axis: str, index: int | None = None, visible: bool | None = None) -> bool:
        """Move and/or toggle one plane (the index clamped to the volume); whether anything changed."""
        if axis not in SLICE_AXES:
            raise ValueError(f"slice axis {axis!r} must be one of {', '.join(SLICE_AXES)}")
        wanted = (
            self.index[axis] if index is None else min(max(int(index), 0), self.size - 1),
            self.visible[axis] if visible is None else bool(visible),
        )
        if wanted == (self.index[axis], self.visible[axis]):
            return False
        self.index[axis], self.visible[axis] = wanted
        return True

    def plane(self, axis: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The plane's RGBA image, quaternion and centre (world units)."""
        assert self.volume is not None, "no volume to slice"
        wxyz, position = slice_pose(axis, self.index[axis], self.size)
        return slice_image(self.volume, axis, self.index[axis], self.opacity), wxyz, position


@dataclass(frozen=True)
class ViewPose:
    """Where a viewer camera stands and looks, in world units; ``fov`` vertical, in radians."""

    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    fov: float | None = None

    def scaled(self, scale: float) -> "ViewPose":
        return ViewPose(self.position * scale, self.look_at * scale, self.up, self.fov)


def camera_view(cameras: PinholeCameras, index: int) -> ViewPose:
    """The pose of camera ``index`` as a viewer camera: its centre, a point straight ahead as far
    away as the origin (which our cameras look at, so turning the view orbits the volume), its
    image's up (−y in OpenCV) and its vertical field of view."""
    camera_to_world = cameras.camera_to_world()[index]
    centre, down, forward = camera_to_world[:3, 3], camera_to_world[:3, 1], camera_to_world[:3, 2]
    distance = float(np.linalg.norm(centre))
    return ViewPose(centre, centre + forward * distance, -down, cameras.fov_y)


# In front of the patient, head up: the view when there is no export to follow.
ANTERIOR_VIEW = ViewPose(np.array([0.0, 4.0, 0.0]), np.zeros(3), np.array([0.0, 0.0, 1.0]))
