"""Low-level parsing of COLMAP model files (cameras, images, points3D; .bin and .txt) into plain records.

Only the byte/line layouts live here (COLMAP ``doc/format.rst``; 3dgs.md §1.7, §5); whether the
records make a scene cubecloud can train on is decided in ``colmap.py``. Every malformed input
raises CubecloudError naming the file, so a foreign scene never fails with a bare struct error.
"""

from __future__ import annotations

import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cubecloud_cli.core.errors import CubecloudError

# COLMAP's camera model ids (src/colmap/sensor/models.h), for names in messages and the text format.
CAMERA_MODEL_NAMES: dict[int, str] = {
    0: "SIMPLE_PINHOLE", 1: "PINHOLE", 2: "SIMPLE_RADIAL", 3: "RADIAL", 4: "OPENCV", 5: "OPENCV_FISHEYE",
    6: "FULL_OPENCV", 7: "FOV", 8: "SIMPLE_RADIAL_FISHEYE", 9: "RADIAL_FISHEYE", 10: "THIN_PRISM_FISHEYE",
    11: "RAD_TAN_THIN_PRISM_FISHEYE", 12: "SIMPLE_DIVISION", 13: "DIVISION", 14: "SIMPLE_FISHEYE",
    15: "FISHEYE", 16: "EUCM", 17: "EQUIRECTANGULAR",
}  # fmt: skip
# Parameter counts of the undistorted models, the only ones a pinhole renderer can use.
PINHOLE_PARAM_COUNTS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4}
UNDISTORT_HINT = "undistort the scene first: `colmap image_undistorter` writes PINHOLE cameras"

# points3D.bin: id, xyz, rgb, error, then the track length (3dgs.md §1.7 `QdddBBBd` + `Q`).
POINT_RECORD = np.dtype(
    [("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8"), ("track_length", "<u8")]
)
POINT_HEAD = struct.Struct("<QdddBBBdQ")  # the same record, for the per-point path
IMAGE_HEAD = struct.Struct("<idddddddi")  # id, qw qx qy qz, tx ty tz, camera_id
CAMERA_HEAD = struct.Struct("<iiQQ")  # id, model_id, width, height
U64 = struct.Struct("<Q")
POINT2D_BYTES = 24  # x, y as doubles and a u64 point3D id


@dataclass(frozen=True)
class CameraRecord:
    camera_id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass(frozen=True)
class ImageRecord:
    image_id: int
    qvec: tuple[float, float, float, float]  # w, x, y, z, world -> camera
    tvec: tuple[float, float, float]
    camera_id: int
    name: str


class ColmapError(CubecloudError):
    """A COLMAP model that cannot be read: what is wrong (``problem``) apart from the fix, which
    depends on who made the model (COLMAP's tools, or `cubecloud export` for our own)."""

    def __init__(self, problem: str, fix: str):
        super().__init__(f"{problem}: {fix}")
        self.problem = problem


def corrupt(path: Path, detail: str) -> ColmapError:
    return ColmapError(
        f"{path} is not a readable COLMAP file ({detail})", "re-export the model with `colmap model_converter`"
    )


def unsupported_model(path: Path, camera_id: int, model: str) -> ColmapError:
    return ColmapError(f"{path}: camera {camera_id} uses the {model} model, which has lens distortion", UNDISTORT_HINT)


class _Cursor:
    """Reads little-endian records from a bytes buffer, turning a short read into a CubecloudError."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.data = path.read_bytes()
        self.pos = 0

    def take(self, layout: struct.Struct) -> tuple:
        if self.pos + layout.size > len(self.data):
            raise corrupt(self.path, f"truncated at byte {self.pos} of {len(self.data)}")
        values = layout.unpack_from(self.data, self.pos)
        self.pos += layout.size
        return values

    def skip(self, count: int) -> None:
        if count < 0 or self.pos + count > len(self.data):
            raise corrupt(self.path, f"truncated at byte {self.pos} of {len(self.data)}")
        self.pos += count

    def count(self, what: str, min_record: int) -> int:
        (n,) = self.take(U64)
        # A garbage count would otherwise send us into a very long loop before the short read.
        if n * min_record > len(self.data) - self.pos:
            raise corrupt(self.path, f"truncated: claims {n} {what} but holds only {len(self.data)} bytes")
        return n

    def string(self) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise corrupt(self.path, f"unterminated image name at byte {self.pos}")
        raw = self.data[self.pos : end]
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise corrupt(self.path, f"image name at byte {self.pos} is not UTF-8") from None

    def finish(self) -> None:
        if self.pos != len(self.data):
            raise corrupt(self.path, f"{len(self.data) - self.pos} unexpected bytes after the last record")


def read_cameras_binary(path: Path) -> list[CameraRecord]:
    cursor = _Cursor(path)
    cameras = []
    for _ in range(cursor.count("cameras", CAMERA_HEAD.size)):
        camera_id, model_id, width, height = cursor.take(CAMERA_HEAD)
        model = CAMERA_MODEL_NAMES.get(model_id, f"unknown (id {model_id})")
        if model not in PINHOLE_PARAM_COUNTS:
            # The parameter count of other models is not needed: we could not use them anyway.
            raise unsupported_model(path, camera_id, model)
        params = cursor.take(struct.Struct(f"<{PINHOLE_PARAM_COUNTS[model]}d"))
        cameras.append(CameraRecord(camera_id, model, width, height, tuple(params)))
    cursor.finish()
    return cameras


def read_images_binary(path: Path) -> list[ImageRecord]:
    cursor = _Cursor(path)
    images = []
    for _ in range(cursor.count("images", IMAGE_HEAD.size + 1 + U64.size)):
        image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = cursor.take(IMAGE_HEAD)
        name = cursor.string()
        (n_points2d,) = cursor.take(U64)
        cursor.skip(n_points2d * POINT2D_BYTES)
        images.append(ImageRecord(image_id, (qw, qx, qy, qz), (tx, ty, tz), camera_id, name))
    cursor.finish()
    return images


def read_points_binary(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """xyz (P, 3) float64 and rgb (P, 3) uint8; tracks are skipped."""
    cursor = _Cursor(path)
    count = cursor.count("points", POINT_RECORD.itemsize)
    body = len(cursor.data) - cursor.pos
    if body == count * POINT_RECORD.itemsize:
        # Every track might be empty (as in the files we write): then the records are fixed-size.
        records = np.frombuffer(cursor.data, POINT_RECORD, count, cursor.pos)
        if not np.any(records["track_length"]):
            return records["xyz"].astype(np.float64), records["rgb"].copy()
    xyz = np.empty((count, 3))
    rgb = np.empty((count, 3), np.uint8)
    for i in range(count):
        _, x, y, z, r, g, b, _, track_length = cursor.take(POINT_HEAD)
        xyz[i] = x, y, z
        rgb[i] = r, g, b
        cursor.skip(track_length * 8)  # (image_id, point2D_idx) as two i32
    cursor.finish()
    return xyz, rgb


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """(1-based line number, stripped text) of every line, comments and blanks included."""
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise corrupt(path, "not UTF-8 text") from None
    return [(number, line.strip()) for number, line in enumerate(text.splitlines(), 1)]


def _is_data(line: str) -> bool:
    return bool(line) and not line.startswith("#")


def read_cameras_text(path: Path) -> list[CameraRecord]:
    cameras = []
    for number, line in _data_lines(path):
        if not _is_data(line):
            continue
        fields = line.split()
        try:
            camera_id, model, width, height = int(fields[0]), fields[1], int(fields[2]), int(fields[3])
            params = tuple(float(value) for value in fields[4:])
        except (IndexError, ValueError):
            raise corrupt(path, f"line {number} is not `CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]`") from None
        if model not in PINHOLE_PARAM_COUNTS:
            raise unsupported_model(path, camera_id, model)
        if len(params) != PINHOLE_PARAM_COUNTS[model]:
            expected = PINHOLE_PARAM_COUNTS[model]
            raise corrupt(path, f"line {number}: {model} takes {expected} parameters, not {len(params)}")
        cameras.append(CameraRecord(camera_id, model, width, height, params))
    return cameras


def read_images_text(path: Path) -> list[ImageRecord]:
    lines = _data_lines(path)
    images = []
    index = 0
    while index < len(lines):
        number, line = lines[index]
        index += 1
        if not _is_data(line):
            continue
        # As COLMAP does: the line right after an image line holds its POINTS2D, even when blank.
        index += 1
        fields = line.split(maxsplit=9)
        try:
            image_id, camera_id, name = int(fields[0]), int(fields[8]), fields[9]
            values = [float(value) for value in fields[1:8]]
        except (IndexError, ValueError):
            raise corrupt(path, f"line {number} is not `IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`") from None
        images.append(ImageRecord(image_id, tuple(values[:4]), tuple(values[4:]), camera_id, name))
    return images


def read_points_text(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """xyz (P, 3) float64 and rgb (P, 3) uint8 from the first 8 columns; tracks are ignored."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": a point-less model
            # numpy's C parser: ~10× a Python line loop, and it tolerates ragged track columns.
            table = np.loadtxt(path, comments="#", usecols=range(8), ndmin=2, encoding="utf-8")
    except (ValueError, UnicodeDecodeError) as error:
        raise corrupt(path, f"not `POINT3D_ID X Y Z R G B ERROR TRACK[]` rows: {error}") from None
    colours = table[:, 4:7]
    if colours.size and (colours.min() < 0 or colours.max() > 255 or np.any(colours != np.round(colours))):
        raise corrupt(path, "a colour is not an integer within 0..255")
    return table[:, 1:4].copy(), colours.astype(np.uint8)
