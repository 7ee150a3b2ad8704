"""What a pixel is (docs/design.md §3): the image models and their per-ray accumulators.

Marching models (``dvr``, ``mip``; ``xray`` later) see the samples of each ray in order, a block
at a time, through an accumulator; ``slice`` samples each ray once where it meets a plane. A new
marching model is one accumulator class and one entry in :data:`ACCUMULATORS`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch

from cubecloud_cli.render.image_model_names import IMAGE_MODELS
from cubecloud_cli.transfer.function import TransferFunction


@dataclass(frozen=True)
class ImageModel:
    kind: str = "dvr"
    transfer: TransferFunction = TransferFunction()
    step: float = 2.0 / 256  # world units between samples along a ray
    # A dvr ray stops once less than this much light could still reach it: the error it
    # leaves is below this bound (the reference 3DGS rasterizer stops at 1e-4 too).
    termination: float = 1e-4
    # slice: the plane of view i lies this far (world units) from the origin along the camera's
    # optical axis; empty puts every plane through the origin (the orbit's slices).
    slice_offsets: tuple[float, ...] = ()

    def validate(self) -> None:
        if self.kind not in IMAGE_MODELS:
            raise ValueError(f"unknown image model {self.kind!r}; choose one of {', '.join(IMAGE_MODELS)}")
        if not (self.step > 0.0 and self.step < 2.0):
            raise ValueError(f"ray step must be within (0, 2) world units, got {self.step}")
        if self.slice_offsets and (self.kind != "slice" or not all(math.isfinite(d) for d in self.slice_offsets)):
            raise ValueError("slice offsets need the slice image model and finite values")
        self.transfer.validate()

    def slice_offset(self, index: int) -> float:
        return float(self.slice_offsets[index]) if self.slice_offsets else 0.0

    @property
    def support_threshold(self) -> float:
        """Samples at or below this intensity add nothing to the image, so space holding only
        such values can be skipped."""
        return self.transfer.low if self.kind == "dvr" else 0.0

    def as_dict(self) -> dict:
        return asdict(self)


class EmissionAbsorption:
    """dvr: C = Σ T_i (1 − exp(−σ_i Δ)) v_i with T_i = Π_{j<i} exp(−σ_j Δ), black background."""

    def __init__(self, model: ImageModel, rays: int, device: torch.device):
        self.model = model
        self.colour = torch.zeros(rays, device=device)
        self.transmittance = torch.ones(rays, device=device)

    def add(self, rays: torch.Tensor, values: torch.Tensor) -> None:
        optical_depth = self.model.transfer.extinction(values) * self.model.step  # ≥ 0, finite
        alpha = -torch.expm1(-optical_depth)  # 1 − exp(−x) without cancellation for tiny x
        survive = 1.0 - alpha
        before = torch.cumprod(torch.cat((torch.ones_like(survive[:, :1]), survive[:, :-1]), dim=1), dim=1)
        transmittance = self.transmittance[rays]
        self.colour[rays] += transmittance * (before * alpha * values).sum(dim=1)
        self.transmittance[rays] = transmittance * before[:, -1] * survive[:, -1]

    def finished(self, rays: torch.Tensor) -> torch.Tensor:
        return self.transmittance[rays] < self.model.termination

    def result(self) -> torch.Tensor:
        return self.colour


class MaximumIntensity:
    """mip: the largest intensity along the ray."""

    def __init__(self, model: ImageModel, rays: int, device: torch.device):
        self.maximum = torch.zeros(rays, device=device)

    def add(self, rays: torch.Tensor, values: torch.Tensor) -> None:
        self.maximum[rays] = torch.maximum(self.maximum[rays], values.amax(dim=1))

    def finished(self, rays: torch.Tensor) -> torch.Tensor:
        return self.maximum[rays] >= 1.0  # intensities never exceed 1

    def result(self) -> torch.Tensor:
        return self.maximum


ACCUMULATORS = {"dvr": EmissionAbsorption, "mip": MaximumIntensity}
