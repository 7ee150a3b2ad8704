"""Transfer-function presets for `--view dvr`: which tissue emits and absorbs light.

Presets are written in Hounsfield units, as radiologists think of them, and converted to the
preprocessed [0, 1] intensities through the window that `preprocess` applied (its manifest
records it). For MR, or a CT whose HU mapping is unknown, each preset has a fallback in window
fractions. A window that clips the preset's range (the abdomen window ends at 240 HU) narrows
the ramp to what the volume can still tell apart.
"""

from __future__ import annotations

from dataclasses import dataclass

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.transfer.function import TransferFunction


@dataclass(frozen=True)
class TransferPreset:
    hu: tuple[float, float] | None  # ramp from 0 to full opacity, in HU (CT)
    fraction: tuple[float, float]  # the same ramp in [0, 1] intensities (MR, unknown windows)
    density: float  # extinction per world unit at full ramp
    description: str


# Densities are chosen so that a ray through the abdomen (about 1.5 world units of body) keeps
# some light: the organs and skeleton show through the skin rather than a white silhouette.
TRANSFER_PRESETS: dict[str, TransferPreset] = {
    "tissue": TransferPreset((-50.0, 250.0), (0.3, 0.9), 4.0, "organs and bone, fat and air clear"),
    "soft": TransferPreset((-120.0, 120.0), (0.15, 0.6), 1.5, "all soft tissue, faint, like a radiograph"),
    "bone": TransferPreset((150.0, 700.0), (0.7, 1.0), 12.0, "skeleton and contrast-filled vessels"),
    "glow": TransferPreset(None, (0.0, 1.0), 1.0, "every non-air voxel glows by its intensity"),
}
DEFAULT_TRANSFER = "tissue"


def hu_to_intensity(hu: float, window: tuple[float, float]) -> float:
    low, high = window
    width = high - low
    if width <= 0:
        return 0.0
    return min(1.0, max(0.0, (hu - low) / width))


def resolve_transfer(
    preset: str,
    intensity_map: dict | None,
    low: float | None = None,
    high: float | None = None,
    density: float | None = None,
) -> TransferFunction:
    """The preset as a TransferFunction for this volume; ``low``/``high`` (intensities) and
    ``density`` override it."""
    if preset not in TRANSFER_PRESETS:
        raise CubecloudError(f"--transfer {preset!r} is not a preset: choose one of {', '.join(TRANSFER_PRESETS)}")
    chosen = TRANSFER_PRESETS[preset]
    ramp_low, ramp_high = chosen.fraction
    window = None
    if intensity_map and intensity_map.get("modality") == "ct" and "low" in intensity_map and "high" in intensity_map:
        window = (float(intensity_map["low"]), float(intensity_map["high"]))
    if chosen.hu is not None and window is not None:
        ramp_low, ramp_high = (hu_to_intensity(h, window) for h in chosen.hu)
    function = TransferFunction(
        low=ramp_low if low is None else low,
        high=ramp_high if high is None else high,
        density=chosen.density if density is None else density,
    )
    try:
        function.validate()
    except ValueError as exc:
        raise CubecloudError(
            f"{exc}: pass --tf-low/--tf-high within [0, 1] with low <= high and --tf-density >= 0"
        ) from None
    return function
