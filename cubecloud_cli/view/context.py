"""What the viewer shows around the Gaussians, read from the work directory: the preprocessed
volume (for the slice planes), the Cube-Cloud points and the export's cameras with their images.

Each is optional: a work directory whose export was made elsewhere, or whose files are damaged,
still shows its Gaussians, and the viewer says in one line which layer it left out and why.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.core.artifacts import require_stage
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.pictures import to_uint8
from cubecloud_cli.scene import read_colmap_model
from cubecloud_cli.scene.point_ply import read_point_cloud_ply

log = logging.getLogger("cubecloud")

# The frustums carry their image as a thumbnail: a few hundred full-size textures would slow
# the page for a picture a few centimetres wide on screen.
THUMBNAIL_SIDE = 128


@dataclass
class SceneContext:
    volume: np.ndarray | None = None  # (S, S, S) in [0, 1], RAS array axes
    points: np.ndarray | None = None  # (P, 3) world units
    point_colours: np.ndarray | None = None  # (P, 3) uint8
    cameras: PinholeCameras | None = None
    thumbnails: np.ndarray | None = None  # (N, h, w) uint8, the training images, one per camera
    left_out: list[str] = field(default_factory=list)  # one line per layer that could not be read


def read_volume(work: Path) -> np.ndarray:
    require_stage(work, "preprocess")
    path = Path(work) / "preprocess" / "volume.npy"
    try:
        volume = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise CubecloudError(
            f"{path} is unreadable ({exc}): run `cubecloud preprocess SCAN -o {work} --force`"
        ) from None
    if volume.ndim != 3 or len(set(volume.shape)) != 1:
        raise CubecloudError(f"{path} is not a cube volume (shape {volume.shape}): rerun preprocess with --force")
    return volume.astype(np.float32, copy=False)


def read_export_points(work: Path) -> tuple[np.ndarray, np.ndarray]:
    require_stage(work, "export")
    xyz, rgb, _ = read_point_cloud_ply(Path(work) / "export" / "points3D.ply")
    return xyz.astype(np.float32), rgb


def thumbnails(images: np.ndarray, side: int = THUMBNAIL_SIDE) -> np.ndarray:
    """(N, H, W) images in [0, 1] as uint8, subsampled by a whole stride so the longer side is ≤ ``side``."""
    stride = max(1, -(-max(images.shape[1:]) // max(side, 1)))
    return to_uint8(images[:, ::stride, ::stride])


def read_export_cameras(work: Path) -> tuple[PinholeCameras, np.ndarray]:
    require_stage(work, "export")
    export = Path(work) / "export"
    model = read_colmap_model(export, f"cubecloud export {work} --force")
    path = export / "images.npy"
    try:
        images = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise CubecloudError(f"{path} is unreadable ({exc}): run `cubecloud export {work} --force`") from None
    # The export names its views view_000, view_001, … in index order, which is the model's name order.
    if images.ndim != 3 or len(images) != len(model.cameras):
        raise CubecloudError(
            f"{path} holds {images.shape} images for {len(model.cameras)} cameras: run `cubecloud export {work} --force`"
        )
    return model.cameras, thumbnails(np.asarray(images))


def load_context(work: Path) -> SceneContext:
    """Every layer that can be read; each one that cannot is noted in ``left_out``."""
    left_out: list[str] = []

    def attempt(layer: str, read: Callable[[], Any]) -> Any:
        try:
            return read()
        except CubecloudError as exc:
            left_out.append(f"{layer} left out: {exc}")
            return None

    volume = attempt("scan slices", lambda: read_volume(work))
    points = attempt("Cube-Cloud points", lambda: read_export_points(work)) or (None, None)
    cameras = attempt("cameras", lambda: read_export_cameras(work)) or (None, None)
    return SceneContext(volume, *points, *cameras, left_out=left_out)
