"""EWA projection of 3D Gaussians into a pinhole view (Zwicker et al. 2001, as 3DGS does it).

Pure, differentiable PyTorch; the constants are those of the reference 3DGS rasterizer
(docs/references.md §1.8–1.9), so a scene trained here renders the same there:

* Gaussians at depth ≤ ``near`` (0.2) are culled;
* the Jacobian is evaluated with x/z and y/z clamped to ±1.3·tan(fov/2), so Gaussians far off
  screen do not blow up;
* 0.3 px² is added to the 2D covariance (a low-pass filter: every splat covers about a pixel);
* the splat's radius is ceil(3·sqrt(λ_max)), λ from mid ± sqrt(max(0.1, mid² − det)).

With ``antialias`` the fixed dilation becomes Mip-Splatting's 2D Mip filter (Yu et al., CVPR
2024): the footprint is convolved with a Gaussian of 0.1 px² (about one pixel's box filter), and
its opacity is scaled by ρ = √(det Σ₂ / det(Σ₂ + 0.1·I)) so that the filter spreads a splat's
energy instead of adding to it. A splat far smaller than a pixel then fades as it shrinks, rather
than staying a 0.3 px² dot at full opacity, which is what makes plain 3DGS alias when zoomed out.
ρ is floored at :data:`MIN_COMPENSATION` (a degenerate, flat splat keeps a trace rather than 0/0);
gsplat's antialiased mode computes the same factor.

Pixel coordinates follow docs/design.md §2: the principal point is (W/2, H/2) and pixel (u, v) has its
centre at (u + 0.5, v + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from cubecloud_cli.raster.constants import (
    DILATION,
    EIGENVALUE_FLOOR,
    FRUSTUM_CLAMP,
    MIN_COMPENSATION,
    MIN_DETERMINANT,
    MIP_FILTER_VARIANCE,
    NEAR_PLANE,
)


def dilation(antialias: bool) -> float:
    """The variance added to every 2D footprint: the Mip filter's, or the reference's fixed one."""
    return MIP_FILTER_VARIANCE if antialias else DILATION


def quaternion_to_rotation(quaternions: torch.Tensor) -> torch.Tensor:
    """(N, 4) w-first quaternions (any norm but 0) to (N, 3, 3) rotation matrices."""
    q = quaternions / quaternions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ),
        dim=-1,
    ).view(-1, 3, 3)


def covariances(scales: torch.Tensor, quaternions: torch.Tensor) -> torch.Tensor:
    """Σ = R S Sᵀ Rᵀ for (N, 3) scales (not log) and (N, 4) quaternions: (N, 3, 3)."""
    m = quaternion_to_rotation(quaternions) * scales[:, None, :]
    return m @ m.transpose(1, 2)


@dataclass
class Projected:
    means2d: torch.Tensor  # (N, 2) pixel coordinates (u, v)
    conics: torch.Tensor  # (N, 3) inverse 2D covariance (a, b, c): power = ½(a dx² + c dy²) + b dx dy
    depths: torch.Tensor  # (N,) camera z
    radii: torch.Tensor  # (N,) int64, 0 where culled
    covariances2d: torch.Tensor  # (N, 3) (a, b, c) of the dilated 2D covariance
    # (N,) the factor each opacity is multiplied by: ρ of the Mip filter, or 1 without it
    compensations: torch.Tensor | None = None

    def effective_opacities(self, opacities: torch.Tensor) -> torch.Tensor:
        return opacities if self.compensations is None else opacities * self.compensations


def project(
    means: torch.Tensor,
    scales: torch.Tensor,
    quaternions: torch.Tensor,
    rotation: torch.Tensor,
    translation: torch.Tensor,
    focal: float,
    width: int,
    height: int,
    near: float = NEAR_PLANE,
    antialias: bool = False,
) -> Projected:
    """Project (N, 3) means with (N, 3) scales (not log) and (N, 4) w-first quaternions through
    one world-to-camera pose; with ``antialias``, through the 2D Mip filter (module docstring).

    Written element by element on (N,) columns rather than with batched 3×3 products: autograd
    then differentiates cheap vector operations, several times faster on a CPU.
    """
    camera = means @ rotation.T + translation
    cx, cy, depth = camera.unbind(1)
    in_front = depth > near
    z = torch.where(in_front, depth, torch.ones_like(depth))  # culled ones stay finite
    limit_x = FRUSTUM_CLAMP * (width / 2.0) / focal
    limit_y = FRUSTUM_CLAMP * (height / 2.0) / focal
    x_over_z = (cx / z).clamp(-limit_x, limit_x)
    y_over_z = (cy / z).clamp(-limit_y, limit_y)
    # Rows of T = J·W (image Jacobian times the camera rotation), each a world-space 3-vector.
    f_over_z = focal / z
    w0, w1, w2 = rotation[0], rotation[1], rotation[2]
    t0 = f_over_z[:, None] * (w0 - x_over_z[:, None] * w2)
    t1 = f_over_z[:, None] * (w1 - y_over_z[:, None] * w2)
    # M = R(q)·diag(s), so Σ = M Mᵀ and the 2D covariance is (T M)(T M)ᵀ.
    q = quaternions / quaternions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    qw, qx, qy, qz = q.unbind(1)
    s0, s1, s2 = scales.unbind(1)
    r = (
        (1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)),
        (2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)),
        (2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)),
    )
    a = torch.zeros_like(depth)
    b = torch.zeros_like(depth)
    c = torch.zeros_like(depth)
    for j, s in enumerate((s0, s1, s2)):
        u0 = (t0[:, 0] * r[0][j] + t0[:, 1] * r[1][j] + t0[:, 2] * r[2][j]) * s
        u1 = (t1[:, 0] * r[0][j] + t1[:, 1] * r[1][j] + t1[:, 2] * r[2][j]) * s
        a = a + u0 * u0
        b = b + u0 * u1
        c = c + u1 * u1
    filter_variance = dilation(antialias)
    compensations = None
    if antialias:
        # ρ² = det Σ₂ / det(Σ₂ + vI) = 1 − (v(a + c) + v²) / det(Σ₂ + vI): the second form keeps its
        # digits (and its gradient) when the splat is far above a pixel and ρ ≈ 1.
        blurred = ((a + filter_variance) * (c + filter_variance) - b * b).clamp_min(MIN_DETERMINANT)
        deficit = (filter_variance * (a + c) + filter_variance**2) / blurred
        compensations = torch.sqrt((1.0 - deficit).clamp_min(MIN_COMPENSATION**2))
    a = a + filter_variance
    c = c + filter_variance
    determinant = (a * c - b * b).clamp_min(MIN_DETERMINANT)
    conics = torch.stack((c / determinant, -b / determinant, a / determinant), dim=-1)
    means2d = torch.stack((focal * cx / z + width / 2.0, focal * cy / z + height / 2.0), dim=-1)
    with torch.no_grad():
        middle = 0.5 * (a + c)
        largest = middle + torch.sqrt((middle * middle - determinant).clamp_min(EIGENVALUE_FLOOR))
        radii = torch.ceil(3.0 * torch.sqrt(largest)).long()
        on_screen = (
            (means2d[:, 0] + radii > 0)
            & (means2d[:, 0] - radii < width)
            & (means2d[:, 1] + radii > 0)
            & (means2d[:, 1] - radii < height)
        )
        finite = torch.isfinite(means2d).all(dim=1) & torch.isfinite(conics).all(dim=1) & torch.isfinite(largest)
        radii = torch.where(
            in_front & on_screen & finite, torch.nan_to_num(radii.float()).long(), torch.zeros_like(radii)
        )
    return Projected(means2d, conics, depth, radii, torch.stack((a, b, c), dim=-1), compensations)
