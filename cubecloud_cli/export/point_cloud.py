"""The cube-sampled point cloud of the paper (its Eq. 1–2), under a structure-aware budget.

The volume's S³ voxels are divided into cubes of ``cube`` voxels per side; ``points_per_cube``
points are drawn uniformly inside each cube (Eq. 2), and the field gives each its intensity and
density. Cubes whose points are all air are dropped, as are air points in the other cubes
(a Gaussian seeded in air only has to be pruned again). The remaining points are held to
``max_points`` by sampling without replacement with weights that favour structure: a fifth of
the weight is spread evenly over the body and four fifths follow the intensity gradient, so
edges, organ boundaries and bone get dense points while homogeneous tissue keeps an even,
sparser cover, and bright but flat regions get no more than dark flat ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

PointFunction = Callable[[torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class PointCloud:
    xyz: np.ndarray  # (P, 3) float32 world coordinates
    intensity: np.ndarray  # (P,) float32 in [0, 1]
    density: np.ndarray  # (P,) float32 ≥ 0 (CuNeRF's σ)
    stats: dict

    @property
    def rgb(self) -> np.ndarray:
        """Grey 8-bit colours (CT is grey: one value in all three channels)."""
        grey = np.clip(np.rint(self.intensity * 255.0), 0, 255).astype(np.uint8)
        return np.repeat(grey[:, None], 3, axis=1)


def cube_boxes(volume_size: int, cube: int) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space corners (C, 3) of the cubes of ``cube`` voxels tiling an S³ volume.

    Cubes are x-major; when ``cube`` does not divide S the last cube along each axis is cut at
    the volume's face, so no point falls outside the volume.
    """
    starts = torch.arange(0, volume_size, cube, dtype=torch.float64)
    stops = torch.clamp(starts + cube, max=volume_size)
    to_world = 2.0 / volume_size
    low_axis, high_axis = starts * to_world - 1.0, stops * to_world - 1.0
    low = torch.stack(torch.meshgrid(low_axis, low_axis, low_axis, indexing="ij"), dim=-1).reshape(-1, 3)
    high = torch.stack(torch.meshgrid(high_axis, high_axis, high_axis, indexing="ij"), dim=-1).reshape(-1, 3)
    return low.float(), high.float()


def sample_in_cubes(low: torch.Tensor, high: torch.Tensor, count: int, generator: torch.Generator) -> torch.Tensor:
    """``count`` points drawn uniformly inside each box: (C, count, 3) (the paper's Eq. 2)."""
    unit = torch.rand((low.shape[0], count, 3), generator=generator, device=low.device)
    return low[:, None, :] + unit * (high - low)[:, None, :]


def gradient_magnitude(function: PointFunction, points: torch.Tensor, spacing: float) -> torch.Tensor:
    """|∇f| by central differences at ``spacing`` world units (one voxel)."""
    squared = torch.zeros(points.shape[0], device=points.device)
    for axis in range(3):
        offset = torch.zeros(3, device=points.device)
        offset[axis] = spacing
        difference = function(points + offset) - function(points - offset)
        squared += difference.float() ** 2
    return squared.sqrt() / (2.0 * spacing)


UNIFORM_SHARE = 0.2  # of the sampling weight, spread evenly so flat tissue is still covered


def structure_weights(gradient: torch.Tensor) -> torch.Tensor:
    """Sampling weights (always > 0): UNIFORM_SHARE of the total spread evenly, the rest in
    proportion to the gradient."""
    mean = gradient.mean() if gradient.numel() else gradient.new_zeros(())
    if not torch.isfinite(mean) or mean <= 0:
        return torch.ones_like(gradient)  # a flat field: every point is as informative as another
    floor = UNIFORM_SHARE / (1.0 - UNIFORM_SHARE)
    return floor + gradient / mean


def weighted_choice(weights: torch.Tensor, count: int, generator: torch.Generator) -> torch.Tensor:
    """``count`` distinct indices drawn with probability ∝ weight (Efraimidis–Spirakis keys),
    in increasing order. Weights must be positive and finite."""
    if count >= weights.numel():
        return torch.arange(weights.numel(), device=weights.device)
    uniform = torch.rand(weights.shape, generator=generator, device=weights.device)
    # log(u)/w is the log of the key u^(1/w); tiny u is clamped so log stays finite.
    keys = torch.log(uniform.clamp_min(1e-30)) / weights
    return torch.topk(keys, count).indices.sort().values


def build_point_cloud(
    intensity: PointFunction,
    density: PointFunction,
    structure: PointFunction,
    volume_size: int,
    cube: int,
    points_per_cube: int,
    max_points: int | None,
    air_threshold: float,
    seed: int = 0,
    device: torch.device | str = "cpu",
    chunk: int = 1 << 18,
) -> PointCloud:
    """Sample, drop air, and hold to the budget. ``intensity``/``density`` come from CuNeRF;
    ``structure`` is the field whose gradient steers the budget (the images' field)."""
    device = torch.device(device)
    generator = torch.Generator(device="cpu").manual_seed(seed)
    low, high = cube_boxes(volume_size, cube)
    points = sample_in_cubes(low, high, points_per_cube, generator).to(device)
    cubes, per_cube = points.shape[0], points.shape[1]
    flat = points.reshape(-1, 3)

    with torch.no_grad():
        values = _chunked(intensity, flat, chunk)
        solid = values > air_threshold
        solid_cubes = solid.view(cubes, per_cube).any(dim=1)
        keep = solid  # points of air cubes are all air, so this drops those cubes too
        kept_points = flat[keep]
        kept_values = values[keep]
        budget_dropped = 0
        if max_points is not None and 0 < max_points < kept_points.shape[0]:
            spacing = 2.0 / volume_size
            gradient = _chunked(lambda p: gradient_magnitude(structure, p, spacing), kept_points, chunk)
            # Drawn on the CPU generator: a seed repeats its points exactly on one device (on
            # another, values may differ by rounding and flip near-ties).
            chosen = weighted_choice(structure_weights(gradient).cpu(), max_points, generator).to(device)
            budget_dropped = kept_points.shape[0] - chosen.numel()
            kept_points, kept_values = kept_points[chosen], kept_values[chosen]
        densities = _chunked(density, kept_points, chunk)

    stats = {
        "cubes": cubes,
        "air_cubes": int(cubes - solid_cubes.sum()),
        "points_per_cube": per_cube,
        "sampled": int(flat.shape[0]),
        "air_points_dropped": int(flat.shape[0] - solid.sum()),
        "budget_dropped": int(budget_dropped),
        "points": int(kept_points.shape[0]),
    }
    return PointCloud(
        kept_points.cpu().numpy().astype(np.float32),
        kept_values.clamp(0.0, 1.0).cpu().numpy().astype(np.float32),
        densities.clamp_min(0.0).cpu().numpy().astype(np.float32),
        stats,
    )


def _chunked(function: PointFunction, points: torch.Tensor, chunk: int) -> torch.Tensor:
    if points.shape[0] == 0:
        return torch.zeros(0, device=points.device)
    return torch.cat([function(points[s : s + chunk]).reshape(-1).float() for s in range(0, points.shape[0], chunk)])
