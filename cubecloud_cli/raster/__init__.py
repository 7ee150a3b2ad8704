"""Gaussian splatting rasterization, a functional API kept apart from training (gsplat-style):
project 3D Gaussians into a view, then composite them front to back. ``backends.rasterizer_for``
picks the implementation for a device (numba kernels on the CPU, gsplat on CUDA when installed,
plain PyTorch otherwise)."""

from cubecloud_cli.raster.backends import Rasterized, Rasterizer, rasterizer_for
from cubecloud_cli.raster.pairs import composite, splat_pairs
from cubecloud_cli.raster.projection import Projected, covariances, project, quaternion_to_rotation

__all__ = [
    "Projected",
    "Rasterized",
    "Rasterizer",
    "composite",
    "covariances",
    "project",
    "quaternion_to_rotation",
    "rasterizer_for",
    "splat_pairs",
]
