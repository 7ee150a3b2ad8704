"""Every parameter of the preprocess stage (recorded in its manifest)."""

from __future__ import annotations

from dataclasses import dataclass

from cubecloud_cli.errors import CubecloudError

MIN_SIZE, MAX_SIZE = 8, 2048


@dataclass(frozen=True)
class PreprocessSettings:
    """Every parameter of the stage, after presets are applied (recorded in the manifest)."""

    size: int = 128
    fit: str = "pad"
    window: str = "abdomen"
    hu_min: float | None = None
    hu_max: float | None = None
    modality: str = "auto"
    percentiles: tuple[float, float] = (0.5, 99.5)
    interpolation: str = "linear"
    spacing: tuple[float, float, float] | None = None
    volume_index: int | None = None

    def validate(self) -> None:
        if not MIN_SIZE <= self.size <= MAX_SIZE:
            raise CubecloudError(f"--size {self.size} is outside {MIN_SIZE}..{MAX_SIZE} voxels: the paper uses 512")
        if self.fit not in ("pad", "stretch"):
            raise CubecloudError(f"--fit {self.fit!r} must be pad or stretch")
        if self.interpolation not in ("linear", "nearest"):
            raise CubecloudError(f"--interpolation {self.interpolation!r} must be linear or nearest")
        low, high = self.percentiles
        if not 0 <= low < high <= 100:
            raise CubecloudError(f"--percentiles {low:g},{high:g} must satisfy 0 <= low < high <= 100")
        if self.modality not in ("auto", "ct", "mr"):
            raise CubecloudError(f"--modality {self.modality!r} must be auto, ct or mr")
