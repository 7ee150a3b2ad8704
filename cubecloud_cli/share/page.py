"""The shared page: one HTML file that holds the viewer (Spark on three.js, vendored), our page
script, the scene as base64 SPZ and what the page needs to know of it, so that it opens from a
double click with no server and no network.

What the page is told (``page_info``): the camera to open on (the export's first view, in
three.js terms), the patient's directions at the cube's ends, the world → scanner millimetres map
for the ruler and the cut's readout, how to blur splats as they were trained (Mip-Splatting's
opacity-compensated 2D filter or plain 3DGS's dilation), and the log-scale range Spark should
spend its 8 bits on. Nothing else of the work directory, and nothing of the scan's header, goes
into the page: not its file name, not a DICOM field.
"""

from __future__ import annotations

import base64
import gzip
import json
import math
import re
from dataclasses import dataclass
from importlib import resources

import numpy as np

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.raster.constants import DILATION, MIP_FILTER_VARIANCE
from cubecloud_cli.transfer.function import TransferFunction
from cubecloud_cli.view.transfer_view import COLOUR_MAPS, MAX_OPACITY_SCALE, DrawnValues

# RAS scanner axes: the letter at the negative and the positive end of each.
PATIENT_DIRECTIONS = (("L", "R"), ("P", "A"), ("I", "S"))
# The anatomical plane across each scanner axis (RAS component → plane name).
PLANE_ACROSS = {0: "sagittal", 1: "coronal", 2: "axial"}
LOG_SCALE_MARGIN = 0.5  # of the range Spark quantizes log scales over, beyond the scene's own


@dataclass(frozen=True)
class PageCamera:
    position: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_y_degrees: float


def page_camera(cameras: PinholeCameras, index: int = 0) -> PageCamera:
    """Camera ``index`` (OpenCV: x right, y down, z forward; world → camera) as three.js places a
    camera: its centre, the point it looks at nearest the world's origin (what the orbit turns
    about), its up (−y) and its vertical field of view."""
    rotation = np.asarray(cameras.rotations[index], dtype=np.float64)
    centre = -rotation.T @ np.asarray(cameras.translations[index], dtype=np.float64)
    forward, up = rotation[2], -rotation[1]
    distance = max(float(-centre @ forward), 1e-6)
    target = centre + distance * forward
    fov = math.degrees(2.0 * math.atan(cameras.height / (2.0 * cameras.focal)))
    return PageCamera(tuple(centre), tuple(target), tuple(up), fov)


def patient_axes(world_to_scanner: np.ndarray | None) -> tuple[list[list[str]], list[int]]:
    """For each world axis, the patient's direction letters at its (negative, positive) end, and
    the scanner component it runs along most. Without a scanner frame the world axes are named
    −x/+x and so on."""
    if world_to_scanner is None:
        return [[f"-{a}", f"+{a}"] for a in "xyz"], [0, 1, 2]
    linear = np.asarray(world_to_scanner, dtype=np.float64)[:3, :3]
    labels, components = [], []
    for axis in range(3):
        column = linear[:, axis]
        component = int(np.argmax(np.abs(column)))
        negative, positive = PATIENT_DIRECTIONS[component]
        labels.append([negative, positive] if column[component] >= 0 else [positive, negative])
        components.append(component)
    return labels, components


def page_info(
    camera: PageCamera, world_to_scanner: np.ndarray | None, antialiased: bool, log_scales: np.ndarray
) -> dict:
    """Everything the page script reads about the scene (see the module docstring)."""
    labels, components = patient_axes(world_to_scanner)
    finite = log_scales[np.isfinite(log_scales)]
    low, high = (float(finite.min()), float(finite.max())) if finite.size else (-12.0, 9.0)
    return {
        "camera": {
            "position": list(camera.position),
            "target": list(camera.target),
            "up": list(camera.up),
            "fovY": camera.fov_y_degrees,
        },
        "axes": labels,
        "scannerComponent": components,
        "cutAxes": {PLANE_ACROSS[component]: axis for axis, component in enumerate(components)},
        "worldToScanner": None if world_to_scanner is None else np.asarray(world_to_scanner, float).tolist(),
        "antialiased": antialiased,
        "blur": {"mip": MIP_FILTER_VARIANCE if antialiased else 0.0, "dilation": 0.0 if antialiased else DILATION},
        "encoding": {"lnScaleMin": low - LOG_SCALE_MARGIN, "lnScaleMax": high + LOG_SCALE_MARGIN},
    }


LOG_LENGTH_STEP = 1.0 / 2048  # int16 steps of log ℓ: ℓ to 0.05 %, over ±16 (ℓ is clamped to ±10)


def scalar_block(drawn: DrawnValues) -> bytes:
    """A scalar scene's per-Gaussian values for the page to recolour under any transfer function,
    gzip-compressed: the value (uint16 over [0, 1]), log ℓ (int16 in 1/2048 steps) and the 3D
    filter's factor (uint16 over [0, 1]), each array whole, little-endian, in the SPZ's order."""
    values = np.rint(np.clip(np.nan_to_num(drawn.values), 0.0, 1.0) * 65535).astype("<u2")
    log_lengths = np.log(np.clip(np.nan_to_num(drawn.lengths, nan=1.0), np.exp(-10.0), np.exp(10.0)))
    steps = np.rint(log_lengths / LOG_LENGTH_STEP).astype("<i2")
    attenuation = np.rint(np.clip(np.nan_to_num(drawn.attenuation), 0.0, 1.0) * 65535).astype("<u2")
    return gzip.compress(values.tobytes() + steps.tobytes() + attenuation.tobytes(), compresslevel=9, mtime=0)


def read_scalar_block(data: bytes) -> DrawnValues:
    """What :func:`scalar_block` wrote, as the page reads it."""
    raw = gzip.decompress(data)
    count = len(raw) // 6
    values = np.frombuffer(raw, "<u2", count, 0).astype(np.float32) / 65535
    lengths = np.exp(np.frombuffer(raw, "<i2", count, 2 * count).astype(np.float64) * LOG_LENGTH_STEP)
    attenuation = np.frombuffer(raw, "<u2", count, 4 * count).astype(np.float32) / 65535
    return DrawnValues(values, lengths.astype(np.float32), attenuation)


def scalar_info(
    presets: dict[str, TransferFunction], hu_window: tuple[float, float] | None, chord_lengths: bool = False
) -> dict:
    """The transfer-function presets (the first as trained) and colour maps the page offers, the
    HU at intensity 0 and 1 for a CT (the window sliders read in HU), else None, and whether ℓ is
    scaled by each Gaussian's chord along the ray (the page then recolours when its camera rests)."""
    return {
        "chordLengths": bool(chord_lengths),
        "huWindow": None if hu_window is None else [float(hu_window[0]), float(hu_window[1])],
        "presets": {name: function.as_dict() for name, function in presets.items()},
        "colourMaps": {name: [list(c) for c in anchors] for name, anchors in COLOUR_MAPS.items()},
        "maxOpacityScale": MAX_OPACITY_SCALE,
    }


def _asset(name: str) -> str:
    return resources.files("cubecloud_cli.share").joinpath("page", name).read_text(encoding="utf-8")


def vendor_script() -> str:
    """The vendored viewer bundle with its licences in a comment ahead of it, as MIT asks."""
    notices = "\n".join(
        _asset(f"vendor/LICENSE-{name}.txt").replace("*/", "* /") for name in ("three", "spark", "fflate")
    )
    versions = _asset("vendor/versions.txt").strip().replace("\n", ", ")
    return f"/*! {versions}\n{notices}*/\n{_asset('vendor/spark-three.min.js')}"


def _safe_in_script(text: str, what: str) -> str:
    """``text`` as it may stand inside a <script> element: no "</script" ends the element early."""
    if "</script" in text.lower():
        raise ValueError(f"the {what} holds '</script': it cannot be inlined into the page")
    return text


def render_page(spz: bytes, info: dict, scalar: bytes | None = None) -> str:
    """The whole index.html; ``scalar``, a :func:`scalar_block`, makes it a scalar scene's page."""
    info_json = json.dumps(info, separators=(",", ":")).replace("</", "<\\/")
    parts = {
        "/*SCENE_INFO*/": info_json,
        "/*SCENE_SPZ*/": base64.b64encode(spz).decode("ascii"),
        "/*SCENE_SCALAR*/": base64.b64encode(scalar or b"").decode("ascii"),
        "/*VENDOR*/": _safe_in_script(vendor_script(), "vendored viewer"),
        "/*VIEWER*/": _safe_in_script(_asset("viewer.js"), "page script"),
    }
    # One pass over the template: text put in is never searched for placeholders again.
    return re.sub(
        r"/\*(SCENE_INFO|SCENE_SPZ|SCENE_SCALAR|VENDOR|VIEWER)\*/", lambda m: parts[m.group(0)], _asset("viewer.html")
    )
