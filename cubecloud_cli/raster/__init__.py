"""Gaussian splatting rasterization, a functional API kept apart from training (gsplat-style):
project 3D Gaussians into a view, then composite them front to back."""

from cubecloud_cli.raster.pairs import composite, splat_pairs
from cubecloud_cli.raster.projection import Projected, covariances, project, quaternion_to_rotation

__all__ = ["Projected", "composite", "covariances", "project", "quaternion_to_rotation", "splat_pairs"]
