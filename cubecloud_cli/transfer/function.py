"""A transfer function: how much light a scan value stops (docs/design.md §3).

Kept free of a torch import, since the command line builds its options from the presets; the
methods work on tensors and arrays alike.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

# Below this the width of a ramp (rising or falling) is treated as a step at its start.
MIN_RAMP_WIDTH = 1e-6


@dataclass(frozen=True)
class TransferFunction:
    """Extinction σ(v) = density · rise(v) · fall(v): ``rise`` goes linearly from 0 at ``low`` to 1
    at ``high``; a band (a window with a top, such as lung or contrast-filled vessels) also has a
    ``fall`` from 1 at ``fall_low`` to 0 at ``fall_high``; without one σ stays at ``density``.

    The ends are preprocessed intensities in [0, 1]; ``density`` is the extinction (per world
    unit; the volume is 2 units wide) of tissue on the band's top.
    """

    low: float = 0.3
    high: float = 0.9
    density: float = 4.0
    fall_low: float | None = None
    fall_high: float | None = None

    def validate(self) -> None:
        if not (0.0 <= self.low <= 1.0 and 0.0 <= self.high <= 1.0) or self.high < self.low:
            raise ValueError(f"transfer function needs 0 <= low <= high <= 1, got low {self.low}, high {self.high}")
        if not (0.0 <= self.density < 1e6):
            raise ValueError(f"transfer function density must be within [0, 1e6), got {self.density}")
        if (self.fall_low is None) != (self.fall_high is None):
            raise ValueError("a band transfer function needs both fall_low and fall_high")
        if self.fall_low is not None and not (self.high <= self.fall_low <= self.fall_high <= 1.0):
            raise ValueError(
                f"a band needs high <= fall_low <= fall_high <= 1, got high {self.high}, "
                f"fall {self.fall_low}..{self.fall_high}"
            )

    @property
    def is_band(self) -> bool:
        return self.fall_low is not None

    def ramp(self, values: torch.Tensor) -> torch.Tensor:
        width = max(self.high - self.low, MIN_RAMP_WIDTH)
        rise = ((values - self.low) / width).clip(0.0, 1.0)
        if self.fall_low is None:
            return rise
        fall_width = max(self.fall_high - self.fall_low, MIN_RAMP_WIDTH)
        return rise * (1.0 - ((values - self.fall_low) / fall_width).clip(0.0, 1.0))

    def extinction(self, values: torch.Tensor) -> torch.Tensor:
        return self.density * self.ramp(values)

    def with_window(self, low: float, high: float) -> TransferFunction:
        """The rise moved to ``low``..``high``; a band's fall is lifted to start no lower than
        ``high``, so that the band keeps its order (its top may shrink to nothing)."""
        if self.fall_low is None or self.fall_low >= high:
            return replace(self, low=low, high=high)
        return replace(self, low=low, high=high, fall_low=high, fall_high=max(self.fall_high, high))

    def march_parameters(self) -> tuple[float, float, float, float, float]:
        """(low, rise width, fall start, fall width, density) as the numba march takes them: widths
        at least MIN_RAMP_WIDTH, and a fall that starts at +∞ where there is none."""
        fall_low = math.inf if self.fall_low is None else float(self.fall_low)
        fall_width = 1.0 if self.fall_low is None else max(self.fall_high - self.fall_low, MIN_RAMP_WIDTH)
        return float(self.low), max(self.high - self.low, MIN_RAMP_WIDTH), fall_low, fall_width, float(self.density)

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, fields: dict) -> TransferFunction:
        """From :meth:`as_dict`'s JSON; files written before bands have no fall."""
        fall_low, fall_high = fields.get("fall_low"), fields.get("fall_high")
        return cls(
            float(fields["low"]),
            float(fields["high"]),
            float(fields["density"]),
            None if fall_low is None else float(fall_low),
            None if fall_high is None else float(fall_high),
        )
