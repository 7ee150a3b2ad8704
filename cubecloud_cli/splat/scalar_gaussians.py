"""Gaussians that carry the scan's value (docs/design.md §4): a transfer function gives each its
opacity and colour when it is drawn, so one trained scene shows any tissue.

Each Gaussian holds a value v ∈ (0, 1), the preprocessed intensity (stored as a logit, as the
reference stores opacity), and an optical length ℓ > 0 in world units (stored as its log). Under
transfer function t it stops the light a slab of extinction σ_t(v) and thickness ℓ stops, and
emits its value, as a dvr sample does (§3):

    α_t = 1 − exp(−σ_t(v) · ℓ),    c = v.

With ``chord_lengths`` (``splat --chord-lengths``, the default) ℓ is the length a ray meets at a
round Gaussian of the same volume, scaled for each view by the Gaussian's chord along the ray
(``splat/chord.py``): α_t = 1 − exp(−σ_t(v) · ℓ · r(d)). `cubecloud view` and the shared page
draw r for their camera once it rests; drawn without a camera (the PLY's reference columns, for
other splat viewers: one opacity per Gaussian), r is its mean over the sphere.

The rasterizers are not changed: they get these opacities and colours, and the gradients run back
through the map to v, ℓ and the Gaussian's shape. A Gaussian whose value lies below every window
it is trained under gets no gradient through its opacity; it is pruned as transparent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from cubecloud_cli.splat.chord import chord_log_ratio, sphere_mean_log_ratio
from cubecloud_cli.splat.gaussians import (
    LOG_SCALE_LIMIT,
    RESET_OPACITY,
    Gaussians,
    neighbour_log_scales,
    rendered_opacities,
    rendered_scales,
)
from cubecloud_cli.splat.scalar_appearance import LOG_LENGTH_LIMIT, scalar_appearance
from cubecloud_cli.splat.spherical_harmonics import rgb_to_sh
from cubecloud_cli.transfer.function import TransferFunction

SCALAR_PARAMETERS = ("means", "log_scales", "quaternions", "value_logits", "log_lengths")
# Values stay this far inside (0, 1), so that their logits are finite in float32.
VALUE_MARGIN = 1e-4
INITIAL_OPACITY = 0.1  # under the most opaque transfer function trained on, as the reference starts


def transfer_opacities(values: torch.Tensor, log_lengths: torch.Tensor, transfer: TransferFunction) -> torch.Tensor:
    """α = 1 − exp(−σ(v) ℓ) per Gaussian, in [0, 1): expm1 keeps tiny depths exact."""
    depth = transfer.extinction(values) * torch.exp(log_lengths.clamp(-LOG_LENGTH_LIMIT, LOG_LENGTH_LIMIT))
    return -torch.expm1(-depth)


def most_opaque(values: torch.Tensor, log_lengths: torch.Tensor, transfers: list[TransferFunction]) -> torch.Tensor:
    """Each Gaussian's largest opacity over ``transfers``: what decides whether it is pruned."""
    return torch.stack([transfer_opacities(values, log_lengths, t) for t in transfers]).amax(dim=0)


def largest_extinctions(values: torch.Tensor, transfers: list[TransferFunction]) -> torch.Tensor:
    return torch.stack([t.extinction(values) for t in transfers]).amax(dim=0)


def log_lengths_for_opacity(
    values: torch.Tensor, transfers: list[TransferFunction], opacity: float, fallback: torch.Tensor
) -> torch.Tensor:
    """log ℓ that gives ``opacity`` under the most opaque of ``transfers``; ``fallback`` where
    every one of them is clear at the value (no ℓ gives it any opacity)."""
    extinction = largest_extinctions(values, transfers)
    wanted = -math.log1p(-opacity)  # the optical depth of that opacity
    safe = extinction.clamp_min(1e-30)  # log of a clear Gaussian's extinction is not used
    lengths = torch.where(extinction > 0, math.log(wanted) - torch.log(safe), fallback)
    return lengths.clamp(-LOG_LENGTH_LIMIT, LOG_LENGTH_LIMIT)


@dataclass
class ScalarGaussians:
    """The Gaussian model of a scalar scene, drawn under ``transfer``; ``transfers`` are those it
    is trained under (pruning and the opacity reset look at the most opaque of them)."""

    means: torch.Tensor
    log_scales: torch.Tensor
    quaternions: torch.Tensor
    value_logits: torch.Tensor  # (N,)
    log_lengths: torch.Tensor  # (N,) log world units
    transfer: TransferFunction
    transfers: list[TransferFunction] = field(default_factory=list)
    smoothing: torch.Tensor | None = None
    # A scene read from its PLY has the 3D filter folded into its scales; this is what the filter
    # leaves of each opacity (``filter_attenuation``), applied under every transfer function.
    opacity_scale: torch.Tensor | None = None
    chord_lengths: bool = False  # ℓ scaled by the chord along each ray (splat/chord.py)

    TRAINED = SCALAR_PARAMETERS
    OPACITY_PARAMETER = "log_lengths"
    channels = 1
    sh_degree = 0

    def __len__(self) -> int:
        return self.means.shape[0]

    def values(self) -> torch.Tensor:
        return torch.sigmoid(self.value_logits)

    def scales(self) -> torch.Tensor:
        return rendered_scales(self.log_scales, self.smoothing)

    def seen_log_lengths(
        self, camera_centre: torch.Tensor | None = None, scales: torch.Tensor | None = None
    ) -> torch.Tensor:
        """(N,) log ℓ as drawn: times the chord ratio r seen from ``camera_centre``, or r's mean
        over the sphere without a camera (one opacity per Gaussian); ℓ alone without chord_lengths.
        ``scales``: ``self.scales()`` where the caller has them already."""
        if not self.chord_lengths:
            return self.log_lengths
        scales = self.scales() if scales is None else scales
        if camera_centre is None:
            return self.log_lengths + sphere_mean_log_ratio(scales.detach().log())
        return self.log_lengths + chord_log_ratio(self.means, self.quaternions, scales, camera_centre)

    def opacities(self, camera_centre: torch.Tensor | None = None, scales: torch.Tensor | None = None) -> torch.Tensor:
        opacity = transfer_opacities(self.values(), self.seen_log_lengths(camera_centre, scales), self.transfer)
        if self.opacity_scale is not None:
            opacity = opacity * self.opacity_scale
        return rendered_opacities(opacity, self.log_scales, self.smoothing)

    def drawn(
        self, camera_centre: torch.Tensor | None, sh_degree: int | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(scales, opacities, colours) as a rasterizer draws them from ``camera_centre``: on a CPU
        by one numba pass each way (``scalar_appearance.py``), elsewhere, or for a scene read from
        its PLY, by the torch map the methods above give."""
        if self.means.device.type != "cpu" or self.opacity_scale is not None:
            scales = self.scales()
            return scales, self.opacities(camera_centre, scales), self.colours(camera_centre, sh_degree)
        return scalar_appearance(
            self.means,
            self.quaternions,
            self.log_scales,
            self.value_logits,
            self.log_lengths,
            self.smoothing,
            self.transfer,
            camera_centre,
            self.chord_lengths,
        )

    def filter_attenuation(self) -> torch.Tensor:
        """(N,) the factor in (0, 1] the 3D filter scales every opacity by (1 without a filter)."""
        ones = torch.ones_like(self.log_lengths)
        scale = ones if self.opacity_scale is None else self.opacity_scale
        return rendered_opacities(scale, self.log_scales, self.smoothing)

    def colours(self, camera_centre: torch.Tensor | None = None, degree: int | None = None) -> torch.Tensor:
        """(N, 1) the emission of dvr: the value itself, seen alike from every side."""
        return self.values()[:, None]

    def pruning_opacities(self) -> torch.Tensor:
        return most_opaque(self.values(), self.log_lengths, self.transfers or [self.transfer])

    def reset_transparency(self, log_lengths: torch.Tensor) -> torch.Tensor:
        """ℓ capped so that no transfer function trained on sees an opacity above 0.01."""
        with torch.no_grad():
            capped = log_lengths_for_opacity(
                self.values(), self.transfers or [self.transfer], RESET_OPACITY, log_lengths
            )
            return torch.minimum(log_lengths, capped)

    def drawn_as(self, transfer: TransferFunction) -> "ScalarGaussians":
        """The same Gaussians drawn under another transfer function (no copy of the tensors)."""
        return replace(self, transfer=transfer)

    def baked(self) -> Gaussians:
        """The reference layout under ``transfer``, 3D filter folded in: what any splat viewer draws."""
        with torch.no_grad():
            sh = rgb_to_sh(self.values()[:, None])[:, None, :]
            plain = Gaussians(
                self.means.detach(),
                self.log_scales.detach(),
                self.quaternions.detach(),
                torch.zeros(len(self)),
                sh,
                torch.zeros(len(self), 0, 1),
                self.smoothing,
            )
            opacity = self.opacities().double().clamp(1e-7, 1.0 - 1e-7)
            baked = plain.baked()
            baked.opacity_logits = (torch.log(opacity) - torch.log1p(-opacity)).float()
        return baked

    def to(self, device: torch.device | str) -> "ScalarGaussians":
        moved = {name: tensor.to(device) for name, tensor in self.parameters().items()}
        smoothing = None if self.smoothing is None else self.smoothing.to(device)
        scale = None if self.opacity_scale is None else self.opacity_scale.to(device)
        return ScalarGaussians(
            **moved,
            transfer=self.transfer,
            transfers=self.transfers,
            smoothing=smoothing,
            opacity_scale=scale,
            chord_lengths=self.chord_lengths,
        )

    def parameters(self) -> dict[str, torch.Tensor]:
        return {name: getattr(self, name) for name in SCALAR_PARAMETERS}


# What the trainer, density control and files take: the baked model or the scalar one.
GaussianModel = Gaussians | ScalarGaussians


def scalar_gaussians_from_points(
    xyz: np.ndarray, values: np.ndarray, transfers: list[TransferFunction], chord_lengths: bool = False
) -> ScalarGaussians:
    """Isotropic Gaussians at points, sized by their neighbours, carrying the points' values (the
    Cube-Cloud's CuNeRF intensities), with opacity 0.1 under the most opaque of ``transfers``
    where any of them shows the value."""
    if not transfers:
        raise ValueError("a scalar scene needs at least one transfer function to train under")
    xyz = np.asarray(xyz, dtype=np.float64)
    count = len(xyz)
    value = torch.from_numpy(
        np.clip(np.asarray(values, dtype=np.float64).reshape(count), VALUE_MARGIN, 1 - VALUE_MARGIN)
    )
    log_scale = torch.from_numpy(neighbour_log_scales(xyz)).float().clamp(-LOG_SCALE_LIMIT, LOG_SCALE_LIMIT)
    # A Gaussian of scale s is about 2.5 s thick along a line through its centre (√(2π) s); a
    # value no transfer function shows starts as thick as that.
    fallback = log_scale.double() + math.log(math.sqrt(2.0 * math.pi))
    log_length = log_lengths_for_opacity(value, transfers, INITIAL_OPACITY, fallback)
    quaternions = torch.zeros(count, 4)
    quaternions[:, 0] = 1.0
    return ScalarGaussians(
        torch.from_numpy(xyz).float(),
        log_scale[:, None].repeat(1, 3),
        quaternions,
        torch.logit(value).float(),
        log_length.float(),
        transfers[0],
        list(transfers),
        chord_lengths=chord_lengths,
    )
