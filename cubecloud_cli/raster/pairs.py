"""Alpha compositing of projected Gaussians, in plain PyTorch, differentiated by autograd.

This is the test oracle of the fast kernels, and the fallback on any device. It enumerates the
(Gaussian, pixel) pairs inside each splat's 3σ square, sorts them by pixel and then depth, and
composites front to back with segmented scans, so memory grows with the pairs, not with pixels
× Gaussians. The rules are those of the reference 3DGS rasterizer (docs/references.md §1.9):

* α = min(0.99, o·exp(−power)), and a pair with α < 1/255 is skipped;
* a pixel stops at the first Gaussian that would bring its transmittance below 1e-4, and that
  Gaussian is not blended;
* C = Σ T_i α_i c_i + T_final · background.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from cubecloud_cli.raster.constants import ALPHA_LEVEL_SCALE, MAX_ALPHA, MIN_ALPHA, TRANSMITTANCE_STOP
from cubecloud_cli.raster.projection import Projected


@dataclass
class Pairs:
    gaussian: torch.Tensor  # (P,) int64, sorted by pixel, then front to back
    pixel: torch.Tensor  # (P,) int64, row-major v * W + u


def pixel_bounds(projected: Projected, width: int, height: int, opacities: torch.Tensor | None = None) -> torch.Tensor:
    """(N, 4) int64 inclusive pixel ranges x0, x1, y0, y1 of each splat: the pixels whose centres
    (i + 0.5) lie within its 3σ square, as in the reference. With ``opacities`` the ranges also
    shrink to the box around the ellipse where α = o·exp(−power) ≥ 1/255, since pairs outside it
    are skipped anyway: the image is the same, the work smaller. Culled or off-image splats get
    an empty range (x1 < x0)."""
    with torch.no_grad():
        u, v = projected.means2d[:, 0].detach(), projected.means2d[:, 1].detach()
        half_x = half_y = projected.radii.to(u.dtype)
        if opacities is not None:
            # α ≥ 1/255 ⇔ power ≤ L = ln(255·o), an ellipse whose box has half-sides √(2L·σ²).
            level = torch.log((ALPHA_LEVEL_SCALE * opacities.detach().to(u.dtype)).clamp_min(1e-30)).clamp_min(0.0)
            covariance = projected.covariances2d.detach().to(u.dtype)
            half_x = torch.minimum(half_x, torch.sqrt(2.0 * level * covariance[:, 0]))
            half_y = torch.minimum(half_y, torch.sqrt(2.0 * level * covariance[:, 2]))
        # nan_to_num first: .long() of NaN is undefined (INT64_MIN here), and culled rows get an
        # explicit empty range, so no kernel ever loops over a garbage span.
        x0 = torch.nan_to_num(torch.ceil(u - half_x - 0.5)).clamp(0, width).long()
        x1 = torch.nan_to_num(torch.floor(u + half_x - 0.5)).clamp(-1, width - 1).long()
        y0 = torch.nan_to_num(torch.ceil(v - half_y - 0.5)).clamp(0, height).long()
        y1 = torch.nan_to_num(torch.floor(v + half_y - 0.5)).clamp(-1, height - 1).long()
        culled = (projected.radii <= 0) | ~torch.isfinite(half_x) | ~torch.isfinite(half_y)
        bounds = torch.stack((x0, x1, y0, y1), dim=1)
        return torch.where(culled[:, None], torch.tensor([0, -1, 0, -1], device=bounds.device), bounds)


def depth_order(projected: Projected) -> torch.Tensor:
    """Indices of the visible Gaussians, front to back (ties keep index order)."""
    visible = (projected.radii > 0).nonzero().squeeze(1)
    return visible[torch.argsort(projected.depths[visible].detach(), stable=True)]


def splat_pairs(projected: Projected, width: int, height: int, opacities: torch.Tensor | None = None) -> Pairs:
    """Every (Gaussian, pixel) pair within the Gaussian's :func:`pixel_bounds`."""
    with torch.no_grad():
        device = projected.depths.device
        order = depth_order(projected)
        bounds = pixel_bounds(projected, width, height, opacities)[order]
        x0, x1, y0, y1 = bounds.unbind(1)
        columns = (x1 - x0 + 1).clamp_min(0)
        counts = columns * (y1 - y0 + 1).clamp_min(0)
        total = int(counts.sum())
        owner = torch.repeat_interleave(torch.arange(order.numel(), device=device), counts)  # depth rank
        first = torch.cumsum(counts, 0) - counts
        local = torch.arange(total, device=device) - first[owner]
        pixel = (y0[owner] + local // columns[owner]) * width + x0[owner] + local % columns[owner]
        # Front to back within a pixel: sort by (pixel, depth rank).
        sorted_pairs = torch.argsort(pixel * max(order.numel(), 1) + owner)
        return Pairs(order[owner[sorted_pairs]], pixel[sorted_pairs])


def composite(
    projected: Projected,
    colours: torch.Tensor,
    opacities: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | None = None,
    pairs: Pairs | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Render (H, W, C) colours and (H, W) accumulated alpha from projected Gaussians with
    (N, C) colours and (N,) opacities in [0, 1]."""
    pairs = pairs or splat_pairs(projected, width, height, opacities)
    channels = colours.shape[1]
    g, pixel = pairs.gaussian, pairs.pixel
    centre_u = (pixel % width).to(colours.dtype) + 0.5
    centre_v = torch.div(pixel, width, rounding_mode="floor").to(colours.dtype) + 0.5
    dx = centre_u - projected.means2d[g, 0]
    dy = centre_v - projected.means2d[g, 1]
    conic = projected.conics[g]
    power = 0.5 * (conic[:, 0] * dx * dx + conic[:, 2] * dy * dy) + conic[:, 1] * dx * dy
    alpha = torch.clamp(opacities[g] * torch.exp(-power.clamp_min(0.0)), max=MAX_ALPHA)
    alpha = torch.where(alpha >= MIN_ALPHA, alpha, torch.zeros_like(alpha))

    # Segmented (per pixel) inclusive sums of log(1 − α), in float64: a global cumulative sum
    # over millions of pairs would otherwise cancel catastrophically.
    log_survive = torch.log1p(-alpha).double()
    running = torch.cumsum(log_survive, 0)
    starts = torch.ones_like(pixel, dtype=torch.bool)
    starts[1:] = pixel[1:] != pixel[:-1]
    segment = torch.cumsum(starts.long(), 0) - 1
    before_segment = (running - log_survive)[starts]
    inclusive = running - before_segment[segment]
    blended = torch.exp(inclusive) >= TRANSMITTANCE_STOP  # a prefix of each pixel's list
    weight = (torch.exp(inclusive - log_survive) * alpha.double() * blended).to(colours.dtype)

    image = torch.zeros(height * width, channels, dtype=colours.dtype, device=colours.device)
    image = image.index_add(0, pixel, weight[:, None] * colours[g])
    coverage = torch.zeros(height * width, dtype=colours.dtype, device=colours.device).index_add(0, pixel, weight)
    if background is not None:
        image = image + (1.0 - coverage)[:, None] * background.to(colours.dtype)
    return image.view(height, width, channels), coverage.view(height, width)
