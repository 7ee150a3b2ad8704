"""What rebuilds a CuNeRF model, torch-free: the field's and the cube renderer's configurations
(stored in every checkpoint), and the chunk a test render takes. The settings (``settings.py``)
make these from options; the networks (``fields.py``, ``model.py``) are built from them."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

DENSITY_ACTIVATIONS = ("softplus", "relu")


@dataclass(frozen=True)
class FieldConfig:
    """Everything needed to rebuild a field (stored in the checkpoint)."""

    kind: str = "grid"  # "cunerf" or "grid"
    density_activation: str = "softplus"
    # cunerf
    frequencies: int = 11
    width: int = 256
    depth: int = 7
    skip_at: int = 4
    # grid
    resolutions: tuple[int, ...] = (16, 32, 64, 128)
    features: int = 4
    hidden: int = 32

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "FieldConfig":
        values = dict(values)
        values["resolutions"] = tuple(values.get("resolutions", cls.resolutions))
        return cls(**values)


@dataclass(frozen=True)
class RenderConfig:
    cube_half_size: float  # world units
    samples_per_axis: int = 4  # n: n³ coarse points per cube (official: 4, i.e. 64)
    importance: int = 64  # fine points drawn from the coarse weights; 0 = coarse only
    separate_fine: bool = True  # a second network for the fine pass (the paper's)
    train_layout: str = "stratified"
    official: bool = False

    @property
    def half_diagonal(self) -> float:
        return self.cube_half_size * math.sqrt(3.0)

    def as_dict(self) -> dict:
        return asdict(self)


RENDER_POINTS_PER_CHUNK = 1 << 18  # ~1 GB of activations for the 8×256 MLP without gradients
# A GPU takes 4× as many: each chunk costs a few kernel launches and a host sync (the air test),
# which at 2¹⁸ points are as long as the paper MLP's bfloat16 products themselves.
GPU_CHUNK_FACTOR = 4


def render_chunk(config: RenderConfig, device_type: str = "cpu") -> int:
    """Cubes per chunk for test renders, so a chunk holds about 262 k points (1 M on a GPU)
    whatever the model's points per cube (8 for the fast preset, 128 for the paper's)."""
    points = config.samples_per_axis**3 + max(config.importance, 0)
    factor = GPU_CHUNK_FACTOR if device_type == "cuda" else 1
    return max(64, min(32768 * factor, RENDER_POINTS_PER_CHUNK * factor // points))
