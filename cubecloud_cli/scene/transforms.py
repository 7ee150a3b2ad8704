"""nerfstudio / instant-ngp ``transforms.json`` for our cameras (3dgs.md §6).

Intrinsics at the top level (one shared camera), one frame per image with its camera-to-world
matrix in the OpenGL/Blender convention these tools use (x right, y up, z backward): our
OpenCV camera-to-world with its y and z columns negated. ``applied_transform`` is the identity
because our world frame is used as is; nerfstudio would otherwise undo it on the point cloud.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cubecloud_cli.cameras.pinhole import PinholeCameras

# OpenCV (y down, z forward) → OpenGL (y up, z back) camera axes, applied on the right of c2w.
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_camera_to_world(cameras: PinholeCameras) -> np.ndarray:
    """(N, 4, 4) camera-to-world matrices with OpenGL camera axes."""
    return cameras.camera_to_world() @ OPENCV_TO_OPENGL


def _checked_split(name: str, paths: Sequence[str] | None, known: set[str]) -> list[str] | None:
    if paths is None:
        return None
    paths = [str(path) for path in paths]
    unknown = [path for path in paths if path not in known]
    if unknown:
        # nerfstudio refuses a split naming a file that is not a frame.
        raise ValueError(f"{name} lists {unknown[0]!r}, which is not one of the frames' file paths")
    return paths


def transforms_json(
    cameras: PinholeCameras,
    file_paths: Sequence[str],
    *,
    train_file_paths: Sequence[str] | None = None,
    test_file_paths: Sequence[str] | None = None,
    ply_file_path: str | None = None,
) -> dict[str, Any]:
    """The transforms.json content for ``cameras``, frame ``i`` showing image ``file_paths[i]``.

    Paths are relative to the folder holding transforms.json. With a split given, we write
    ``train_filenames``, ``val_filenames`` and ``test_filenames`` (val = test): once any of
    them is present nerfstudio requires the list for every split it loads, and its trainer
    evaluates on "val". Without one, nerfstudio chooses its own split.
    """
    paths = [str(path) for path in file_paths]
    if len(paths) != len(cameras):
        raise ValueError(f"{len(paths)} file paths for {len(cameras)} cameras")
    if len(set(paths)) != len(paths):
        raise ValueError("file paths must be unique")
    train = _checked_split("train_file_paths", train_file_paths, set(paths))
    test = _checked_split("test_file_paths", test_file_paths, set(paths))
    # A lone list would leave nerfstudio without the other and stop it: the rest of the frames fill it.
    if train is not None and test is None:
        test = [path for path in paths if path not in set(train)]
    elif test is not None and train is None:
        train = [path for path in paths if path not in set(test)]

    focal = float(cameras.focal)
    content: dict[str, Any] = {
        "camera_model": "PINHOLE",
        "fl_x": focal,
        "fl_y": focal,
        "cx": float(cameras.cx),
        "cy": float(cameras.cy),
        "w": int(cameras.width),
        "h": int(cameras.height),
        # instant-ngp and the NeRF-synthetic readers derive the focal from these field-of-view angles.
        "camera_angle_x": cameras.fov_x,
        "camera_angle_y": cameras.fov_y,
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "frames": [
            # colmap_im_id matches the image ids of write_colmap_model (1..N in the same order).
            {"file_path": path, "transform_matrix": matrix.tolist(), "colmap_im_id": index}
            for index, (path, matrix) in enumerate(zip(paths, opengl_camera_to_world(cameras)), 1)
        ],
        "applied_transform": np.eye(4)[:3].tolist(),
    }
    if train is not None and test is not None:
        content["train_filenames"] = train
        content["val_filenames"] = list(test)
        content["test_filenames"] = list(test)
    if ply_file_path is not None:
        content["ply_file_path"] = str(ply_file_path)
    return content


def write_json(path: Path, content: Any) -> Path:
    """Write ``content`` as indented UTF-8 JSON with a final newline; creates the parent folder."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(content, indent=2) + "\n", encoding="utf-8")
    return path
