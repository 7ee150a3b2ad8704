"""`cubecloud splat`: options and the call into cubecloud_cli.splat."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Optional

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
from cubecloud_cli.presets import DEFAULT_PRESET
from cubecloud_cli.splat.settings import Init, SplatSettings

log = logging.getLogger("cubecloud")


def _option(name: str, *flags: str):
    return settings_option(SplatSettings, name, *flags)


def splat_settings(preset: str, **options) -> SplatSettings:
    return build_settings(SplatSettings, preset, options)


WorkArgument = Annotated[Path, typer.Argument(help="Work directory; its export/ is the scene unless --scene is given.")]
SceneOption = Annotated[
    Optional[Path],
    typer.Option(
        "--scene",
        help="Train on this COLMAP scene folder instead (sparse/0 + images/, PINHOLE or SIMPLE_PINHOLE).",
        show_default=False,
    ),
]
NameOption = Annotated[
    Optional[str],
    typer.Option(
        "--name",
        help="Write WORK/splat-NAME/ instead of WORK/splat/ (e.g. --name random for the baseline).",
        show_default=False,
    ),
]
IterationsOption = Annotated[Optional[int], _option("iterations")]


@reports_errors
def splat_command(
    work: WorkArgument = Path("work"),
    scene: SceneOption = None,
    preset: PresetOption = DEFAULT_PRESET,
    init: Annotated[Optional[Init], _option("init")] = None,
    random_points: Annotated[Optional[int], _option("random_points")] = None,
    iterations: IterationsOption = None,
    scalar: Annotated[Optional[bool], _option("scalar", "--scalar/--baked")] = None,
    value_anchor: Annotated[Optional[float], _option("value_anchor")] = None,
    value_spread: Annotated[Optional[float], _option("value_spread")] = None,
    chord_lengths: Annotated[Optional[bool], _option("chord_lengths", "--chord-lengths/--no-chord-lengths")] = None,
    channels: Annotated[Optional[int], _option("channels")] = None,
    sh_degree: Annotated[Optional[int], _option("sh_degree")] = None,
    max_gaussians: Annotated[Optional[int], _option("max_gaussians")] = None,
    dssim_weight: Annotated[Optional[float], _option("dssim_weight")] = None,
    rmse_share: Annotated[Optional[float], _option("rmse_share")] = None,
    refine: Annotated[Optional[bool], _option("refine", "--refine/--no-refine")] = None,
    antialias: Annotated[Optional[bool], _option("antialias", "--antialias/--no-antialias")] = None,
    filter_scale: Annotated[Optional[float], _option("filter_scale")] = None,
    eval_every: Annotated[Optional[int], _option("eval_every")] = None,
    checkpoint_every: Annotated[Optional[int], _option("checkpoint_every")] = None,
    seed: Annotated[Optional[int], _option("seed")] = None,
    device: DeviceOption = None,
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

      cubecloud splat work --scalar --name scalar            # Gaussians that carry the scan's value

      cubecloud splat work --scene my_colmap_scene --channels 3 --sh-degree 3 --name mine
    """
    configure_logging(quiet)
    settings = splat_settings(
        preset,
        iterations=iterations,
        max_gaussians=max_gaussians,
        init=init,
        random_points=random_points,
        scalar=scalar,
        value_anchor=value_anchor,
        value_spread=value_spread,
        chord_lengths=chord_lengths,
        channels=channels,
        sh_degree=sh_degree,
        dssim_weight=dssim_weight,
        rmse_share=rmse_share,
        refine=refine,
        antialias=antialias,
        filter_scale=filter_scale,
        eval_every=eval_every,
        checkpoint_every=checkpoint_every,
        seed=seed,
    )
    from cubecloud_cli.splat.stage import train_splat  # torch: imported when the stage runs

    runtime = runtime_from_options(device, threads)
    with stage_bar(stage_dir_name("splat", name)) as on_progress:
        manifest = train_splat(
            work,
            settings,
            scene_dir=scene,
            force=force,
            resume=resume,
            runtime=runtime,
            name=name,
            on_progress=on_progress,
        )
    log.info(f"wrote {Path(work) / stage_dir_name('splat', name)}: {describe_splat(manifest)}")


def describe_splat(manifest: dict) -> str:
    metrics = manifest["metrics"]
    psnr = metrics.get("test_psnr")
    psnr_text = f"{psnr:.2f} dB" if isinstance(psnr, (int, float)) else str(psnr)
    return (
        f"test PSNR {psnr_text} on {metrics['test_views']} views, {metrics['gaussians']} Gaussians, "
        f"{metrics['iterations_per_second']:.1f} it/s, {manifest['timings_s']['total']:.0f} s"
    )
