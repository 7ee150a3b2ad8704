"""`cubecloud splat`: options and the call into cubecloud_cli.splat."""

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
from cubecloud_cli.cli.cunerf import Device, DeviceOption, ThreadsOption
from cubecloud_cli.presets import PRESETS, preset_note, resolve
from cubecloud_cli.cli.progress import stage_progress
from cubecloud_cli.runtime import Runtime
from cubecloud_cli.splat.settings import SplatSettings
from cubecloud_cli.splat.stage import train_splat

log = logging.getLogger("cubecloud")


class Init(str, Enum):
    cloud = "cloud"
    random = "random"


WorkArgument = Annotated[Path, typer.Argument(help="Work directory; its export/ is the scene unless --scene is given.")]
SceneOption = Annotated[Optional[Path], unset_option("--scene", "Train on this COLMAP scene folder instead (sparse/0 + images/, PINHOLE or SIMPLE_PINHOLE).")]
InitOption = Annotated[Init, typer.Option("--init", help="cloud: the scene's points (Cube-Cloud). random: uniform points in the volume's cube (the paper's baseline).")]
RandomPointsOption = Annotated[int, typer.Option("--random-points", help="Points for --init random.")]
IterationsOption = Annotated[Optional[int], unset_option("--iterations", f"Training iterations, one view each. {preset_note('splat', 'iterations')}")]
ChannelsOption = Annotated[int, typer.Option("--channels", help="Colour channels: 1 for CT (grey), 3 for RGB scenes.")]
ShDegreeOption = Annotated[int, typer.Option("--sh-degree", help="Spherical-harmonics degree; dvr and slice images are view-independent, so 0.")]
MaxGaussiansOption = Annotated[Optional[int], unset_option("--max-gaussians", f"Gaussian budget; densification stops growing at it. {preset_note('splat', 'max_gaussians')}")]
DssimOption = Annotated[float, typer.Option("--dssim-weight", help="λ of (1-λ)·L1 + λ·D-SSIM (the paper: 0.2).")]
RefineOption = Annotated[bool, typer.Option("--refine/--no-refine", help="Densify, prune and reset opacity on the reference schedule (scaled to --iterations).")]
AntialiasOption = Annotated[Optional[bool], unset_option("--antialias/--no-antialias", f"Mip-Splatting's anti-aliasing: a 3D smoothing filter tied to the training views' sampling rate (baked into point_cloud.ply) and a 2D Mip filter instead of the 0.3 px dilation, so the scene holds when the view zooms. --no-antialias is the paper's plain 3DGS. {preset_note('splat', 'antialias')}")]
EvalEveryOption = Annotated[int, typer.Option("--eval-every", help="Score the test views every K iterations.")]
CheckpointEveryOption = Annotated[int, typer.Option("--checkpoint-every", help="Save a checkpoint every K iterations (and on Ctrl-C).")]
SeedOption = Annotated[int, typer.Option("--seed", help="Seed of the view order, random points and splits.")]
NameOption = Annotated[Optional[str], unset_option("--name", "Write WORK/splat-NAME/ instead of WORK/splat/ (e.g. --name random for the baseline).")]
ResumeOption = Annotated[bool, typer.Option("--resume", help="Continue an interrupted run from its last checkpoint.")]


def splat_settings(preset: str, **options) -> SplatSettings:
    preset_keys = PRESETS["splat"][preset]
    values = resolve("splat", preset, {k: v for k, v in options.items() if k in preset_keys})
    return SplatSettings(**values, **{k: v for k, v in options.items() if k not in preset_keys})


@reports_errors
def splat_command(
    work: WorkArgument = Path("work"),
    scene: SceneOption = None,
    preset: PresetOption = DEFAULT_PRESET_VALUE,
    init: InitOption = Init.cloud,
    random_points: RandomPointsOption = 100_000,
    iterations: IterationsOption = None,
    channels: ChannelsOption = 1,
    sh_degree: ShDegreeOption = 0,
    max_gaussians: MaxGaussiansOption = None,
    dssim_weight: DssimOption = 0.2,
    refine: RefineOption = True,
    antialias: AntialiasOption = None,
    eval_every: EvalEveryOption = 500,
    checkpoint_every: CheckpointEveryOption = 500,
    seed: SeedOption = 0,
    device: DeviceOption = Device.auto,
    threads: ThreadsOption = None,
    name: NameOption = None,
    resume: ResumeOption = False,
    force: ForceOption = False,
    quiet: QuietOption = False,
) -> None:
    """Train 3D Gaussian Splatting on the exported scene, initialised from the Cube-Cloud points.

    One view per iteration with the paper's loss (0.8·L1 + 0.2·D-SSIM), Adam with the reference learning rates, and the reference's densification, pruning and opacity reset scaled to --iterations; anti-aliased as Mip-Splatting unless --no-antialias. On the CPU the rasterizer is cubecloud's numba kernel. Writes WORK/splat/: point_cloud.ply (reference 3DGS layout, opens in splat viewers), preview.png, log.csv and manifest.json with the test views' PSNR.

    Ctrl-C saves a checkpoint; the same command with --resume continues it.

    Examples:

      cubecloud splat work                                   # Cube-Cloud initialisation

      cubecloud splat work --init random --name random       # the paper's baseline, beside it

      cubecloud splat work --scene my_colmap_scene --channels 3 --sh-degree 3 --name mine
    """
    configure_logging(quiet)
    settings = splat_settings(
        preset.value, iterations=iterations, max_gaussians=max_gaussians, init=init.value, random_points=random_points,
        channels=channels, sh_degree=sh_degree, dssim_weight=dssim_weight, refine=refine, antialias=antialias, eval_every=eval_every,
        checkpoint_every=checkpoint_every, seed=seed,
    )
    manifest = train_splat_with_progress(work, settings, scene, force, resume, Runtime(device.value, threads), name)
    log.info(f"wrote {Path(work) / stage_dir_name('splat', name)}: {describe_splat(manifest)}")


def describe_splat(manifest: dict) -> str:
    metrics = manifest["metrics"]
    psnr = metrics.get("test_psnr")
    psnr_text = f"{psnr:.2f} dB" if isinstance(psnr, (int, float)) else str(psnr)
    return (f"test PSNR {psnr_text} on {metrics['test_views']} views, {metrics['gaussians']} Gaussians, "
            f"{metrics['iterations_per_second']:.1f} it/s, {manifest['timings_s']['total']:.0f} s")


def train_splat_with_progress(work: Path, settings: SplatSettings, scene: Path | None, force: bool, resume: bool,
                              runtime: Runtime, name: str | None = None) -> dict:
    with stage_progress("splat", total=settings.iterations) as on_progress:
        return train_splat(work, settings, scene_dir=scene, force=force, resume=resume, runtime=runtime, name=name,
                           on_progress=on_progress)
