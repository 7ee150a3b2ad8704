"""The Gaussian model: raw (pre-activation) parameters, as the reference 3DGS stores them.

means (N, 3) world units; log scales (N, 3); quaternions (N, 4), w first, normalised on use;
opacity logits (N,); SH coefficients split as the reference does, the constant term sh_dc
(N, 1, C) and the rest (N, (degree+1)² − 1, C), with C = 1 for CT (grey, docs/design.md §4) or 3 (they
train at different rates). Activations: exp, normalise, sigmoid, and :func:`sh_to_colour`.
``smoothing`` is the variance of Mip-Splatting's 3D filter per Gaussian (``smoothing.py``), a
property of the training cameras rather than a trained parameter; the scales and opacities the
rasterizer sees include it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from cubecloud_cli.splat.smoothing import smoothed_scales, smoothing_attenuation
from cubecloud_cli.splat.spherical_harmonics import MAX_DEGREE, coefficient_count, rgb_to_sh, sh_to_colour

# The per-Gaussian tensors that training optimises, each a parameter group of Adam.
TRAINED_PARAMETERS = ("means", "log_scales", "quaternions", "opacity_logits", "sh_dc", "sh_rest")
INITIAL_OPACITY = 0.1  # the reference initialisation
# exp(±LOG_SCALE_LIMIT) keeps scales, and the projected covariance's a·c (∝ s⁴ · focal⁴),
# finite in float32 whatever the optimizer does; e¹⁰ is 22 000 world units, far past any scene.
LOG_SCALE_LIMIT = 10.0
MIN_NEIGHBOUR_DISTANCE_SQUARED = 1e-7  # the reference clamp, for duplicated points
# Baked opacities stay this far inside (0, 1), so that their logits are finite in float32.
MIN_BAKED_OPACITY = 1e-7
RESET_OPACITY = 0.01  # the reference's periodic reset caps every opacity at this


def rendered_scales(log_scales: torch.Tensor, smoothing: torch.Tensor | None) -> torch.Tensor:
    """The axis scales as rendered (with the 3D filter, when there is one)."""
    clamped = log_scales.clamp(-LOG_SCALE_LIMIT, LOG_SCALE_LIMIT)
    return torch.exp(clamped) if smoothing is None else smoothed_scales(clamped, smoothing)


def rendered_opacities(
    opacities: torch.Tensor, log_scales: torch.Tensor, smoothing: torch.Tensor | None
) -> torch.Tensor:
    """``opacities`` as rendered (times the 3D filter's attenuation, when there is one)."""
    if smoothing is None:
        return opacities
    return opacities * smoothing_attenuation(log_scales.clamp(-LOG_SCALE_LIMIT, LOG_SCALE_LIMIT), smoothing)


def reset_opacity(opacity_logits: torch.Tensor) -> torch.Tensor:
    """Opacities capped at 0.01 (the reference's periodic reset), as logits."""
    capped = torch.sigmoid(opacity_logits).clamp(max=RESET_OPACITY)
    return torch.logit(capped.clamp_min(1e-7))


@dataclass
class Gaussians:
    means: torch.Tensor
    log_scales: torch.Tensor
    quaternions: torch.Tensor
    opacity_logits: torch.Tensor
    sh_dc: torch.Tensor  # (N, 1, C)
    sh_rest: torch.Tensor  # (N, K − 1, C)
    smoothing: torch.Tensor | None = None  # (N,) 3D filter variance, world units²; None: no filter

    TRAINED = TRAINED_PARAMETERS
    OPACITY_PARAMETER = "opacity_logits"  # the parameter the periodic reset rewrites

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh(self) -> torch.Tensor:
        """All SH coefficients, (N, K, C)."""
        return torch.cat((self.sh_dc, self.sh_rest), dim=1)

    @property
    def channels(self) -> int:
        return self.sh_dc.shape[2]

    @property
    def sh_degree(self) -> int:
        return int(round((self.sh_rest.shape[1] + 1) ** 0.5)) - 1

    def scales(self) -> torch.Tensor:
        """The axis scales as rendered (with the 3D filter, when there is one)."""
        return rendered_scales(self.log_scales, self.smoothing)

    def opacities(self, camera_centre: torch.Tensor | None = None, scales: torch.Tensor | None = None) -> torch.Tensor:
        """The opacities as rendered (with the 3D filter's attenuation, when there is one); the
        same from every camera."""
        return rendered_opacities(torch.sigmoid(self.opacity_logits), self.log_scales, self.smoothing)

    def drawn(
        self, camera_centre: torch.Tensor | None, sh_degree: int | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(scales, opacities, colours) as a rasterizer draws them from ``camera_centre``."""
        return self.scales(), self.opacities(), self.colours(camera_centre, sh_degree)

    def pruning_opacities(self) -> torch.Tensor:
        """The opacities that densification prunes by (the reference's: without the 3D filter)."""
        return torch.sigmoid(self.opacity_logits)

    @staticmethod
    def reset_transparency(opacity_logits: torch.Tensor) -> torch.Tensor:
        return reset_opacity(opacity_logits)

    def baked(self) -> "Gaussians":
        """The same rendered Gaussians with the 3D filter folded into their scales and opacities,
        for files that viewers open without knowing of the filter."""
        if self.smoothing is None:
            return self
        with torch.no_grad():
            scales = self.scales().double()
            opacities = self.opacities().double().clamp(MIN_BAKED_OPACITY, 1.0 - MIN_BAKED_OPACITY)
            logits = torch.log(opacities) - torch.log1p(-opacities)
        dtype = self.log_scales.dtype
        return Gaussians(
            self.means.detach(),
            torch.log(scales).to(dtype),
            self.quaternions.detach(),
            logits.to(dtype),
            self.sh_dc.detach(),
            self.sh_rest.detach(),
        )

    def colours(self, camera_centre: torch.Tensor | None = None, degree: int | None = None) -> torch.Tensor:
        """(N, C) colours seen from ``camera_centre`` (needed only above degree 0)."""
        degree = self.sh_degree if degree is None else min(degree, self.sh_degree)
        directions = None if degree == 0 else self.means - camera_centre
        return sh_to_colour(self.sh, directions, degree)

    def to(self, device: torch.device | str) -> "Gaussians":
        """The same Gaussians on ``device`` (a rasterizer draws on the device its inputs are on)."""
        moved = {name: tensor.to(device) for name, tensor in self.parameters().items()}
        return Gaussians(**moved, smoothing=None if self.smoothing is None else self.smoothing.to(device))

    def parameters(self) -> dict[str, torch.Tensor]:
        return {
            "means": self.means,
            "log_scales": self.log_scales,
            "quaternions": self.quaternions,
            "opacity_logits": self.opacity_logits,
            "sh_dc": self.sh_dc,
            "sh_rest": self.sh_rest,
        }


def neighbour_log_scales(points: np.ndarray) -> np.ndarray:
    """log √(mean squared distance to the 3 nearest neighbours), the reference initial scale."""
    from scipy.spatial import cKDTree

    count = len(points)
    if count < 2:
        return np.zeros(count)
    neighbours = min(3, count - 1)
    distances, _ = cKDTree(points).query(points, k=neighbours + 1)
    squared = np.maximum(np.mean(distances[:, 1:] ** 2, axis=1), MIN_NEIGHBOUR_DISTANCE_SQUARED)
    return 0.5 * np.log(squared)


def gaussians_from_points(xyz: np.ndarray, colours: np.ndarray, channels: int = 1, sh_degree: int = 0) -> Gaussians:
    """Isotropic Gaussians at points, sized by their neighbours, with opacity 0.1 and the
    points' colours (``colours`` in [0, 1], (P, 1) or (P, 3))."""
    if not 0 <= sh_degree <= MAX_DEGREE:
        raise ValueError(f"SH degree must be within 0..{MAX_DEGREE}, got {sh_degree}")
    xyz = np.asarray(xyz, dtype=np.float64)
    colours = np.asarray(colours, dtype=np.float32).reshape(len(xyz), -1)
    if channels == 1 and colours.shape[1] == 3:
        colours = colours.mean(axis=1, keepdims=True)
    elif channels == 3 and colours.shape[1] == 1:
        colours = np.repeat(colours, 3, axis=1)
    count = len(xyz)
    log_scale = torch.from_numpy(neighbour_log_scales(xyz)).float()
    sh = torch.zeros(count, coefficient_count(sh_degree), channels)
    sh[:, 0] = rgb_to_sh(torch.from_numpy(colours))
    quaternions = torch.zeros(count, 4)
    quaternions[:, 0] = 1.0
    return Gaussians(
        torch.from_numpy(xyz).float(),
        log_scale[:, None].repeat(1, 3),
        quaternions,
        torch.full((count,), float(np.log(INITIAL_OPACITY / (1 - INITIAL_OPACITY)))),
        sh[:, :1].contiguous(),
        sh[:, 1:].contiguous(),
    )


def random_points(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The paper's baseline initialisation: points uniform in the volume's cube [−1, 1]³ with
    random grey levels."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, (count, 3)), rng.uniform(0.0, 1.0, (count, 1))
