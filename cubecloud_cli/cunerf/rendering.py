"""CuNeRF's isotropic volume rendering of one cube (docs/cunerf.md §2.3).

Samples are sorted by their distance r from the cube centre and composited outward:

    r̂_i = r_i / (cube half-diagonal)            A_i = 4π r̂_i²  (the area of the shell through i)
    α_i = A_i (1 − exp(−σ_i δ_i))               T_i = exp(−Σ_{j<i} A_j σ_j δ_j)   (T_1 = 1)
    w_i = T_i α_i                                Ĉ = Σ_i w_i c_i

with δ_i = r̂_{i+1} − r̂_i and the last δ repeating the one before, as in the official code.
Two choices of ours, both reducing to the official formula on randomly placed samples:

* δ is measured in units of the cube half-diagonal, like r̂ (the official code uses its
  [−π, π] coordinate units). This only rescales σ, and makes it independent of the volume size
  and cube radius.
* Samples at the same radius (a symmetric lattice has whole shells of them) share their shell:
  each gets the shell's thickness divided by the shell's count, and each sees the
  transmittance at the start of the shell. The official code gives every tied sample but one
  δ = 0, so which sample speaks for the shell depends on the sort.

``bounded=True`` (our default) divides Ĉ by max(1, Σ w): the shell factor reaches 4π, so the
weights can sum past 1 and Ĉ past 1 (official issue #9). Dividing keeps Ĉ a weighted mean of
intensities in [0, 1] whenever Σ w > 1, and leaves it untouched otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

TIE_TOLERANCE = 1e-6  # radii closer than this (in half-diagonals) form one shell
MAX_DENSITY = 1e4  # σ beyond this changes nothing visible and would risk inf·0


@dataclass
class CubeRender:
    value: torch.Tensor  # (B,) rendered intensity
    weights: torch.Tensor  # (B, N) w_i, in sorted order
    radii: torch.Tensor  # (B, N) r̂_i, sorted ascending
    order: torch.Tensor  # (B, N) the sort permutation of the input samples


def shell_intervals(radii: torch.Tensor, tie_aware: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """δ per sample and the shell index of each sample, for radii sorted ascending (B, N).

    Without ties this is δ_i = r_{i+1} − r_i with the last repeated. With ``tie_aware``, tied
    radii share one shell: thickness = gap to the next shell (the last shell repeats the one
    before; a single shell reaches to r̂ = 1), divided among the shell's members.
    """
    batch, count = radii.shape
    if count == 1:
        return (1.0 - radii).clamp(min=0.0), torch.zeros_like(radii, dtype=torch.long)
    gaps = radii[:, 1:] - radii[:, :-1]
    if not tie_aware:
        delta = torch.cat((gaps, gaps[:, -1:]), dim=1)
        return delta, torch.arange(count, device=radii.device).expand(batch, count)
    new_shell = torch.cat((torch.ones_like(gaps[:, :1], dtype=torch.bool), gaps > TIE_TOLERANCE), dim=1)
    shell = torch.cumsum(new_shell.long(), dim=1) - 1  # (B, N) in [0, shells)
    shells = shell[:, -1:] + 1
    shell_radius = torch.zeros_like(radii).scatter_reduce(1, shell, radii, reduce="amin", include_self=False)
    members = torch.zeros_like(radii).scatter_add(1, shell, torch.ones_like(radii))
    index = torch.arange(count, device=radii.device).expand(batch, count)
    next_radius = torch.cat((shell_radius[:, 1:], shell_radius[:, -1:]), dim=1)
    thickness = next_radius - shell_radius
    # The last shell repeats the thickness of the one before; a lone shell reaches r̂ = 1.
    last = index == (shells - 1)
    before_last = thickness.gather(1, (shells - 2).clamp(min=0))
    lone = (1.0 - shell_radius).clamp(min=0.0)
    thickness = torch.where(last, torch.where(shells > 1, before_last, lone), thickness)
    delta = thickness.gather(1, shell) / members.gather(1, shell).clamp(min=1.0)
    return delta, shell


def render_cubes(
    offsets: torch.Tensor,
    intensity: torch.Tensor,
    density: torch.Tensor,
    half_diagonal: float,
    *,
    tie_aware: bool = True,
    bounded: bool = True,
) -> CubeRender:
    """Render cubes from their samples.

    offsets: (B, N, 3) sample positions relative to each cube centre (world units);
    intensity: (B, N) in [0, 1]; density: (B, N) ≥ 0; half_diagonal: the cube's half-diagonal
    in world units, which normalises the radii.
    """
    if half_diagonal <= 0 or not math.isfinite(half_diagonal):
        raise ValueError(f"the cube half-diagonal must be positive and finite, got {half_diagonal}")
    radii = torch.linalg.vector_norm(offsets, dim=-1) / half_diagonal
    radii, order = torch.sort(radii, dim=1, stable=True)
    sigma = density.gather(1, order).clamp(0.0, MAX_DENSITY)
    color = intensity.gather(1, order)
    delta, shell = shell_intervals(radii, tie_aware)
    area = 4.0 * math.pi * radii * radii
    optical_depth = area * sigma * delta
    before = torch.cumsum(optical_depth, dim=1) - optical_depth  # exclusive sum: T_1 = 1
    if tie_aware:
        # Every member of a shell sees the transmittance at the shell's start.
        start = torch.full_like(before, float("inf")).scatter_reduce(1, shell, before, reduce="amin")
        before = start.gather(1, shell)
    transmittance = torch.exp(-before.clamp(min=0.0))
    alpha = area * -torch.expm1(-sigma * delta)
    weights = transmittance * alpha
    value = (weights * color).sum(dim=1)
    if bounded:
        value = value / weights.sum(dim=1).clamp(min=1.0)
    return CubeRender(value=value, weights=weights, radii=radii, order=order)


def shell_edges(radii: torch.Tensor) -> torch.Tensor:
    """Bin edges for resampling: the mid-radii between consecutive sorted samples (B, N−1)."""
    return 0.5 * (radii[:, 1:] + radii[:, :-1])
