"""What `splat` trains on: a COLMAP scene (ours from `export`, or any other) as tensors.

Images come from ``images.npy`` when the scene has it (our export's exact float renders) and
otherwise from the image files that ``images.txt`` names. The test split is ``split.json`` (ours),
else ``sparse/0/test.txt`` (recent 3DGS), else every 8th image by name (the reference rule).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.core.artifacts import read_manifest
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.scene import find_colmap_model, read_colmap_model, read_point_cloud_ply
from cubecloud_cli.transfer.function import TransferFunction
from cubecloud_cli.transfer.training_set import member_views

HOLDOUT_EVERY = 8
TRANSFER_IMAGES = "transfer_images.npy"  # our export's training views under each transfer function
# Cameras within this fraction of their distance from the origin (or 1e-9 world units) of their
# mean count as one place: poses written once and read back differ by rounding.
SAME_CENTRE = 1e-6


@dataclass
class TrainingScene:
    directory: Path
    cameras: PinholeCameras
    names: list[str]
    images: torch.Tensor  # (V, H, W, C) float32 in [0, 1]
    train: list[int]
    test: list[int]
    points: tuple[np.ndarray, np.ndarray] | None  # xyz (P, 3), colours (P, 3) in [0, 1]
    # The scan value at each point (our export's float intensity), which seeds a scalar scene.
    point_values: np.ndarray | None = None
    # The transfer functions the images were rendered under (our dvr export's); none for a
    # scene that does not say. With more than one, transfer_images holds the views under each
    # (K, V // S, H, W, C): member k at views member_views(k, S, V), the first's being ``images``'.
    transfers: list[TransferFunction] = field(default_factory=list)
    transfer_images: torch.Tensor | None = None
    transfer_stride: int = 1

    def transfer_pairs(self) -> list[tuple[int, int]]:
        """(member, view) of every training image rendered under a member of the set other than the first."""
        views = len(self.names)
        train = set(self.train)
        return [
            (member, view)
            for member in range(1, len(self.transfers))
            for view in member_views(member, self.transfer_stride, views)
            if view in train
        ]

    def _centre_spread(self) -> tuple[float, float]:
        """The largest distance of a training camera from their mean, and that mean's distance
        from the world origin."""
        centres = self.cameras.centres()[self.train]
        mean = centres.mean(axis=0)
        return float(np.linalg.norm(centres - mean, axis=1).max()), float(np.linalg.norm(mean))

    @property
    def single_centre(self) -> bool:
        return _one_place(*self._centre_spread())

    @property
    def extent(self) -> float:
        """1.1 × the largest distance of a training camera from their mean (the reference's
        scene extent, which scales learning rates and size thresholds).

        Cameras that share one centre (the paper's baseline) would give the reference an extent
        of 0, which freezes every mean; they get 1.1 × their distance from the world origin
        instead, what an orbit about the origin at that distance would give.
        """
        spread, distance = self._centre_spread()
        return 1.1 * (distance if _one_place(spread, distance) else spread)


def _one_place(spread: float, distance: float) -> bool:
    return not spread > max(1e-9, SAME_CENTRE * distance)


def _read_image(path: Path, channels: int, width: int, height: int) -> np.ndarray:
    import imageio.v3 as iio

    try:
        pixels = np.asarray(iio.imread(path))
    except Exception as exc:  # missing or unreadable
        raise CubecloudError(
            f"cannot read {path} ({type(exc).__name__}): the scene's images/ must hold every image images.txt names"
        ) from None
    if pixels.shape[:2] != (height, width):
        raise CubecloudError(
            f"{path} is {pixels.shape[1]}x{pixels.shape[0]} but its camera is {width}x{height}: undistort or resize the scene consistently"
        )
    if pixels.dtype == np.bool_:
        pixels = pixels.astype(np.float32)
    elif np.issubdtype(pixels.dtype, np.integer):
        pixels = pixels.astype(np.float32) / float(np.iinfo(pixels.dtype).max)  # each depth's own range
    elif np.issubdtype(pixels.dtype, np.floating):
        pixels = pixels.astype(np.float32)  # float images are taken as [0, 1] already
    else:
        raise CubecloudError(
            f"{path} has pixels of type {pixels.dtype}: convert the scene's images to 8- or 16-bit PNG"
        )
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    if pixels.ndim != 3 or pixels.shape[2] not in (1, 2, 3, 4):
        raise CubecloudError(
            f"{path} has an image shape {pixels.shape} that is neither grey nor RGB: convert it to PNG"
        )
    colour = pixels[..., :1] if pixels.shape[2] <= 2 else pixels[..., :3]  # drop alpha (LA, RGBA)
    if channels == 1:
        return colour.mean(axis=2, keepdims=True)
    return colour if colour.shape[2] == 3 else np.repeat(colour, 3, axis=2)


def _split(directory: Path, names: list[str]) -> list[int]:
    split_file = directory / "split.json"
    if split_file.is_file():
        try:
            test = set(json.loads(split_file.read_text()).get("test", []))
        except (ValueError, AttributeError, TypeError):
            raise CubecloudError(
                f'{split_file} is not a split ({{"test": [image names]}}): re-export the scene, or delete it to hold out every 8th image'
            ) from None
    elif (find_colmap_model(directory) / "test.txt").is_file():
        test = set((find_colmap_model(directory) / "test.txt").read_text().split())
    else:
        test = {name for index, name in enumerate(names) if index % HOLDOUT_EVERY == 0}
    return [index for index, name in enumerate(names) if name in test]


def _transfers(directory: Path) -> list[TransferFunction]:
    """The transfer functions of our dvr export's training images, from its manifest (its
    "transfers", else its image model's); none for other scenes."""
    try:
        manifest = json.loads((directory / "manifest.json").read_text())
        model = manifest.get("image_model", {})
    except (OSError, ValueError, AttributeError):
        return []
    if not isinstance(model, dict) or model.get("kind") != "dvr":
        return []
    listed = manifest.get("transfers") or [model.get("transfer")]
    try:
        functions = [TransferFunction.from_dict(t) for t in listed]
        for function in functions:
            function.validate()
    except (KeyError, TypeError, ValueError):
        raise CubecloudError(
            f"{directory / 'manifest.json'} records a transfer function that is not one ({listed}): re-export the scene"
        ) from None
    return functions


def _transfer_stride(directory: Path, views: int) -> int:
    """The export's --transfer-stride (1 for exports made before it)."""
    stride = json.loads((directory / "manifest.json").read_text()).get("transfer_stride", 1)
    if not isinstance(stride, int) or not 1 <= stride <= views:
        raise CubecloudError(
            f"{directory / 'manifest.json'} records a transfer stride {stride!r} outside 1..{views}: re-export the scene"
        )
    return stride


def _transfer_images(
    directory: Path, transfers: int, views: int, height: int, width: int, stride: int
) -> torch.Tensor | None:
    path = directory / TRANSFER_IMAGES
    if transfers < 2:
        return None
    if not path.is_file():
        raise CubecloudError(
            f"{directory} lists {transfers} transfer functions but has no {TRANSFER_IMAGES}: re-export the scene"
        )
    stack = np.load(path, mmap_mode="r")
    if stack.shape != (transfers, views // stride, height, width):
        raise CubecloudError(
            f"{path} holds {stack.shape} but the scene has {transfers} transfer functions of {views // stride} views "
            f"of {width}x{height}: re-export the scene"
        )
    images = np.array(stack, dtype=np.float32)[..., None]
    if not np.isfinite(images).all():
        raise CubecloudError(f"{path} holds NaN or Inf values: re-export the scene")
    return torch.from_numpy(images)


def export_remake(directory: Path) -> str | None:
    """The command that writes ``directory`` again when it is an export of ours, else None (a
    foreign scene, fixed with COLMAP's tools)."""
    directory = Path(directory)
    try:
        manifest = read_manifest(directory)
    except CubecloudError:
        return None
    if manifest.get("stage") != "export":
        return None
    name = manifest.get("name")
    return f"cubecloud export {directory.parent}{f' --name {name}' if name else ''} --force"


def load_scene(directory: Path, channels: int = 1, every_transfer: bool = False) -> TrainingScene:
    """The scene's cameras, images and points; ``every_transfer`` loads its views under every
    transfer function too (a scalar run trains on them)."""
    directory = Path(directory)
    model = read_colmap_model(directory, export_remake(directory))
    cameras, names = model.cameras, model.image_names
    height, width = cameras.height, cameras.width
    stack = directory / "images.npy"
    if stack.is_file():
        images = np.load(stack, mmap_mode="r")
        if images.shape[:3] != (len(names), height, width):
            raise CubecloudError(
                f"{stack} holds {images.shape} but the cameras say {len(names)} views of {width}x{height}: re-export the scene"
            )
        images = np.array(images, dtype=np.float32)  # a writable copy of the memory map
        images = images[..., None] if images.ndim == 3 else images
        images = (
            images
            if images.shape[3] == channels
            else (images.mean(axis=3, keepdims=True) if channels == 1 else np.repeat(images, 3, axis=3))
        )
    else:
        images = np.stack([_read_image(directory / "images" / name, channels, width, height) for name in names])
    if not np.isfinite(images).all():
        raise CubecloudError(f"the images of {directory} hold NaN or Inf values: re-export the scene")
    test = _split(directory, names)
    train = [index for index in range(len(names)) if index not in set(test)]
    if not train:
        raise CubecloudError(f"{directory} leaves no image for training after the test split")
    points, point_values = None, None
    for candidate in (directory / "points3D.ply", find_colmap_model(directory) / "points3D.ply"):
        if candidate.is_file():
            xyz, rgb, extras = read_point_cloud_ply(candidate)
            points = (xyz, rgb.astype(np.float32) / 255.0)
            point_values = extras.get("intensity")
            break
    if points is None and len(model.xyz):
        points = (model.xyz, model.rgb.astype(np.float32) / 255.0)
    if points is not None and not np.isfinite(points[0]).all():
        raise CubecloudError(
            f"the point cloud of {directory} holds NaN or Inf coordinates: fix it, or use --init random"
        )
    transfers = _transfers(directory)
    scene = TrainingScene(
        directory,
        cameras,
        names,
        torch.from_numpy(np.array(images, dtype=np.float32)),
        train,
        test,
        points,
        point_values,
        transfers,
    )
    if every_transfer and len(transfers) > 1:
        scene.transfer_stride = _transfer_stride(directory, len(names))
        scene.transfer_images = _transfer_images(
            directory, len(transfers), len(names), height, width, scene.transfer_stride
        )
    if not scene.extent > 1e-9:
        raise CubecloudError(
            f"the training cameras of {directory} sit together at the world origin, so the scene has no extent: 3DGS needs views from different places"
        )
    return scene
