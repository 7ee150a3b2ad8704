"""Where a cube's samples go: the points inside a cube, directions on the sphere, and the
radii that hierarchical resampling draws from the coarse weights (docs/cunerf.md §2.2, §2.4).

Offsets are returned relative to the cube centre, in the units of ``half_size`` (world units),
so a cube of half-size h spans [−h, h]³ around its centre.

Layouts (``n`` points per axis, n³ per cube):

* ``stratified`` (training default): one uniform point in each of the n³ sub-cells.
* ``uniform``: n³ i.i.d. uniform points in the whole cube.
* ``lattice`` (test default): the n³ sub-cell centres, symmetric about the centre.
* ``official-train`` / ``official-lattice``: the official code's layouts, kept for A/B
  comparison. Fractions t ∈ {1/n, 2/n, …, 1} of the side from the low corner; training scales
  each by an independent U(0, 1), which biases points toward the low corner; test uses the
  fractions themselves, which include the high face but not the low one.
"""

from __future__ import annotations

import math
from typing import Literal

import torch

CubeLayout = Literal["stratified", "uniform", "lattice", "official-train", "official-lattice"]
DirectionMode = Literal["uniform", "official", "fibonacci"]
TRAIN_LAYOUTS = ("stratified", "uniform", "official-train")
TEST_LAYOUTS = ("lattice", "official-lattice")


def _cell_corners(n: int, device: torch.device) -> torch.Tensor:
    """(n³, 3) integer sub-cell indices, x varying slowest."""
    steps = torch.arange(n, device=device, dtype=torch.float32)
    return torch.cartesian_prod(steps, steps, steps)


def cube_offsets(
    count: int,
    n: int,
    layout: CubeLayout,
    half_size: float,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """(count, n³, 3) offsets from the cube centre for ``count`` cubes of half-size ``half_size``.

    Deterministic layouts return the same offsets for every cube (an expanded view).
    """
    if n < 1:
        raise ValueError("a cube needs at least one point per axis")
    device = torch.device(device)
    cells = _cell_corners(n, device)  # (n³, 3)
    points = cells.shape[0]
    if layout == "lattice":
        unit = (cells + 0.5) / n  # sub-cell centres, in [0, 1]
        return (2.0 * unit - 1.0).mul(half_size).expand(count, points, 3)
    if layout == "official-lattice":
        unit = (cells + 1.0) / n
        return (2.0 * unit - 1.0).mul(half_size).expand(count, points, 3)
    draws = torch.rand((count, points, 3), generator=generator, device=device)
    if layout == "stratified":
        unit = (cells + draws) / n
    elif layout == "uniform":
        unit = draws
    elif layout == "official-train":
        unit = (cells + 1.0) / n * draws
    else:
        raise ValueError(f"unknown cube layout {layout!r}")
    return (2.0 * unit - 1.0) * half_size


def sphere_directions(
    shape: tuple[int, ...],
    mode: DirectionMode,
    generator: torch.Generator | None = None,
    device: torch.device | str = "cpu",
) -> torch.Tensor:
    """Unit vectors of shape ``shape + (3,)``.

    ``uniform``: area-uniform (cos θ ~ U(−1, 1)). ``official``: θ ~ U(0, π), which crowds the
    poles, as the official code does. ``fibonacci``: deterministic antipodal pairs over a
    Fibonacci sphere along the last dimension of ``shape``, the same for every cube (for
    repeatable test renders).
    """
    device = torch.device(device)
    if mode == "fibonacci":
        # The caller pairs direction j with the j-th smallest radius. Consecutive directions
        # are antipodal pairs (d, −d) over a Fibonacci spiral of half the count, so a cube's
        # points stay centred: neighbouring radii cancel instead of all long radii pointing
        # the same way (the spiral alone runs from +z to −z).
        count = shape[-1]
        half = (count + 1) // 2
        index = torch.arange(half, device=device, dtype=torch.float32) + 0.5
        cos_theta = 1.0 - 2.0 * index / half
        phi = index * (math.pi * (3.0 - math.sqrt(5.0)))
        sin_theta = torch.sqrt(torch.clamp(1.0 - cos_theta * cos_theta, min=0.0))
        spiral = torch.stack((sin_theta * torch.cos(phi), sin_theta * torch.sin(phi), cos_theta), dim=-1)
        if count % 2:  # the one unpaired direction goes with the smallest radius
            paired = torch.cat((spiral[:1], torch.stack((spiral[1:], -spiral[1:]), dim=1).reshape(-1, 3)))
        else:
            paired = torch.stack((spiral, -spiral), dim=1).reshape(-1, 3)
        return paired.expand(*shape, 3)
    u = torch.rand(shape, generator=generator, device=device)
    phi = 2.0 * math.pi * torch.rand(shape, generator=generator, device=device)
    cos_theta = 1.0 - 2.0 * u if mode == "uniform" else torch.cos(math.pi * u)
    sin_theta = torch.sqrt(torch.clamp(1.0 - cos_theta * cos_theta, min=0.0))
    directions = torch.stack((sin_theta * torch.cos(phi), sin_theta * torch.sin(phi), cos_theta), dim=-1)
    return directions.expand(*shape, 3)


def sample_radii_from_weights(
    bin_edges: torch.Tensor,
    weights: torch.Tensor,
    count: int,
    deterministic: bool,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Draw ``count`` radii per cube from the piecewise-constant PDF that ``weights`` put on
    the bins between consecutive ``bin_edges`` (inverse-CDF sampling, as NeRF's ``sample_pdf``).

    bin_edges: (B, M+1) ascending; weights: (B, M) ≥ 0. ``deterministic`` uses evenly spaced
    quantiles instead of uniform draws. An all-zero row falls back to a uniform PDF, and bins
    of zero width never divide by zero.
    """
    weights = weights.detach().clamp(min=0.0) + 1e-5  # the 1e-5 keeps empty cubes samplable
    pdf = weights / weights.sum(dim=-1, keepdim=True)
    cdf = torch.cumsum(pdf, dim=-1)
    cdf = torch.cat((torch.zeros_like(cdf[..., :1]), cdf), dim=-1).clamp(max=1.0)
    batch = weights.shape[0]
    if deterministic:
        u = torch.linspace(0.0, 1.0, count, device=weights.device).expand(batch, count)
    else:
        u = torch.rand((batch, count), generator=generator, device=weights.device)
    u = u.contiguous()
    above = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    below = above - 1
    cdf_low, cdf_high = cdf.gather(-1, below), cdf.gather(-1, above)
    edge_low, edge_high = bin_edges.gather(-1, below), bin_edges.gather(-1, above)
    span = cdf_high - cdf_low
    fraction = torch.where(span > 1e-12, (u - cdf_low) / span.clamp(min=1e-12), torch.zeros_like(span))
    return edge_low + fraction.clamp(0.0, 1.0) * (edge_high - edge_low)
