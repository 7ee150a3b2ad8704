"""Preset values per stage (DESIGN.md §6). An option given on the command line wins.

``paper`` is the paper's setting; ``fast`` and ``balanced`` are for a 2-core CPU. The preprocess
sizes follow the scans: the bundled 3 mm abdomen CT is 366 mm across, so 128³ (2.9 mm voxels)
keeps its full resolution and 256³ oversamples it twofold.
"""

from __future__ import annotations

from typing import Any, Mapping

PRESET_NAMES = ("fast", "balanced", "paper")
DEFAULT_PRESET = "fast"

PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "preprocess": {
        "fast": {"size": 128, "fit": "pad", "window": "abdomen", "interpolation": "linear"},
        "balanced": {"size": 256, "fit": "pad", "window": "abdomen", "interpolation": "linear"},
        # The paper resized every CT to 512³ with nearest neighbour and min-max scaled it
        # (research/cunerf.md §3.4-3.5).
        "paper": {"size": 512, "fit": "stretch", "window": "full", "interpolation": "nearest"},
    },
}


def resolve(stage: str, preset: str, overrides: Mapping[str, Any]) -> dict[str, Any]:
    """The preset's values for ``stage`` with every non-None override applied."""
    if preset not in PRESET_NAMES:
        raise ValueError(f"unknown preset {preset!r}")
    values = dict(PRESETS[stage][preset])
    values.update({key: value for key, value in overrides.items() if value is not None})
    return values
