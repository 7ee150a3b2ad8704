"""Pinhole cameras in the OpenCV / COLMAP convention (DESIGN §2) and the orbit that `export` uses."""

from cubecloud_cli.cameras.orbit import ORBIT_AXES, OrbitSpec, orbit_cameras
from cubecloud_cli.cameras.pinhole import PinholeCameras

__all__ = ["ORBIT_AXES", "OrbitSpec", "PinholeCameras", "orbit_cameras"]
