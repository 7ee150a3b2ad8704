"""The splat stage: 3D Gaussian Splatting trained on an exported (or any COLMAP) scene."""

from cubecloud_cli.splat.gaussians import Gaussians, gaussians_from_points, random_points
from cubecloud_cli.splat.ply import read_gaussians_ply, write_gaussians_ply

__all__ = ["Gaussians", "gaussians_from_points", "random_points", "read_gaussians_ply", "write_gaussians_ply"]
