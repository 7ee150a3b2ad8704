"""Every parameter of the cunerf stage (recorded in the manifest), and how it builds a model."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import ClassVar, Literal, get_args

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.cunerf.config import DENSITY_ACTIVATIONS, RENDER_POINTS_PER_CHUNK, FieldConfig, RenderConfig
from cubecloud_cli.cunerf.precision import Precision, precision_problem
from cubecloud_cli.presets import preset_default

Model = Literal["fast", "cunerf"]
MODELS = get_args(Model)
TrainLayout = Literal["stratified", "uniform"]
GridInit = Literal["random", "volume"]


@dataclass(frozen=True)
class CunerfSettings:
    STAGE: ClassVar[str] = "cunerf"

    model: Model = preset_default("cunerf", "model")
    """fast: multiresolution feature grid + small MLP (CPU). cunerf: the paper's 8×256 MLP with positional
    encoding, coarse + fine (GPU)."""
    iterations: int = preset_default("cunerf", "iterations")
    """Training iterations; 0 with --grid-init volume keeps the fitted start as it is."""
    batch_size: int = preset_default("cunerf", "batch_size")  # cubes per iteration (official: 1024)
    """Cubes (voxels) per iteration (the official code: 1024)."""
    lr: float = preset_default("cunerf", "lr")
    """Peak learning rate (Adam)."""
    lr_final: float = preset_default("cunerf", "lr_final")
    """Learning rate at the last iteration, reached by log-linear decay."""
    warmup: int = preset_default("cunerf", "warmup")  # iterations of sine warm-up from 1% of lr (official: 1000)
    """Iterations of sine warm-up from 1% of --lr (the official code: 1000)."""
    cube_radius: float = preset_default(
        "cunerf", "cube_radius"
    )  # cube half-size in voxels of the training lattice (official: 1)
    """Cube half-size in voxels, times --train-scale (the paper: 1; 0.5 is the voxel itself)."""
    samples_per_axis: int = preset_default("cunerf", "samples_per_axis")  # n: n³ points per cube (official: 4 → 64)
    """n: n³ points per cube (the paper: 4, so 64 points)."""
    importance: int = preset_default(
        "cunerf", "importance"
    )  # fine points per cube from the coarse weights (official: 64)
    """Fine points per cube drawn from the coarse weights; 0 = no fine pass (the paper: 64)."""
    train_layout: TrainLayout = "stratified"
    """Training points: stratified (one per sub-cell) or uniform (i.i.d. in the cube)."""
    official: bool = False  # the official code's sampling and rendering quirks
    """Reproduce the official code's sampling and rendering quirks (corner-biased samples, asymmetric lattice,
    polar-crowded random directions, unbounded weights) for A/B comparison."""
    density: str = "softplus"
    """Density activation: softplus, or relu as in the official code (can die and render black)."""
    grid_levels: int = 3
    """fast model: grid levels, geometric from --grid-base to one vertex per voxel."""
    grid_base: int = 16
    """fast model: vertices per axis of the coarsest level."""
    grid_features: int = 2
    """fast model: features per grid vertex."""
    grid_hidden: int = 32
    """fast model: width of the MLP's hidden layer."""
    grid_init: GridInit = preset_default("cunerf", "grid_init")
    """fast model: random (tiny random features), or volume (the finest level is solved so that the field renders
    the training voxels exactly, and training only refines it)."""
    train_scale: int = 1
    """Zero-shot super-resolution: train on every s-th voxel per axis, score against all of them."""
    holdout: int = 8  # axial slices kept for validation
    """Axial slices kept out of training for validation."""
    val_every: int = preset_default("cunerf", "val_every")
    """Validate on the held-out slices every K iterations."""
    checkpoint_every: int = preset_default("cunerf", "checkpoint_every")
    """Save a checkpoint every K iterations (and on Ctrl-C)."""
    body_fraction: float = 0.8
    """Share of each batch drawn from non-air voxels; the rest is uniform."""
    export_scale: float = 1.0
    """recon.nii.gz resolution as a multiple of the volume's (2 = twice as many voxels per axis)."""
    skip_air: bool = True
    """Skip rendering blocks that hold no non-zero training voxel (they read 0)."""
    seed: int = 0
    """Seed of every random draw; the same seed repeats a run."""
    precision: Precision = "float32"
    """cunerf model on a CUDA GPU: float32 (as the paper), tf32 (tensor cores in the matrix products) or bf16
    (hidden layers in bfloat16; encoding, head and renderer in float32). The CPU computes in float32."""

    def validate(self) -> None:
        """Refuse options that no volume makes right, with a one-line error naming the fix."""

        def bad(message: str) -> CubecloudError:
            return CubecloudError(message)

        if self.model not in MODELS:
            raise bad(f"--model {self.model!r} must be one of {', '.join(MODELS)}")
        if self.iterations < 0:
            raise bad(f"--iterations {self.iterations} must not be negative")
        if not 1 <= self.batch_size <= 1 << 20:
            raise bad(f"--batch-size {self.batch_size} must be within 1..1048576 cubes")
        if not (0 < self.lr < 10 and 0 < self.lr_final <= self.lr):
            raise bad(f"--lr {self.lr:g} and --lr-final {self.lr_final:g} must satisfy 0 < lr-final <= lr < 10")
        if self.warmup < 0:
            raise bad(f"--warmup {self.warmup} must not be negative")
        if not (math.isfinite(self.cube_radius) and 0.05 <= self.cube_radius <= 16):
            raise bad(f"--cube-radius {self.cube_radius:g} must be within 0.05..16 voxels (the paper uses 1)")
        if not 2 <= self.samples_per_axis <= 8:
            raise bad(f"--samples-per-axis {self.samples_per_axis} must be within 2..8 (the paper uses 4)")
        if not 0 <= self.importance <= 512:
            raise bad(f"--importance {self.importance} must be within 0..512 (the paper uses 64)")
        if self.train_layout not in get_args(TrainLayout):
            raise bad(f"--train-layout {self.train_layout!r} must be stratified or uniform")
        if self.density not in DENSITY_ACTIVATIONS:
            raise bad(f"--density {self.density!r} must be softplus or relu")
        if not 1 <= self.grid_levels <= 8 or self.grid_base < 2 or not 1 <= self.grid_features <= 16:
            raise bad("--grid-levels must be 1..8, --grid-base at least 2, --grid-features 1..16")
        if self.grid_init not in get_args(GridInit):
            raise bad(f"--grid-init {self.grid_init!r} must be random or volume")
        if self.iterations == 0 and self.grid_init != "volume":
            raise bad("--iterations 0 needs --grid-init volume: untrained random features render noise")
        if self.grid_init == "volume" and self.model != "fast":
            raise bad("--grid-init volume needs --model fast (a feature grid to start from)")
        if self.grid_init == "volume" and self.grid_hidden < 2:
            raise bad(
                f"--grid-init volume needs --grid-hidden of at least 2 (a feature passes through two units), not {self.grid_hidden}"
            )
        if not 1 <= self.grid_hidden <= 1024:
            raise bad(f"--grid-hidden {self.grid_hidden} must be within 1..1024")
        if not 1 <= self.train_scale <= 16:
            raise bad(f"--train-scale {self.train_scale} must be within 1..16")
        if self.holdout < 0 or self.val_every < 1 or self.checkpoint_every < 1:
            raise bad("--holdout must be >= 0 and --val-every, --checkpoint-every >= 1")
        if not 0.0 <= self.body_fraction <= 1.0:
            raise bad(f"--body-fraction {self.body_fraction:g} must be within 0..1")
        if not (math.isfinite(self.export_scale) and 0.05 <= self.export_scale <= 8):
            raise bad(f"--export-scale {self.export_scale:g} must be within 0.05..8")
        problem = precision_problem(self.precision, self.model, "cuda")  # the device is checked where it is known
        if problem:
            raise bad(problem)

    def check_for_device(self, device_type: str) -> None:
        """Refuse options that the device cannot run."""
        problem = precision_problem(self.precision, self.model, device_type)
        if problem:
            raise CubecloudError(problem)

    def check_for_volume(self, volume_size: int) -> None:
        """Refuse options that do not fit a volume of ``volume_size``³ voxels."""
        if volume_size // self.train_scale < 2:
            raise CubecloudError(
                f"--train-scale {self.train_scale} leaves fewer than 2 voxels per axis of a {volume_size}³ volume"
            )
        out = round(volume_size * self.export_scale)
        if not 2 <= out <= 2048:
            raise CubecloudError(
                f"--export-scale {self.export_scale:g} gives a {out}³ reconstruction: keep it within 2..2048"
            )

    def points_per_cube(self) -> int:
        return self.samples_per_axis**3 + self.importance

    def training_bytes(self, volume_size: int) -> int:
        """A rough estimate of the memory training allocates (torch itself not counted): the
        volume, the parameters with a gradient and Adam's two moments, and the larger of one
        batch's activations (about 1.3 kB per point for the grid field, 14 kB for the 8×256
        MLP) and one test-render chunk's."""
        volume = 4 * volume_size**3 * 2  # the volume and the body-voxel index
        if self.model == "cunerf":
            parameters, per_point = 2 * 431_000, 14_000
        else:
            rows = sum(r**3 for r in self.field_config(volume_size).resolutions)
            parameters, per_point = rows * self.grid_features, 1_300
        batch = self.batch_size * self.points_per_cube() * per_point
        render = RENDER_POINTS_PER_CHUNK * per_point // 3  # test renders keep no gradients
        return volume + 16 * parameters + max(batch, render)

    def field_config(self, volume_size: int) -> FieldConfig:
        if self.model == "cunerf":
            return FieldConfig(kind="cunerf", density_activation=self.density)
        return FieldConfig(
            kind="grid",
            density_activation=self.density,
            # A coarse level of at most S/8 vertices carries the field across held-out slices.
            resolutions=grid_resolutions(min(self.grid_base, max(2, volume_size // 8)), volume_size, self.grid_levels),
            features=self.grid_features,
            hidden=self.grid_hidden,
        )

    def render_config(self, volume_size: int) -> RenderConfig:
        voxel = 2.0 / volume_size  # world units per voxel
        return RenderConfig(
            cube_half_size=self.cube_radius * self.train_scale * voxel,
            samples_per_axis=self.samples_per_axis,
            importance=self.importance,
            separate_fine=self.model == "cunerf",
            train_layout=self.train_layout,
            official=self.official,
        )

    def as_dict(self) -> dict:
        return asdict(self)


def grid_resolutions(base: int, finest: int, levels: int) -> tuple[int, ...]:
    """Geometric from ``base`` to ``finest`` (one vertex per voxel at the finest level)."""
    base = min(base, finest)
    if levels == 1 or base == finest:
        return (max(finest, 2),)
    growth = (finest / base) ** (1.0 / (levels - 1))
    values = [max(2, int(round(base * growth**level))) for level in range(levels)]
    return tuple(sorted(set(values)))
