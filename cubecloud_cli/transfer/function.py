"""A transfer function: how much light a scan value stops (docs/design.md §3).

Kept free of a torch import, since the command line builds its options from the presets; the
methods work on tensors and arrays alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

# Below this the width of the transfer function's ramp is treated as a step at ``low``.
MIN_RAMP_WIDTH = 1e-6


@dataclass(frozen=True)
class TransferFunction:
    """Extinction σ(v) = density · ramp(v), ramp rising linearly from 0 at ``low`` to 1 at ``high``.

    ``low`` and ``high`` are preprocessed intensities in [0, 1]; ``density`` is the extinction
    (per world unit; the volume is 2 units wide) of tissue at or above ``high``.
    """

    low: float = 0.3
    high: float = 0.9
    density: float = 4.0

    def validate(self) -> None:
        if not (0.0 <= self.low <= 1.0 and 0.0 <= self.high <= 1.0) or self.high < self.low:
            raise ValueError(f"transfer function needs 0 <= low <= high <= 1, got low {self.low}, high {self.high}")
        if not (0.0 <= self.density < 1e6):
            raise ValueError(f"transfer function density must be within [0, 1e6), got {self.density}")

    def ramp(self, values: torch.Tensor) -> torch.Tensor:
        width = max(self.high - self.low, MIN_RAMP_WIDTH)
        return ((values - self.low) / width).clamp(0.0, 1.0)

    def extinction(self, values: torch.Tensor) -> torch.Tensor:
        return self.density * self.ramp(values)
