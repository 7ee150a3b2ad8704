"""The splat stage: 3D Gaussian Splatting trained on an exported (or any COLMAP) scene."""

from cubecloud_cli.core.lazy import lazy_exports

_EXPORTS = {
    "Gaussians": "gaussians",
    "gaussians_from_points": "gaussians",
    "random_points": "gaussians",
    "read_gaussians_ply": "gaussian_ply",
    "write_gaussians_ply": "gaussian_ply",
}
__getattr__ = lazy_exports(__name__, _EXPORTS)

__all__ = ["Gaussians", "gaussians_from_points", "random_points", "read_gaussians_ply", "write_gaussians_ply"]
