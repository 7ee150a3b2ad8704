"""From physical values (HU, MR units) to the [0, 1] intensities every later stage uses."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from cubecloud_cli.core.errors import CubecloudError

log = logging.getLogger("cubecloud")

# Width and level in HU (docs/references.md §2). abdomen = OHIF "soft tissue" (W400 L40), the
# natural default for KiTS-like abdominal CT; soft-tissue = the teaching/mediastinum W350 L50.
CT_WINDOWS: dict[str, tuple[float, float]] = {
    "abdomen": (400.0, 40.0),
    "soft-tissue": (350.0, 50.0),
    "liver": (150.0, 90.0),
    "lung": (1500.0, -600.0),
    "bone": (2500.0, 480.0),
    "brain": (80.0, 40.0),
}
WINDOW_NAMES = (*CT_WINDOWS, "full")  # full = the scan's own min..max (the paper's min-max)
MODALITIES = ("auto", "ct", "mr")  # auto: the DICOM header, else CT when values reach -500 HU

# No tissue is below -500 HU except air and lung, and MR magnitude images are non-negative.
CT_AIR_THRESHOLD_HU = -500.0


@dataclass(frozen=True)
class IntensityMap:
    """A clip to [low, high] followed by the linear map to [0, 1]."""

    low: float
    high: float
    modality: str  # "ct" or "mr"
    method: str  # "window abdomen", "hu range", "min-max", "percentiles 0.5-99.5"

    @property
    def scale(self) -> float:
        # A constant scan has high == low; its map sends everything to 0 rather than dividing by
        # 0. The cap keeps the float32 product finite for ranges down to ~1e-30.
        width = self.high - self.low
        return 1.0 / width if width > 1e-30 else 0.0

    def apply(self, values: np.ndarray, inplace: bool = False) -> np.ndarray:
        """``values`` mapped into [0, 1] as float32 (values are assumed finite).

        With ``inplace`` a float32 input is overwritten instead of copied (saves a volume of
        memory on large scans).
        """
        out = np.asarray(values, dtype=np.float32)
        if out is values and not inplace:
            out = out.copy()
        np.subtract(out, np.float32(self.low), out=out)
        np.multiply(out, np.float32(self.scale), out=out)
        return np.clip(out, 0.0, 1.0, out=out)

    def as_dict(self) -> dict:
        return {"modality": self.modality, "method": self.method, "low": self.low, "high": self.high}


def replace_nonfinite(data: np.ndarray) -> int:
    """Replace NaN and -Inf by the smallest finite value, +Inf by the largest, in place.

    NaN usually marks voxels outside the field of view, which is air. Returns how many voxels
    were replaced; an array with no finite value at all cannot be repaired.
    """
    finite = np.isfinite(data)
    bad = int(finite.size - np.count_nonzero(finite))
    if bad == 0:
        return 0
    if bad == data.size:
        raise CubecloudError("every voxel of the scan is NaN or Inf: the file holds no image")
    low, high = float(data[finite].min()), float(data[finite].max())
    data[np.isnan(data) | np.isneginf(data)] = low
    data[np.isposinf(data)] = high
    return bad


def detect_modality(data: np.ndarray, header_modality: str | None) -> tuple[str, str]:
    """("ct" | "mr", reason). The header wins; otherwise CT is recognised by air in HU."""
    if header_modality in ("ct", "mr"):
        return header_modality, "from the file header"
    minimum = float(data.min())
    if minimum <= CT_AIR_THRESHOLD_HU:
        return "ct", f"values reach {minimum:.0f}, air in Hounsfield units"
    return "mr", f"no value below {CT_AIR_THRESHOLD_HU:.0f}, so not Hounsfield units"


def resolve_intensity_map(
    data: np.ndarray,
    modality: str,
    window: str,
    hu_min: float | None = None,
    hu_max: float | None = None,
    percentiles: tuple[float, float] = (0.5, 99.5),
) -> IntensityMap:
    """Choose the clip range for a scan: a named CT window, an explicit HU range, the scan's
    min-max (``window="full"``), or MR percentiles. ``data`` must be finite."""
    if (hu_min is None) != (hu_max is None):
        raise CubecloudError("give both --hu-min and --hu-max, or neither")
    if modality == "mr":
        if hu_min is not None:
            raise CubecloudError(
                "--hu-min/--hu-max are Hounsfield units, which MR scans do not have: use --percentiles"
            )
        low_pct, high_pct = percentiles
        if not 0 <= low_pct < high_pct <= 100:
            raise CubecloudError(f"--percentiles {low_pct:g},{high_pct:g} must satisfy 0 <= low < high <= 100")
        low, high = np.percentile(data, [low_pct, high_pct])
        return IntensityMap(float(low), float(high), "mr", f"percentiles {low_pct:g}-{high_pct:g}")
    if hu_min is not None:
        if not (np.isfinite(hu_min) and np.isfinite(hu_max) and hu_max > hu_min):
            raise CubecloudError(f"--hu-min {hu_min:g} must be below --hu-max {hu_max:g}")
        return IntensityMap(float(hu_min), float(hu_max), "ct", "hu range")
    if window == "full":
        return IntensityMap(float(data.min()), float(data.max()), "ct", "min-max")
    if window not in CT_WINDOWS:
        raise CubecloudError(f"unknown --window {window!r}: choose one of {', '.join(WINDOW_NAMES)}")
    width, level = CT_WINDOWS[window]
    return IntensityMap(level - width / 2, level + width / 2, "ct", f"window {window}")
