"""`cubecloud cunerf`: options and the call into cubecloud_cli.cunerf."""

from __future__ import annotations

import logging
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer

from cubecloud_cli.artifacts import stage_dir_name
from cubecloud_cli.cli.common import (
    DEFAULT_PRESET_VALUE,
    ForceOption,
    PresetOption,
    QuietOption,
    configure_logging,
    reports_errors,
    unset_option,
)
from cubecloud_cli.cunerf import CunerfSettings, Runtime, train_cunerf
from cubecloud_cli.presets import CUNERF_PRESETS, preset_note, resolve_cunerf
from cubecloud_cli.cli.progress import stage_progress

log = logging.getLogger("cubecloud")


class Model(str, Enum):
    fast = "fast"
    cunerf = "cunerf"


class Density(str, Enum):
    softplus = "softplus"
    relu = "relu"


class Layout(str, Enum):
    stratified = "stratified"
    uniform = "uniform"


class Device(str, Enum):
    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


WorkArgument = Annotated[Path, typer.Argument(help="Work directory holding preprocess/ (from `cubecloud preprocess`).")]
ModelOption = Annotated[Optional[Model], unset_option("--model", "fast: multiresolution feature grid + small MLP (CPU). cunerf: the paper's 8×256 MLP with positional encoding, coarse + fine (GPU). (preset: fast, balanced -> fast; paper -> cunerf)")]
IterationsOption = Annotated[Optional[int], unset_option("--iterations", f"Training iterations. {preset_note('cunerf', 'iterations')}, each with its preset's model; with --model cunerf, fast {CUNERF_PRESETS['fast']['cunerf']['iterations']} and balanced {CUNERF_PRESETS['balanced']['cunerf']['iterations']}")]
BatchOption = Annotated[Optional[int], unset_option("--batch-size", "Cubes (voxels) per iteration. (fast model 4096-8192; cunerf 512-1024)")]
LrOption = Annotated[Optional[float], unset_option("--lr", "Peak learning rate (Adam). (fast 0.05; cunerf 2e-3)")]
LrFinalOption = Annotated[Optional[float], unset_option("--lr-final", "Learning rate at the last iteration, reached by log-linear decay. (fast 5e-4; cunerf 2e-5)")]
WarmupOption = Annotated[Optional[int], unset_option("--warmup", "Iterations of sine warm-up from 1% of --lr. (fast 100; cunerf 1000)")]
CubeRadiusOption = Annotated[Optional[float], unset_option("--cube-radius", "Cube half-size in voxels (times --train-scale). (fast 0.5: the voxel itself; cunerf 1, the paper's)")]
SamplesOption = Annotated[Optional[int], unset_option("--samples-per-axis", "n: n³ points per cube. (fast model 2; cunerf 4, the paper's 64)")]
ImportanceOption = Annotated[Optional[int], unset_option("--importance", "Fine points per cube drawn from the coarse weights; 0 = no fine pass. (fast 0; cunerf 64)")]
LayoutOption = Annotated[Layout, typer.Option("--train-layout", help="Training points: stratified (one per sub-cell) or uniform (i.i.d. in the cube).")]
OfficialOption = Annotated[bool, typer.Option("--official-quirks", help="Reproduce the official code's sampling and rendering quirks (corner-biased samples, asymmetric lattice, polar-crowded random directions, unbounded weights) for A/B comparison.")]
DensityOption = Annotated[Density, typer.Option("--density", help="Density activation: softplus, or relu as in the official code (can die and render black).")]
GridLevelsOption = Annotated[int, typer.Option("--grid-levels", help="fast model: grid levels, geometric from --grid-base to one vertex per voxel.")]
GridBaseOption = Annotated[int, typer.Option("--grid-base", help="fast model: vertices per axis of the coarsest level.")]
GridFeaturesOption = Annotated[int, typer.Option("--grid-features", help="fast model: features per grid vertex.")]
GridHiddenOption = Annotated[int, typer.Option("--grid-hidden", help="fast model: width of the MLP's hidden layer.")]
TrainScaleOption = Annotated[int, typer.Option("--train-scale", help="Zero-shot super-resolution: train on every s-th voxel per axis, score against all of them.")]
HoldoutOption = Annotated[int, typer.Option("--holdout", help="Axial slices kept out of training for validation.")]
ValEveryOption = Annotated[Optional[int], unset_option("--val-every", "Validate on the held-out slices every K iterations. (fast model 1000)")]
CheckpointEveryOption = Annotated[Optional[int], unset_option("--checkpoint-every", "Save a checkpoint every K iterations (and on Ctrl-C). (fast model 500)")]
BodyFractionOption = Annotated[float, typer.Option("--body-fraction", help="Share of each batch drawn from non-air voxels; the rest is uniform.")]
ExportScaleOption = Annotated[float, typer.Option("--export-scale", help="recon.nii.gz resolution as a multiple of the volume's (2 = twice as many voxels per axis).")]
SkipAirOption = Annotated[bool, typer.Option("--skip-air/--no-skip-air", help="Skip rendering blocks that hold no non-zero training voxel (they read 0).")]
SeedOption = Annotated[int, typer.Option("--seed", help="Seed of every random draw; the same seed repeats a run.")]
DeviceOption = Annotated[Device, typer.Option("--device", help="auto (CUDA when available), cpu or cuda.")]
ThreadsOption = Annotated[Optional[int], unset_option("--threads", "CPU threads for torch and for splat's numba kernels (default: all cores).")]
NameOption = Annotated[Optional[str], unset_option("--name", "Write WORK/cunerf-NAME/ instead of WORK/cunerf/, for runs side by side.")]
ResumeOption = Annotated[bool, typer.Option("--resume", help="Continue an interrupted run from its last checkpoint.")]


@reports_errors
def cunerf_command(
    work: WorkArgument = Path("work"),
    preset: PresetOption = DEFAULT_PRESET_VALUE,
    model: ModelOption = None,
    iterations: IterationsOption = None,
    batch_size: BatchOption = None,
    lr: LrOption = None,
    lr_final: LrFinalOption = None,
    warmup: WarmupOption = None,
    cube_radius: CubeRadiusOption = None,
    samples_per_axis: SamplesOption = None,
    importance: ImportanceOption = None,
    train_layout: LayoutOption = Layout.stratified,
    official_quirks: OfficialOption = False,
    density: DensityOption = Density.softplus,
    grid_levels: GridLevelsOption = 3,
    grid_base: GridBaseOption = 16,
    grid_features: GridFeaturesOption = 2,
    grid_hidden: GridHiddenOption = 32,
    train_scale: TrainScaleOption = 1,
    holdout: HoldoutOption = 8,
    val_every: ValEveryOption = None,
    checkpoint_every: CheckpointEveryOption = None,
    body_fraction: BodyFractionOption = 0.8,
    export_scale: ExportScaleOption = 1.0,
    skip_air: SkipAirOption = True,
    seed: SeedOption = 0,
    device: DeviceOption = Device.auto,
    threads: ThreadsOption = None,
    name: NameOption = None,
    resume: ResumeOption = False,
    force: ForceOption = False,
    quiet: QuietOption = False,
) -> None:
    """Train the cube-based neural field (CuNeRF) on the preprocessed volume.

    Each iteration renders cubes centred on voxels, CuNeRF's isotropic volume rendering over n³ points per cube, against the voxels' values. Writes WORK/cunerf/: model.pt (load it with cubecloud_cli.cunerf.CunerfField.load), recon.nii.gz (the field at --export-scale, over the original scan), preview.png, log.csv and manifest.json with 3D PSNR/SSIM.

    Ctrl-C saves a checkpoint; the same command with --resume continues it.

    Examples:

      cubecloud cunerf work                                 # fast grid model, under 3 min on 2 cores

      cubecloud cunerf work --model cunerf --preset paper   # the paper's network (GPU)

      cubecloud cunerf work --train-scale 2 --export-scale 2 --name sr2   # zero-shot super-resolution
    """
    configure_logging(quiet)
    values = resolve_cunerf(
        preset.value,
        model.value if model else None,
        {
            "iterations": iterations,
            "batch_size": batch_size,
            "lr": lr,
            "lr_final": lr_final,
            "warmup": warmup,
            "cube_radius": cube_radius,
            "samples_per_axis": samples_per_axis,
            "importance": importance,
            "val_every": val_every,
            "checkpoint_every": checkpoint_every,
        },
    )
    settings = CunerfSettings(
        **values,
        train_layout=train_layout.value,
        official=official_quirks,
        density=density.value,
        grid_levels=grid_levels,
        grid_base=grid_base,
        grid_features=grid_features,
        grid_hidden=grid_hidden,
        train_scale=train_scale,
        holdout=holdout,
        body_fraction=body_fraction,
        export_scale=export_scale,
        skip_air=skip_air,
        seed=seed,
    )
    manifest = train_cunerf_with_progress(work, settings, force, resume, Runtime(device.value, threads), name)
    log.info(f"wrote {Path(work) / stage_dir_name('cunerf', name)}: {describe_metrics(manifest)}")


def _number(value, digits: int) -> str:
    # The manifest stores inf and nan as strings (JSON has neither).
    return f"{value:.{digits}f}" if isinstance(value, (int, float)) else str(value)


def describe_metrics(manifest: dict) -> str:
    metrics = manifest["metrics"]
    text = f"3D PSNR {_number(metrics['psnr_3d'], 2)} dB"
    if "ssim_3d" in metrics:
        text += f", SSIM {_number(metrics['ssim_3d'], 4)}"
    if "val_psnr" in metrics:
        text += f" (held-out slices {_number(metrics['val_psnr'], 2)} dB)"
    return text + f", {manifest['timings_s']['total']:.0f} s"


def train_cunerf_with_progress(
    work: Path, settings: CunerfSettings, force: bool, resume: bool, runtime: Runtime, name: str | None = None
) -> dict:
    """The stage with a bar: iterations with rate, ETA, loss and validation PSNR."""
    with stage_progress(f"cunerf ({settings.model})", total=settings.iterations) as on_progress:
        return train_cunerf(
            work, settings, force=force, resume=resume, runtime=runtime, name=name, on_progress=on_progress
        )
