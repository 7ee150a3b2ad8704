"""cubecloud: turn a CT scan into a 3D Gaussian Splatting scene (Cube-Cloud 3DGS)."""

__version__ = "0.1.0"
