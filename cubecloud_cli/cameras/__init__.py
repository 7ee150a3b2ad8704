"""Pinhole cameras in the OpenCV / COLMAP convention (docs/design.md §2): the sphere and the orbit that
`export` trains from, the single-pose slice stack of the paper's 3DGS baseline, and the novel
views that every scene is scored on."""

from cubecloud_cli.cameras.orbit import ORBIT_AXES, OrbitSpec, orbit_cameras
from cubecloud_cli.cameras.pinhole import PinholeCameras
from cubecloud_cli.cameras.sphere import sphere_cameras
from cubecloud_cli.cameras.stack import stack_cameras, stack_offsets

__all__ = [
    "ORBIT_AXES",
    "OrbitSpec",
    "PinholeCameras",
    "orbit_cameras",
    "sphere_cameras",
    "stack_cameras",
    "stack_offsets",
]
