"""A set of pinhole cameras sharing one image size and focal length.

Convention (docs/design.md §2, the one COLMAP, OpenCV and the reference 3DGS code use): camera x right,
y down, z forward; poses are world-to-camera, ``X_cam = R @ X_world + t``; pixel (u, v) covers
[u, u+1) × [v, v+1) with its centre at (u + 0.5, v + 0.5); the principal point is the image centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Depths at or below this are behind (or on) the camera plane: their projection is undefined.
MIN_DEPTH = 1e-6


@dataclass(frozen=True)
class PinholeCameras:
    rotations: np.ndarray  # (N, 3, 3) world -> camera, float64
    translations: np.ndarray  # (N, 3)
    width: int
    height: int
    focal: float  # fx = fy, in pixels

    def __post_init__(self) -> None:
        if self.rotations.ndim != 3 or self.rotations.shape[1:] != (3, 3):
            raise ValueError(f"rotations must be (N, 3, 3), got {self.rotations.shape}")
        if self.translations.shape != (len(self.rotations), 3):
            raise ValueError(f"translations must be ({len(self.rotations)}, 3), got {self.translations.shape}")
        if self.width < 1 or self.height < 1 or not np.isfinite(self.focal) or self.focal <= 0:
            raise ValueError(f"bad intrinsics: {self.width}x{self.height}, focal {self.focal}")

    def __len__(self) -> int:
        return len(self.rotations)

    @property
    def cx(self) -> float:
        return self.width / 2.0

    @property
    def cy(self) -> float:
        return self.height / 2.0

    @property
    def fov_x(self) -> float:
        """Horizontal field of view in radians (the 3DGS ``focal2fov``)."""
        return 2.0 * float(np.arctan(self.width / (2.0 * self.focal)))

    @property
    def fov_y(self) -> float:
        return 2.0 * float(np.arctan(self.height / (2.0 * self.focal)))

    def intrinsics(self) -> np.ndarray:
        """The 3×3 calibration matrix K."""
        return np.array([[self.focal, 0.0, self.cx], [0.0, self.focal, self.cy], [0.0, 0.0, 1.0]])

    def centres(self) -> np.ndarray:
        """Camera centres in world coordinates, −Rᵀt, (N, 3)."""
        return -np.einsum("nji,nj->ni", self.rotations, self.translations)

    def world_to_camera(self) -> np.ndarray:
        """(N, 4, 4) homogeneous world-to-camera matrices."""
        matrices = np.tile(np.eye(4), (len(self), 1, 1))
        matrices[:, :3, :3] = self.rotations
        matrices[:, :3, 3] = self.translations
        return matrices

    def camera_to_world(self) -> np.ndarray:
        """(N, 4, 4) camera-to-world matrices (OpenCV axes)."""
        matrices = np.tile(np.eye(4), (len(self), 1, 1))
        matrices[:, :3, :3] = np.transpose(self.rotations, (0, 2, 1))
        matrices[:, :3, 3] = self.centres()
        return matrices

    def project(self, index: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (P, 2) of world points in view ``index`` and their depths (P,).

        Coordinates are continuous: the pixel that holds (u, v) is (floor(u), floor(v)). Points
        at depth ≤ MIN_DEPTH (behind the camera) get NaN coordinates instead of a division by
        a tiny or negative depth.
        """
        camera_points = np.asarray(points, dtype=np.float64) @ self.rotations[index].T + self.translations[index]
        depth = camera_points[:, 2]
        in_front = depth > MIN_DEPTH
        safe = np.where(in_front, depth, 1.0)
        pixels = np.stack(
            (self.focal * camera_points[:, 0] / safe + self.cx, self.focal * camera_points[:, 1] / safe + self.cy),
            axis=1,
        )
        pixels[~in_front] = np.nan
        return pixels, depth

    def pixel_directions(self, index: int, subpixel: tuple[float, float] = (0.5, 0.5)) -> np.ndarray:
        """Unit world-space directions through the same point of every pixel, (H·W, 3), row-major
        (v, u): its centre by default, (u + subpixel[0], v + subpixel[1]) in general."""
        u = (np.arange(self.width) + subpixel[0] - self.cx) / self.focal
        v = (np.arange(self.height) + subpixel[1] - self.cy) / self.focal
        uu, vv = np.meshgrid(u, v, indexing="xy")
        camera_dirs = np.stack((uu, vv, np.ones_like(uu)), axis=-1).reshape(-1, 3)
        camera_dirs /= np.linalg.norm(camera_dirs, axis=1, keepdims=True)  # ≥ 1 by construction
        return camera_dirs @ self.rotations[index]  # Rᵀ d, row-wise

    def subset(self, indices) -> "PinholeCameras":
        indices = np.asarray(indices, dtype=int)
        return PinholeCameras(self.rotations[indices], self.translations[indices], self.width, self.height, self.focal)
