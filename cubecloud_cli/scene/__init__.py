"""Interop with the 3DGS ecosystem: COLMAP sparse models, point-cloud PLY, nerfstudio transforms.json."""

from cubecloud_cli.scene.colmap import (
    ColmapModel,
    find_colmap_model,
    read_colmap_model,
    write_colmap_model,
    write_test_list,
)
from cubecloud_cli.scene.point_ply import read_point_cloud_ply, write_point_cloud_ply
from cubecloud_cli.scene.quaternions import quaternion_to_rotation, rotation_to_quaternion
from cubecloud_cli.scene.transforms import opengl_camera_to_world, transforms_json, write_json

__all__ = [
    "ColmapModel",
    "find_colmap_model",
    "opengl_camera_to_world",
    "quaternion_to_rotation",
    "read_colmap_model",
    "read_point_cloud_ply",
    "rotation_to_quaternion",
    "transforms_json",
    "write_colmap_model",
    "write_json",
    "write_point_cloud_ply",
    "write_test_list",
]
