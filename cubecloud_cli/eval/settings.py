"""Every parameter of the eval stage (recorded in its manifest)."""

from __future__ import annotations

from dataclasses import dataclass

from cubecloud_cli.core.errors import CubecloudError


@dataclass(frozen=True)
class EvalSettings:
    turntable_frames: int = 72  # 0: no turntables
    """Frames of each run's turntable GIF (a dense orbit like the export's); 0 for none."""
    turntable_resolution: int = 256  # renders larger than this are shown at this size
    """Largest side of the turntable frames, in pixels."""

    def validate(self) -> None:
        from cubecloud_cli.eval.runs import MAX_TURNTABLE_FRAMES  # torch: not for --help

        if self.turntable_frames != 0 and not 2 <= self.turntable_frames <= MAX_TURNTABLE_FRAMES:
            raise CubecloudError(
                f"--turntable-frames {self.turntable_frames} must be 0 (none) or between 2 and "
                f"{MAX_TURNTABLE_FRAMES}, e.g. 72"
            )
        if not 16 <= self.turntable_resolution <= 4096:
            raise CubecloudError(
                f"--turntable-resolution {self.turntable_resolution} must be between 16 and 4096 pixels"
            )
