"""Everything that decides what `splat` trains (recorded in its manifest), and the reference
3DGS schedule scaled to the iteration count (docs/references.md §1.1–1.3)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import ClassVar, Literal, get_args

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.presets import preset_default

REFERENCE_ITERATIONS = 30_000
Init = Literal["cloud", "random"]
INIT_CHOICES = get_args(Init)


@dataclass(frozen=True)
class SplatSettings:
    STAGE: ClassVar[str] = "splat"

    iterations: int = preset_default("splat", "iterations")
    """Training iterations, one view each."""
    init: Init = "cloud"
    """cloud: the scene's points (Cube-Cloud). random: uniform points in the volume's cube (the paper's baseline)."""
    random_points: int = 100_000
    """Points for --init random."""
    scalar: bool = False
    """Train Gaussians that carry the scan's value and an optical length instead of a baked grey level and opacity:
    a transfer function gives their colour and opacity when drawn, so the scene shows other tissue without retraining.
    Needs a dvr scene from `cubecloud export`."""
    value_anchor: float = 1.0
    """--scalar: weight of a term that holds each Gaussian's value to the scan's at its centre (WORK/preprocess/volume.npy),
    so that Gaussians no training transfer function shows keep true values for those that will. 0 leaves values free."""
    value_spread: float = 1.0
    """--scalar: weight of the scan's variance over each Gaussian's footprint (gᵀΣg for the scan's gradient g at its
    centre), which keeps Gaussians thin across edges, where one value cannot show both sides: 0.8–1.5 dB better under
    held-out transfer functions. 0 turns it off."""
    chord_lengths: bool = True
    """--scalar: scale each Gaussian's optical length by its chord along the ray over a round Gaussian's, so that its
    opacity changes with the view as a volume's does: 0.5–2.3 dB better under held-out transfer functions, about 4 ms
    more a step. `view` and `share` redraw it for the camera once it rests; the PLY, for other splat viewers, holds the
    ratio's mean over the sphere (docs/design.md §4)."""
    channels: int = 1
    """Colour channels: 1 for CT (grey), 3 for RGB scenes."""
    sh_degree: int = 0
    """Spherical-harmonics degree; dvr and slice images are view-independent, so 0."""
    max_gaussians: int | None = preset_default("splat", "max_gaussians")
    """Gaussian budget; densification stops growing at it."""
    dssim_weight: float = 0.2
    """λ of (1-λ)·L1 + λ·D-SSIM (the paper: 0.2)."""
    rmse_share: float = 0.0
    """ρ of the pixel term (1-ρ)·L1 + ρ·RMSE. PSNR scores squared error, which L1 pulls down at one rate for small and
    large errors alike; the RMSE weighs the few large ones on the edges of small bright structures more. 0 is the
    paper's L1; `run --scalar` takes 0.5."""
    lr_means: float = 1.6e-4  # × scene extent, decaying log-linearly to lr_means_final
    lr_means_final: float = 1.6e-6
    lr_sh: float = 0.0025  # the rest of the SH bands train at a twentieth of it
    lr_opacity: float = 0.025
    lr_scales: float = 0.005
    lr_rotation: float = 0.001
    lr_value: float = 0.0025  # a scalar scene's value logits (--scalar)
    lr_length: float = 0.025  # a scalar scene's log optical lengths (--scalar)
    grad_threshold: float = 0.0002
    percent_dense: float = 0.01
    refine: bool = True
    """Densify, prune and reset opacity on the reference schedule (scaled to --iterations)."""
    # Mip-Splatting's filters: docs/design.md §4.
    antialias: bool = preset_default("splat", "antialias")
    """Mip-Splatting's anti-aliasing: a 3D smoothing filter tied to the training views' sampling rate (baked into
    point_cloud.ply) and a 2D Mip filter instead of the 0.3 px dilation, so the scene holds when the view zooms.
    --no-antialias is the paper's plain 3DGS."""
    filter_scale: float = 0.2
    """The 3D filter's variance in squared training pixels (Mip-Splatting's 0.2). A scalar scene, whose values are held
    to the scan at every Gaussian's centre, knows detail finer than a training pixel: `run --scalar` takes 0.01."""
    seed: int = 0
    """Seed of the view order, random points and splits."""
    eval_every: int = 500
    """Score the test views every K iterations."""
    checkpoint_every: int = 500
    """Save a checkpoint every K iterations (and on Ctrl-C)."""

    def validate(self) -> None:
        from cubecloud_cli.splat.spherical_harmonics import MAX_DEGREE  # torch: not for --help

        if self.iterations < 1:
            raise CubecloudError(f"--iterations {self.iterations} must be at least 1")
        if self.init not in INIT_CHOICES:
            raise CubecloudError(f"--init {self.init!r} must be cloud or random")
        if self.scalar and self.channels != 1:
            raise CubecloudError("--scalar Gaussians carry one scan value: leave --channels at 1")
        if not (math.isfinite(self.value_anchor) and self.value_anchor >= 0.0):
            raise CubecloudError(
                f"--value-anchor {self.value_anchor:g} must be a finite weight of 0 or more (default 1)"
            )
        if not (math.isfinite(self.value_spread) and self.value_spread >= 0.0):
            raise CubecloudError(
                f"--value-spread {self.value_spread:g} must be a finite weight of 0 or more (default 1)"
            )
        if self.channels not in (1, 3):
            raise CubecloudError(f"--channels {self.channels} must be 1 (grey CT) or 3")
        if not 0 <= self.sh_degree <= MAX_DEGREE:
            raise CubecloudError(f"--sh-degree {self.sh_degree} must be within 0..{MAX_DEGREE}")
        if self.max_gaussians is not None and self.max_gaussians < 1:
            raise CubecloudError(f"--max-gaussians {self.max_gaussians} must be at least 1")
        if self.random_points < 1:
            raise CubecloudError(f"--random-points {self.random_points} must be at least 1")
        if not 0.0 <= self.dssim_weight <= 1.0:
            raise CubecloudError(f"--dssim-weight {self.dssim_weight:g} must be within [0, 1] (the paper: 0.2)")
        if not 0.0 <= self.rmse_share <= 1.0:
            raise CubecloudError(f"--rmse-share {self.rmse_share:g} must be within [0, 1] (0: the paper's L1)")
        if not (math.isfinite(self.filter_scale) and 0.0 <= self.filter_scale <= 10.0):
            raise CubecloudError(
                f"--filter-scale {self.filter_scale:g} must be within [0, 10] squared pixels (Mip-Splatting: 0.2)"
            )
        if self.eval_every < 1 or self.checkpoint_every < 1:
            raise CubecloudError("--eval-every and --checkpoint-every must be at least 1")

    def as_dict(self) -> dict:
        return asdict(self)

    def scaled(self, reference_iteration: int, minimum: int = 1) -> int:
        """A reference iteration number (out of 30 000) at this run's length."""
        return max(minimum, round(reference_iteration * self.iterations / REFERENCE_ITERATIONS))

    def schedule(self) -> dict[str, int]:
        """Densification from 500 to 15 000 every 100, opacity reset every 3000, one more SH band
        every 1000: the reference's iterations scaled to this run (an interval never drops
        below 10 iterations, so the gradient statistics see several views)."""
        return {
            "densify_from": self.scaled(500),
            "densify_until": self.scaled(15_000),
            "densify_every": self.scaled(100, minimum=10),
            "reset_every": self.scaled(3000, minimum=10),
            "sh_up_every": self.scaled(1000, minimum=1),
        }
