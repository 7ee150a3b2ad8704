"""`cubecloud cunerf`: options and the call into cubecloud_cli.cunerf."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Literal, Optional

import typer

from cubecloud_cli.cli.common import (
    DeviceOption,
    ForceOption,
    PresetOption,
    QuietOption,
    ResumeOption,
    ThreadsOption,
    configure_logging,
    reports_errors,
    runtime_from_options,
)
from cubecloud_cli.cli.options import build_settings, settings_option
from cubecloud_cli.cli.progress_bar import stage_bar
from cubecloud_cli.core.artifacts import stage_dir_name
from cubecloud_cli.cunerf.precision import Precision
from cubecloud_cli.cunerf.settings import DENSITY_ACTIVATIONS, CunerfSettings, GridInit, Model, TrainLayout
from cubecloud_cli.presets import DEFAULT_PRESET

log = logging.getLogger("cubecloud")


def _option(name: str, *flags: str):
    return settings_option(CunerfSettings, name, *flags)


WorkArgument = Annotated[Path, typer.Argument(help="Work directory holding preprocess/ (from `cubecloud preprocess`).")]
NameOption = Annotated[
    Optional[str],
    typer.Option(
        "--name", help="Write WORK/cunerf-NAME/ instead of WORK/cunerf/, for runs side by side.", show_default=False
    ),
]
IterationsOption = Annotated[Optional[int], _option("iterations")]


@reports_errors
def cunerf_command(
    work: WorkArgument = Path("work"),
    preset: PresetOption = DEFAULT_PRESET,
    model: Annotated[Optional[Model], _option("model")] = None,
    iterations: IterationsOption = None,
    batch_size: Annotated[Optional[int], _option("batch_size")] = None,
    lr: Annotated[Optional[float], _option("lr")] = None,
    lr_final: Annotated[Optional[float], _option("lr_final")] = None,
    warmup: Annotated[Optional[int], _option("warmup")] = None,
    cube_radius: Annotated[Optional[float], _option("cube_radius")] = None,
    samples_per_axis: Annotated[Optional[int], _option("samples_per_axis")] = None,
    importance: Annotated[Optional[int], _option("importance")] = None,
    train_layout: Annotated[Optional[TrainLayout], _option("train_layout")] = None,
    official_quirks: Annotated[Optional[bool], _option("official", "--official-quirks")] = None,
    density: Annotated[Optional[Literal[DENSITY_ACTIVATIONS]], _option("density")] = None,  # type: ignore[valid-type]
    grid_levels: Annotated[Optional[int], _option("grid_levels")] = None,
    grid_base: Annotated[Optional[int], _option("grid_base")] = None,
    grid_features: Annotated[Optional[int], _option("grid_features")] = None,
    grid_hidden: Annotated[Optional[int], _option("grid_hidden")] = None,
    grid_init: Annotated[Optional[GridInit], _option("grid_init")] = None,
    train_scale: Annotated[Optional[int], _option("train_scale")] = None,
    holdout: Annotated[Optional[int], _option("holdout")] = None,
    val_every: Annotated[Optional[int], _option("val_every")] = None,
    checkpoint_every: Annotated[Optional[int], _option("checkpoint_every")] = None,
    body_fraction: Annotated[Optional[float], _option("body_fraction")] = None,
    export_scale: Annotated[Optional[float], _option("export_scale")] = None,
    skip_air: Annotated[Optional[bool], _option("skip_air", "--skip-air/--no-skip-air")] = None,
    seed: Annotated[Optional[int], _option("seed")] = None,
    precision: Annotated[Optional[Precision], _option("precision")] = None,
    device: DeviceOption = None,
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

      cubecloud cunerf work --preset paper --precision bf16 --device cuda   # its MLP in bfloat16

      cubecloud cunerf work --train-scale 2 --export-scale 2 --name sr2   # zero-shot super-resolution
    """
    configure_logging(quiet)
    options = {
        "model": model,
        "iterations": iterations,
        "batch_size": batch_size,
        "lr": lr,
        "lr_final": lr_final,
        "warmup": warmup,
        "cube_radius": cube_radius,
        "samples_per_axis": samples_per_axis,
        "importance": importance,
        "train_layout": train_layout,
        "official": official_quirks,
        "density": density,
        "grid_levels": grid_levels,
        "grid_base": grid_base,
        "grid_features": grid_features,
        "grid_hidden": grid_hidden,
        "grid_init": grid_init,
        "train_scale": train_scale,
        "holdout": holdout,
        "val_every": val_every,
        "checkpoint_every": checkpoint_every,
        "body_fraction": body_fraction,
        "export_scale": export_scale,
        "skip_air": skip_air,
        "seed": seed,
        "precision": precision,
    }
    from cubecloud_cli.cunerf.stage import train_cunerf  # torch: imported when the stage runs

    settings = build_settings(CunerfSettings, preset, options)
    runtime = runtime_from_options(device, threads)
    with stage_bar(stage_dir_name("cunerf", name)) as on_progress:
        manifest = train_cunerf(
            work, settings, force=force, resume=resume, runtime=runtime, name=name, on_progress=on_progress
        )
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
