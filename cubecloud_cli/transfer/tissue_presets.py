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
    """A ramp (``low, high``) or a band (``low, high, fall_low, fall_high``: up, level, down)."""

    hu: tuple[float, ...] | None  # the ends in HU (CT)
    fraction: tuple[float, ...]  # the same ends in [0, 1] intensities (MR, unknown windows)
    density: float  # extinction per world unit at the top
    description: str


# Densities are chosen so that a ray through the abdomen (about 1.5 world units of body) keeps
# some light: the organs and skeleton show through the skin rather than a white silhouette.
# Lung parenchyma lies near -850 HU, air below -950, soft tissue above -100; enhanced blood
# 150-400 HU, cortical bone above 700 (docs/references.md §2).
TRANSFER_PRESETS: dict[str, TransferPreset] = {
    "tissue": TransferPreset((-50.0, 250.0), (0.3, 0.9), 4.0, "organs and bone, fat and air clear"),
    "soft": TransferPreset((-120.0, 120.0), (0.15, 0.6), 1.5, "all soft tissue, faint, like a radiograph"),
    "bone": TransferPreset((150.0, 700.0), (0.7, 1.0), 12.0, "skeleton and contrast-filled vessels"),
    "glow": TransferPreset(None, (0.0, 1.0), 1.0, "every non-air voxel glows by its intensity"),
    "lung": TransferPreset(
        (-950.0, -800.0, -500.0, -300.0), (0.05, 0.15, 0.3, 0.4), 2.0, "lung parenchyma; air and soft tissue clear"
    ),
    "vessels": TransferPreset(
        (100.0, 200.0, 400.0, 600.0), (0.55, 0.65, 0.8, 0.9), 10.0, "contrast-filled vessels; cortical bone clear"
    ),
}
DEFAULT_TRANSFER = "tissue"


def hu_to_intensity(hu: float, window: tuple[float, float]) -> float:
    low, high = window
    width = high - low
    if width <= 0:
        return 0.0
    return min(1.0, max(0.0, (hu - low) / width))


def ct_window(intensity_map: dict | None) -> tuple[float, float] | None:
    """The HU mapped to intensity 0 and 1 by a CT's preprocess window; None for another scan."""
    if intensity_map and intensity_map.get("modality") == "ct" and "low" in intensity_map and "high" in intensity_map:
        return float(intensity_map["low"]), float(intensity_map["high"])
    return None


def clipped_away(preset: str, intensity_map: dict | None) -> str | None:
    """Why the volume cannot show ``preset`` (its HU range lies wholly outside the window that
    preprocess clipped to, so it would show nothing, or everything), or None when it can."""
    chosen = TRANSFER_PRESETS[preset]
    window = ct_window(intensity_map)
    if chosen.hu is None or window is None:
        return None
    top = chosen.hu[-1] if len(chosen.hu) == 4 else float("inf")
    if chosen.hu[0] < window[1] and top > window[0]:
        return None
    return (
        f"{preset} shows {chosen.hu[0]:g}..{top:g} HU, which the window {window[0]:g}..{window[1]:g} HU "
        "clips away: preprocess with a --window that keeps it (lung, bone, full)"
    )


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
    ends = chosen.fraction
    window = ct_window(intensity_map)
    if chosen.hu is not None and window is not None:
        ends = tuple(hu_to_intensity(h, window) for h in chosen.hu)
    fall = ends[2:] if len(ends) == 4 else (None, None)
    function = TransferFunction(ends[0], ends[1], chosen.density if density is None else density, *fall)
    # A --tf-high above the band's top lifts the fall with it.
    function = function.with_window(function.low if low is None else low, function.high if high is None else high)
    try:
        function.validate()
    except ValueError as exc:
        raise CubecloudError(
            f"{exc}: pass --tf-low/--tf-high within [0, 1] with low <= high and --tf-density >= 0"
        ) from None
    return function
