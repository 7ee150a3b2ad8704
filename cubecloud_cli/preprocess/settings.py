"""Every parameter of the preprocess stage (recorded in its manifest).

Each field's docstring is its command-line help; a field the presets set takes its default from
the default preset (presets.py), so each value is written once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal, get_args

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.presets import preset_default
from cubecloud_cli.volume.intensity import MODALITIES

MIN_SIZE, MAX_SIZE = 8, 2048
# A size the preset leaves to the scan (volume/cube_frame.size_for_scan), decided once it is read.
SIZE_FROM_SCAN = "scan"

Fit = Literal["pad", "stretch"]
Modality = Literal[MODALITIES]  # typing flattens the tuple: Literal["auto", "ct", "mr"]
Interpolation = Literal["linear", "nearest"]


@dataclass(frozen=True)
class PreprocessSettings:
    """Every parameter of the stage, after presets are applied (recorded in the manifest)."""

    STAGE: ClassVar[str] = "preprocess"

    size: int | str = preset_default("preprocess", "size")
    """Cube side S in voxels (the paper: 512); the detail preset's "scan" keeps the scan's finest voxel spacing,
    rounded up to a multiple of 16 and capped at 512."""
    fit: Fit = preset_default("preprocess", "fit")
    """pad: keep the physical aspect ratio, pad with air. stretch: resize each axis to S (the paper)."""
    window: str = preset_default("preprocess", "window")
    """CT window, width/level in HU; full = the scan's min..max (the paper)."""
    hu_min: float | None = None
    """Lower end of a custom HU window (with --hu-max); replaces --window."""
    hu_max: float | None = None
    """Upper end of a custom HU window (with --hu-min)."""
    modality: Modality = "auto"
    """ct, mr, or auto: the DICOM header, else CT when values reach -500 HU (air)."""
    percentiles: tuple[float, float] = (0.5, 99.5)
    """MR only: the LOW,HIGH percentiles mapped to 0 and 1."""
    interpolation: Interpolation = preset_default("preprocess", "interpolation")
    """linear (anti-aliased when shrinking) or nearest (the paper's resize)."""
    spacing: tuple[float, float, float] | None = None
    """Voxel size X,Y,Z in mm: required for .npy (axes in RAS order), overrides a wrong header otherwise."""
    volume_index: int | None = None
    """Which volume of a 4D file to use (0-based)."""
    series: str | None = None
    """DICOM: the SeriesInstanceUID to read from a folder holding several (default: the largest axial one)."""

    def validate(self) -> None:
        if self.size == SIZE_FROM_SCAN:
            pass
        elif isinstance(self.size, str) or not MIN_SIZE <= self.size <= MAX_SIZE:
            raise CubecloudError(f"--size {self.size} is outside {MIN_SIZE}..{MAX_SIZE} voxels: the paper uses 512")
        if self.fit not in get_args(Fit):
            raise CubecloudError(f"--fit {self.fit!r} must be pad or stretch")
        if self.interpolation not in get_args(Interpolation):
            raise CubecloudError(f"--interpolation {self.interpolation!r} must be linear or nearest")
        low, high = self.percentiles
        if not 0 <= low < high <= 100:
            raise CubecloudError(f"--percentiles {low:g},{high:g} must satisfy 0 <= low < high <= 100")
        if self.modality not in get_args(Modality):
            raise CubecloudError(f"--modality {self.modality!r} must be auto, ct or mr")
