"""EWA projection of 3D Gaussians into a pinhole view (Zwicker et al. 2001, as 3DGS does it).

Pure, differentiable PyTorch; the constants are those of the reference 3DGS rasterizer
(research/3dgs.md §1.8–1.9), so a scene trained here renders the same there:

* Gaussians at depth ≤ ``near`` (0.2) are culled;
* the Jacobian is evaluated with x/z and y/z clamped to ±1.3·tan(fov/2), so Gaussians far off
  screen do not blow up;
* 0.3 px² is added to the 2D covariance (a low-pass filter: every splat covers about a pixel);
* the splat's radius is ceil(3·sqrt(λ_max)), λ from mid ± sqrt(max(0.1, mid² − det)).

Pixel coordinates follow DESIGN §2: the principal point is (W/2, H/2) and pixel (u, v) has its
centre at (u + 0.5, v + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

NEAR_PLANE = 0.2
DILATION = 0.3
FRUSTUM_CLAMP = 1.3
MIN_DETERMINANT = 1e-12


def quaternion_to_rotation(quaternions: torch.Tensor) -> torch.Tensor:
    """(N, 4) w-first quaternions (any norm but 0) to (N, 3, 3) rotation matrices."""
    q = quaternions / quaternions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
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


def project(
    means: torch.Tensor,
    covariances3d: torch.Tensor,
    rotation: torch.Tensor,
    translation: torch.Tensor,
    focal: float,
    width: int,
    height: int,
    near: float = NEAR_PLANE,
) -> Projected:
    """Project (N, 3) means and (N, 3, 3) covariances through one world-to-camera pose."""
    camera = means @ rotation.T + translation
    depth = camera[:, 2]
    in_front = depth > near
    safe_depth = torch.where(in_front, depth, torch.ones_like(depth))  # culled ones stay finite
    limit_x = FRUSTUM_CLAMP * (width / 2.0) / focal
    limit_y = FRUSTUM_CLAMP * (height / 2.0) / focal
    tx = (camera[:, 0] / safe_depth).clamp(-limit_x, limit_x) * safe_depth
    ty = (camera[:, 1] / safe_depth).clamp(-limit_y, limit_y) * safe_depth
    zeros = torch.zeros_like(depth)
    jacobian = torch.stack(
        (
            focal / safe_depth, zeros, -focal * tx / safe_depth**2,
            zeros, focal / safe_depth, -focal * ty / safe_depth**2,
        ),
        dim=-1,
    ).view(-1, 2, 3)
    transform = jacobian @ rotation
    cov2d = transform @ covariances3d @ transform.transpose(1, 2)
    a = cov2d[:, 0, 0] + DILATION
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + DILATION
    determinant = (a * c - b * b).clamp_min(MIN_DETERMINANT)
    conics = torch.stack((c / determinant, -b / determinant, a / determinant), dim=-1)
    means2d = torch.stack(
        (focal * camera[:, 0] / safe_depth + width / 2.0, focal * camera[:, 1] / safe_depth + height / 2.0), dim=-1
    )
    with torch.no_grad():
        middle = 0.5 * (a + c)
        largest = middle + torch.sqrt((middle * middle - determinant).clamp_min(0.1))
        radii = torch.ceil(3.0 * torch.sqrt(largest)).long()
        on_screen = (
            (means2d[:, 0] + radii > 0) & (means2d[:, 0] - radii < width)
            & (means2d[:, 1] + radii > 0) & (means2d[:, 1] - radii < height)
        )
        radii = torch.where(in_front & on_screen & torch.isfinite(means2d).all(dim=1), radii, torch.zeros_like(radii))
    return Projected(means2d, conics, depth, radii, torch.stack((a, b, c), dim=-1))
