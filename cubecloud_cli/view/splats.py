"""Trained Gaussians as a browser viewer draws them: centres, 3×3 covariances, RGB and opacity
computed exactly as the rasterizer computes them, a scene scale that survives the viewer's
float16 covariances, and the clipping plane with what it leaves in view.

The viewer (viser) sends centres as float32 but the six covariance terms as float16, whose
smallest normal number is 6.1e-5: variances below it (σ under 0.008 world units, two voxels of a
512³ cube) fall into float16's subnormal range and lose their digits, and the smallest vanish.
The whole viewer scene is therefore drawn in view units, world × ``scale``, with the scale a
power of two (exact in binary) that brings the typical σ near 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from cubecloud_cli.raster.projection import covariances as world_covariances
from cubecloud_cli.splat.gaussians import Gaussians

FLOAT16_MAX = 65504.0
MAX_VIEW_SCALE = 1024.0
# RAS world axes (docs/design.md §2): the plane normal of each anatomical cut.
CLIP_AXES: dict[str, int] = {"sagittal": 0, "coronal": 1, "axial": 2}
CLIP_CHOICES = ("off", *CLIP_AXES, "view direction")
ClipSide = Literal["below", "above"]


@dataclass(frozen=True)
class ViewSplats:
    """Gaussians in world units, as the rasterizer renders them."""

    centers: np.ndarray  # (N, 3) float32
    covariances: np.ndarray  # (N, 3, 3) float32, R diag(s²) Rᵀ
    rgbs: np.ndarray  # (N, 3) in [0, 1]; a grey scene repeats its one channel
    opacities: np.ndarray  # (N, 1) in [0, 1]

    def __len__(self) -> int:
        return self.centers.shape[0]

    def subset(self, keep: np.ndarray | slice) -> "ViewSplats":
        """The Gaussians ``keep`` selects (a mask, a slice or indices, in their order)."""
        if isinstance(keep, np.ndarray) and keep.dtype.kind in "iu":
            # np.take gathers rows 3x faster than fancy indexing (8 against 27 ms for 100k covariances).
            return ViewSplats(
                *(np.take(a, keep, axis=0) for a in (self.centers, self.covariances, self.rgbs, self.opacities))
            )
        return ViewSplats(self.centers[keep], self.covariances[keep], self.rgbs[keep], self.opacities[keep])

    def scaled(self, scale: float) -> "ViewSplats":
        """The same Gaussians in view units (world × ``scale``)."""
        return ViewSplats(self.centers * scale, self.covariances * scale**2, self.rgbs, self.opacities)


def view_splats(gaussians: Gaussians) -> ViewSplats:
    """Centres, covariances, colours (the SH DC term, as a view-independent render colours them)
    and opacities, with the 3D smoothing filter when the Gaussians carry one."""
    with torch.no_grad():
        covariances = world_covariances(gaussians.scales().double(), gaussians.quaternions.double())
        colours = gaussians.colours(degree=0).double().clamp(0.0, 1.0)
        opacities = gaussians.opacities().double().clamp(0.0, 1.0)
    if colours.shape[1] == 1:
        colours = colours.expand(-1, 3)
    return ViewSplats(
        gaussians.means.detach().numpy().astype(np.float32),
        covariances.numpy().astype(np.float32),
        colours.numpy().astype(np.float32),
        opacities.numpy().astype(np.float32)[:, None],
    )


def view_scale(covariances: np.ndarray) -> float:
    """The power of two that brings the median σ of the Gaussians near 1 in view units, bounded
    so that the largest variance still fits a float16 (and 1 when there is nothing to draw)."""
    variances = np.trace(covariances, axis1=1, axis2=2) / 3.0 if len(covariances) else np.zeros(0)
    variances = variances[np.isfinite(variances) & (variances > 0)]
    if variances.size == 0:
        return 1.0
    median_sigma = math.sqrt(float(np.median(variances)))
    scale = 2.0 ** round(-math.log2(median_sigma))
    largest = float(np.abs(covariances).max())
    while scale > 1.0 / MAX_VIEW_SCALE and largest * scale**2 > FLOAT16_MAX / 2:
        scale /= 2.0
    return float(min(max(scale, 1.0 / MAX_VIEW_SCALE), MAX_VIEW_SCALE))


def clip_mask(centers: np.ndarray, normal: np.ndarray, offset: float, keep: ClipSide = "below") -> np.ndarray:
    """The Gaussians on the kept side of the plane normal·x = offset: "below" keeps normal·x ≤
    offset (those beyond the plane are hidden), "above" the rest. A zero normal keeps every one."""
    normal = np.asarray(normal, dtype=np.float64)
    length = float(np.linalg.norm(normal))
    if not math.isfinite(length) or length == 0.0:
        return np.ones(len(centers), dtype=bool)
    distance = centers.astype(np.float64) @ (normal / length)
    return distance <= offset if keep == "below" else distance >= offset


def axis_normal(axis: str) -> np.ndarray:
    """The RAS unit normal of an anatomical cut (sagittal: left→right, coronal: posterior→anterior,
    axial: inferior→superior)."""
    normal = np.zeros(3)
    normal[CLIP_AXES[axis]] = 1.0
    return normal


def importance_order(splats: ViewSplats, variances: np.ndarray | None = None, stable: bool = True) -> np.ndarray:
    """Indices of the Gaussians, the one that shapes a picture most first: opacity × mean variance
    (how much of the image a Gaussian covers, times how much it hides there), so that drawing the
    first k gives the best picture k Gaussians can. Non-finite weights go last; ties keep their
    order unless ``stable`` is off (a third of the time: the order among equal weights, such as
    the Gaussians a transfer function makes clear, changes no picture). ``variances`` (mean
    variance per Gaussian) saves recomputing them when only the opacities changed."""
    if variances is None:
        variances = mean_variances(splats.covariances)
    weight = splats.opacities[:, 0].astype(np.float64) * variances
    weight = np.where(np.isfinite(weight), weight, -np.inf)
    return np.argsort(-weight, kind="stable" if stable else "quicksort")


def mean_variances(covariances: np.ndarray) -> np.ndarray:
    return np.trace(covariances.astype(np.float64), axis1=1, axis2=2) / 3.0


def by_importance(splats: ViewSplats) -> ViewSplats:
    """The same Gaussians in ``importance_order``."""
    return splats.subset(importance_order(splats))


def detail_percent(percent: float) -> float:
    """A detail setting as the viewer uses it: 1 to 100 %, NaN as 100."""
    return 100.0 if math.isnan(percent) else min(max(float(percent), 1.0), 100.0)


def detail_count(total: int, percent: float) -> int:
    """How many Gaussians ``percent`` of ``total`` draws: at least one of a non-empty scene, at
    most all of them (NaN draws all)."""
    if total <= 0:
        return 0
    share = 1.0 if math.isnan(percent) else min(max(float(percent), 0.0), 100.0) / 100.0
    return min(total, max(1, math.ceil(total * share)))


@dataclass
class Clip:
    """The clipping plane in world units: ``axis`` one of CLIP_CHOICES, ``position`` along it."""

    axis: str = "off"
    position: float = 0.0
    keep: str = "below"
    view_direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))

    def normal(self) -> np.ndarray | None:
        if self.axis == "off":
            return None
        if self.axis == "view direction":
            return -np.asarray(self.view_direction, dtype=np.float64)  # hide what faces the viewer
        return axis_normal(self.axis)


def visible_splats(splats: ViewSplats, clip: Clip) -> ViewSplats:
    """The Gaussians the clipping plane leaves in view."""
    normal = clip.normal()
    if normal is None:
        return splats
    return splats.subset(clip_mask(splats.centers, normal, clip.position, clip.keep))  # type: ignore[arg-type]
