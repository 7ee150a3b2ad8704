"""COLMAP sparse models: write ours for 3DGS/nerfstudio/gsplat, read foreign ones for `splat --scene`.

We write one shared PINHOLE camera (id 1), images 1..N with world-to-camera poses, and the
points with empty tracks, in both the binary and the text layout: COLMAP and pycolmap prefer
.bin, while the reference 3DGS falls back to .txt and its text reader insists on PINHOLE
(3dgs.md §1.7, §5). Reading accepts only what a pinhole renderer with a centred principal
point and one focal length can reproduce exactly; anything else is refused with its fix.
"""

from __future__ import annotations

import struct
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cubecloud_cli.cameras.pinhole import PinholeCameras
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.scene import colmap_parse as parse
from cubecloud_cli.scene.quaternions import quaternion_to_rotation, rotation_to_quaternion

CAMERA_ID = 1
PINHOLE_MODEL_ID = 1
# Largest pixel error we accept from forcing a foreign camera into our model: a principal point
# off the image centre, or fx ≠ fy replaced by their mean (measured at the image border).
PIXEL_TOLERANCE = 0.5
# Where a scene root keeps its model: 3DGS/COLMAP layout, then nerfstudio's ns-process-data.
MODEL_SUBDIRECTORIES = (".", "sparse/0", "sparse", "colmap/sparse/0")
TEXT_CHUNK = 100_000  # points formatted per string operation: bounds the memory of the .txt writer


@dataclass(frozen=True)
class ColmapModel:
    cameras: PinholeCameras  # sorted by image name, like image_names
    image_names: list[str]
    xyz: np.ndarray  # (P, 3) float64
    rgb: np.ndarray  # (P, 3) uint8


# ----------------------------------------------------------------------------------------- writing


def _checked_names(names: Sequence[str], count: int) -> list[str]:
    names = [str(name) for name in names]
    if len(names) != count:
        raise ValueError(f"{len(names)} image names for {count} cameras")
    if len(set(names)) != len(names):
        raise ValueError("image names must be unique")
    for name in names:
        # The text format splits on white space and the binary one ends names at NUL.
        if not name or any(c.isspace() or c == "\0" for c in name):
            raise ValueError(f"image name {name!r} is empty or contains white space")
    return names


def _checked_points(xyz: np.ndarray, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    xyz, rgb = np.asarray(xyz, dtype=np.float64), np.asarray(rgb)
    if xyz.size == 0 and rgb.size == 0:  # "no points" may arrive as any empty shape
        xyz, rgb = xyz.reshape(0, 3), rgb.reshape(0, 3)
    if xyz.ndim != 2 or xyz.shape[1] != 3 or rgb.shape != xyz.shape:
        raise ValueError(f"xyz and rgb must both be (P, 3), got {xyz.shape} and {rgb.shape}")
    if not np.all(np.isfinite(xyz)):
        raise ValueError("xyz holds NaN or infinite coordinates")
    if rgb.dtype != np.uint8:
        if rgb.size and (not np.issubdtype(rgb.dtype, np.integer) or rgb.min() < 0 or rgb.max() > 255):
            raise ValueError("rgb must be uint8 (or integers within 0..255)")
        rgb = rgb.astype(np.uint8)
    return xyz, rgb


def _pose_vectors(cameras: PinholeCameras) -> tuple[np.ndarray, np.ndarray]:
    return rotation_to_quaternion(cameras.rotations).reshape(-1, 4), np.asarray(cameras.translations, np.float64)


def _pinhole_params(cameras: PinholeCameras) -> tuple[float, float, float, float]:
    return float(cameras.focal), float(cameras.focal), float(cameras.cx), float(cameras.cy)


def _write_text(directory: Path, cameras: PinholeCameras, names: list[str], xyz: np.ndarray, rgb: np.ndarray) -> None:
    # repr() is the shortest decimal that reads back to the same float64.
    params = " ".join(repr(value) for value in _pinhole_params(cameras))
    (directory / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        "# Number of cameras: 1\n"
        f"{CAMERA_ID} PINHOLE {cameras.width} {cameras.height} {params}\n",
        encoding="utf-8",
    )
    qvecs, tvecs = _pose_vectors(cameras)
    lines = [
        "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
        f"# Number of images: {len(names)}, mean observations per image: 0\n"
    ]
    for image_id, (q, t, name) in enumerate(zip(qvecs.tolist(), tvecs.tolist(), names), 1):
        # The empty second line is the (absent) POINTS2D list; readers consume it unconditionally.
        lines.append(f"{image_id} {' '.join(map(repr, q))} {' '.join(map(repr, t))} {CAMERA_ID} {name}\n\n")
    (directory / "images.txt").write_text("".join(lines), encoding="utf-8")

    with open(directory / "points3D.txt", "w", encoding="utf-8") as stream:
        stream.write(
            "# 3D point list with one line of data per point:\n"
            "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
            f"# Number of points: {len(xyz)}, mean track length: 0\n"
        )
        # %.17g round-trips float64 like repr() and formats a third faster, which counts at 10⁶ points.
        row = "%d %.17g %.17g %.17g %d %d %d 0.0\n"
        for start in range(0, len(xyz), TEXT_CHUNK):
            stop = min(start + TEXT_CHUNK, len(xyz))
            table = np.empty((stop - start, 7))  # ids and colours are exact in float64; %d prints them
            table[:, 0] = np.arange(start + 1, stop + 1)
            table[:, 1:4] = xyz[start:stop]
            table[:, 4:7] = rgb[start:stop]
            # One % over a repeated row format: C-speed formatting, no per-point Python call.
            stream.write((row * (stop - start)) % tuple(table.ravel().tolist()))


def _write_binary(directory: Path, cameras: PinholeCameras, names: list[str], xyz: np.ndarray, rgb: np.ndarray) -> None:
    (directory / "cameras.bin").write_bytes(
        parse.U64.pack(1)
        + parse.CAMERA_HEAD.pack(CAMERA_ID, PINHOLE_MODEL_ID, cameras.width, cameras.height)
        + struct.pack("<4d", *_pinhole_params(cameras))
    )
    qvecs, tvecs = _pose_vectors(cameras)
    chunks = [parse.U64.pack(len(names))]
    for image_id, (q, t, name) in enumerate(zip(qvecs.tolist(), tvecs.tolist(), names), 1):
        chunks.append(parse.IMAGE_HEAD.pack(image_id, *q, *t, CAMERA_ID))
        chunks.append(name.encode("utf-8") + b"\0" + parse.U64.pack(0))  # no 2D points
    (directory / "images.bin").write_bytes(b"".join(chunks))

    records = np.zeros(len(xyz), dtype=parse.POINT_RECORD)  # error 0, empty tracks
    records["id"] = np.arange(1, len(xyz) + 1)
    records["xyz"] = xyz
    records["rgb"] = rgb
    with open(directory / "points3D.bin", "wb") as stream:
        stream.write(parse.U64.pack(len(xyz)))
        stream.write(records.tobytes())


def write_colmap_model(
    directory: Path,
    cameras: PinholeCameras,
    image_names: Sequence[str],
    xyz: np.ndarray,
    rgb: np.ndarray,
    *,
    text: bool = True,
    binary: bool = True,
) -> None:
    """Write cameras/images/points3D (.txt and/or .bin) for ``cameras`` into ``directory``.

    Image ``i`` (id i+1) is ``image_names[i]``, relative to the scene's image folder. Points get
    ids 1..P, reprojection error 0 and empty tracks: they seed Gaussians, not bundle adjustment.
    """
    names = _checked_names(image_names, len(cameras))
    xyz, rgb = _checked_points(xyz, rgb)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if text:
        _write_text(directory, cameras, names, xyz, rgb)
    if binary:
        _write_binary(directory, cameras, names, xyz, rgb)


def write_test_list(directory: Path, names: Sequence[str]) -> Path:
    """Write ``test.txt`` (one image name per line), the held-out views recent upstream 3DGS reads
    from ``sparse/0/test.txt`` with ``--eval``; names are full image names, extension included."""
    path = Path(directory) / "test.txt"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{name}\n" for name in names), encoding="utf-8")
    return path


# ----------------------------------------------------------------------------------------- reading


def find_colmap_model(directory: Path) -> Path:
    """The folder holding the model: ``directory`` itself or its ``sparse/0`` (3DGS), ``sparse``
    or ``colmap/sparse/0`` (nerfstudio), whichever first has cameras and images files."""
    directory = Path(directory)
    if not directory.is_dir():
        raise parse.ColmapError(
            f"COLMAP scene {directory} does not exist or is not a folder", "pass the scene folder or its sparse/0"
        )
    for sub in MODEL_SUBDIRECTORIES:
        candidate = directory / sub
        for ext in (".bin", ".txt"):
            if (candidate / f"cameras{ext}").is_file() and (candidate / f"images{ext}").is_file():
                return candidate.resolve()
    raise parse.ColmapError(
        f"no COLMAP model in {directory} (cameras.bin + images.bin, or .txt, there or in sparse/0)",
        "run COLMAP (or `colmap model_converter`) to produce one",
    )


def _shared_intrinsics(path: Path, cameras: list[parse.CameraRecord]) -> tuple[int, int, float]:
    """Width, height and focal common to ``cameras``, or CubecloudError saying why there is none."""
    width, height = cameras[0].width, cameras[0].height
    focals = []
    for camera in cameras:
        if (camera.width, camera.height) != (width, height):
            raise parse.ColmapError(
                f"{path}: cameras {cameras[0].camera_id} and {camera.camera_id} have different image sizes "
                f"({width}x{height}, {camera.width}x{camera.height})",
                "resize all images to one size first",
            )
        if camera.width < 1 or camera.height < 1:
            raise parse.corrupt(path, f"camera {camera.camera_id} has size {camera.width}x{camera.height}")
        fx, fy, cx, cy = camera.params if camera.model == "PINHOLE" else (camera.params[0], *camera.params)
        if not all(np.isfinite((fx, fy, cx, cy))) or fx <= 0 or fy <= 0:
            raise parse.corrupt(path, f"camera {camera.camera_id} has parameters {list(camera.params)}")
        if abs(cx - width / 2) > PIXEL_TOLERANCE or abs(cy - height / 2) > PIXEL_TOLERANCE:
            raise parse.ColmapError(
                f"{path}: camera {camera.camera_id} has its principal point at ({cx:g}, {cy:g}), not the image "
                f"centre ({width / 2:g}, {height / 2:g})",
                f"{parse.UNDISTORT_HINT} and a centred principal point",
            )
        focals.append((fx, fy))
    focals = np.asarray(focals)
    focal = float(focals.mean())
    # Border displacement from using one focal for both axes of every camera.
    error = np.max(np.abs(focals - focal) / focals * (np.array([width, height]) / 2))
    if error > PIXEL_TOLERANCE:
        raise parse.ColmapError(
            f"{path}: the cameras' focal lengths differ (fx, fy from {focals.min():g} to {focals.max():g} px, "
            f"{error:.2f} px apart at the border) where cubecloud needs one square-pixel focal length",
            "undistort to a shared PINHOLE camera (`colmap image_undistorter`) or resample the images",
        )
    return width, height, focal


def _read_records(model: Path) -> tuple[list[parse.CameraRecord], list[parse.ImageRecord], Path, Path]:
    """Cameras and images from the binary pair when both exist (COLMAP's preference), else the text pair."""
    binary = (model / "cameras.bin").is_file() and (model / "images.bin").is_file()
    camera_path, image_path = (model / f"{stem}.{'bin' if binary else 'txt'}" for stem in ("cameras", "images"))
    if binary:
        return parse.read_cameras_binary(camera_path), parse.read_images_binary(image_path), camera_path, image_path
    return parse.read_cameras_text(camera_path), parse.read_images_text(image_path), camera_path, image_path


def _read_points(model: Path) -> tuple[np.ndarray, np.ndarray]:
    # Points only seed Gaussians: a model without them still trains (from a random init).
    if (model / "points3D.bin").is_file():
        return parse.read_points_binary(model / "points3D.bin")
    if (model / "points3D.txt").is_file():
        return parse.read_points_text(model / "points3D.txt")
    return np.zeros((0, 3)), np.zeros((0, 3), np.uint8)


def read_colmap_model(directory: Path, remake: str | None = None) -> ColmapModel:
    """Read a COLMAP model (binary preferred, as COLMAP does) into cameras sorted by image name.

    ``directory`` may be the model folder or a scene root (see ``find_colmap_model``). Only
    PINHOLE / SIMPLE_PINHOLE cameras with a centred principal point and one shared focal length
    are accepted; anything else, or a damaged file, raises CubecloudError with the fix: COLMAP's
    tools for a foreign model, ``remake`` (the command that writes it again) for one of ours.
    """
    try:
        return _read_model(directory)
    except parse.ColmapError as error:
        if remake is None:
            raise
        raise CubecloudError(f"{error.problem}: run `{remake}`") from None


def _read_model(directory: Path) -> ColmapModel:
    model = find_colmap_model(directory)
    cameras, images, camera_path, image_path = _read_records(model)
    if not images:
        raise parse.ColmapError(f"{image_path} lists no images (the reconstruction registered none)", "re-run COLMAP")
    by_id = {camera.camera_id: camera for camera in cameras}
    missing = sorted({image.camera_id for image in images} - by_id.keys())
    if missing:
        raise parse.corrupt(image_path, f"images refer to camera ids {missing} absent from {camera_path.name}")
    used = [by_id[camera_id] for camera_id in sorted({image.camera_id for image in images})]
    width, height, focal = _shared_intrinsics(camera_path, used)

    images = sorted(images, key=lambda image: image.name)
    names = [image.name for image in images]
    repeated = [name for name, count in Counter(names).items() if count > 1]
    if repeated:
        raise parse.corrupt(image_path, f"image name {repeated[0]!r} appears more than once")
    qvecs = np.array([image.qvec for image in images], dtype=np.float64)
    tvecs = np.array([image.tvec for image in images], dtype=np.float64)
    norms = np.linalg.norm(qvecs, axis=1)
    bad = ~np.isfinite(norms) | (norms < 1e-12) | ~np.all(np.isfinite(tvecs), axis=1)
    if np.any(bad):
        raise parse.corrupt(image_path, f"image {names[int(np.argmax(bad))]!r} has a zero or non-finite pose")
    rotations = quaternion_to_rotation(qvecs)
    xyz, rgb = _read_points(model)
    return ColmapModel(PinholeCameras(rotations, tvecs, width, height, focal), names, xyz, rgb)
