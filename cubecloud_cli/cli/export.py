"""`cubecloud export`: options and the call into cubecloud_cli.export."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Literal, Optional

import typer

from cubecloud_cli.cameras import ORBIT_AXES
from cubecloud_cli.cli.common import (
    DeviceOption,
    ForceOption,
    PresetOption,
    QuietOption,
    ResolutionOption,
    ThreadsOption,
    ViewOption,
    ViewsOption,
    configure_logging,
    reports_errors,
    runtime_from_options,
)
from cubecloud_cli.cli.options import build_settings, settings_option
from cubecloud_cli.cli.progress_bar import stage_bar
from cubecloud_cli.core.artifacts import stage_dir_name
from cubecloud_cli.export.settings import CameraPath, ExportSettings, RenderSource
from cubecloud_cli.presets import DEFAULT_PRESET
from cubecloud_cli.transfer.tissue_presets import TRANSFER_PRESETS

log = logging.getLogger("cubecloud")

_TRANSFERS = "; ".join(f"{name}: {preset.description}" for name, preset in TRANSFER_PRESETS.items())


def _option(name: str, *flags: str, extra: str = ""):
    return settings_option(ExportSettings, name, *flags, extra=extra)


def export_settings(preset: str, **options) -> ExportSettings:
    """Preset values with every option that was given applied on top."""
    return build_settings(ExportSettings, preset, options)


WorkArgument = Annotated[Path, typer.Argument(help="Work directory holding preprocess/ and cunerf/.")]
CunerfNameOption = Annotated[
    Optional[str],
    typer.Option("--cunerf-name", help="Export WORK/cunerf-NAME/ instead of WORK/cunerf/.", show_default=False),
]
NameOption = Annotated[
    Optional[str], typer.Option("--name", help="Write WORK/export-NAME/ instead of WORK/export/.", show_default=False)
]


@reports_errors
def export_command(
    work: WorkArgument = Path("work"),
    preset: PresetOption = DEFAULT_PRESET,
    cube: Annotated[Optional[int], _option("cube")] = None,
    points_per_cube: Annotated[Optional[int], _option("points_per_cube")] = None,
    max_points: Annotated[Optional[int], _option("max_points")] = None,
    air_threshold: Annotated[Optional[float], _option("air_threshold")] = None,
    cameras: Annotated[Optional[CameraPath], _option("cameras")] = None,
    views: ViewsOption = None,
    axis: Annotated[Optional[Literal[tuple(ORBIT_AXES)]], _option("axis")] = None,  # type: ignore[misc]
    radius: Annotated[Optional[float], _option("radius")] = None,
    fov: Annotated[Optional[float], _option("fov")] = None,
    resolution: ResolutionOption = None,
    elevation: Annotated[Optional[float], _option("elevation")] = None,
    view: ViewOption = None,
    transfer: Annotated[
        Optional[Literal[tuple(TRANSFER_PRESETS)]], _option("transfer", extra=f"({_TRANSFERS})")
    ] = None,  # type: ignore[misc]
    tf_low: Annotated[Optional[float], _option("tf_low")] = None,
    tf_high: Annotated[Optional[float], _option("tf_high")] = None,
    tf_density: Annotated[Optional[float], _option("tf_density")] = None,
    transfer_set: Annotated[Optional[int], _option("transfer_set")] = None,
    transfer_stride: Annotated[Optional[int], _option("transfer_stride")] = None,
    held_out_windows: Annotated[Optional[int], _option("held_out_windows")] = None,
    step: Annotated[Optional[float], _option("step")] = None,
    render_from: Annotated[Optional[RenderSource], _option("render_from")] = None,
    bake_size: Annotated[Optional[int], _option("bake_size")] = None,
    seed: Annotated[Optional[int], _option("seed")] = None,
    novel_directions: Annotated[Optional[int], _option("novel_directions")] = None,
    device: DeviceOption = None,
    threads: ThreadsOption = None,
    cunerf_name: CunerfNameOption = None,
    name: NameOption = None,
    force: ForceOption = False,
    quiet: QuietOption = False,
) -> None:
    """Write the CuNeRF scene as a COLMAP scene: cube-sampled points, cameras, rendered views.

    Samples --points-per-cube points in every --cube³ block (the paper's Eq. 1-2) with CuNeRF's intensity and density, drops air, and keeps --max-points where the field has structure. Renders --views images from cameras over the sphere (or a ring about --axis) from CuNeRF (WORK/export/images/, the training images) and from the preprocessed volume (WORK/export/reference/, the ground truth for eval), with the same cameras and image model, and the novel-view test from the volume (WORK/export/novel/). Writes sparse/0/ (COLMAP .bin and .txt), points3D.ply, transforms.json, split.json, contact sheets and manifest.json. 3DGS, gsplat, nerfstudio, OpenSplat and pycolmap open the folder as it is.

    Examples:

      cubecloud export work                                  # dvr, 60 views over the sphere, 128 px (fast preset)

      cubecloud export work --cameras orbit --elevation 20 --name ring   # one ring, raised 20°

      cubecloud export work --view slice --axis ap --name paper-slices   # the paper's images

      cubecloud export work --cameras stack --view slice --axis lr --name sagittal-stack   # the paper's 3DGS baseline

      cubecloud export work --transfer bone --elevation 20 --resolution 256

      cubecloud export work --transfer-set 41 --transfer-stride 6   # views under 41 transfer functions, one view in 6 each, for splat --scalar

      cubecloud export work --transfer-set 41 --transfer-stride 6 --held-out-windows 12   # and 12 random ones held out, for eval
    """
    configure_logging(quiet)
    settings = export_settings(
        preset,
        cube=cube,
        points_per_cube=points_per_cube,
        max_points=max_points,
        air_threshold=air_threshold,
        cameras=cameras,
        views=views,
        axis=axis,
        radius=radius,
        fov=fov,
        resolution=resolution,
        elevation=elevation,
        view=view,
        transfer=transfer,
        tf_low=tf_low,
        tf_high=tf_high,
        tf_density=tf_density,
        transfer_set=transfer_set,
        transfer_stride=transfer_stride,
        held_out_windows=held_out_windows,
        step=step,
        render_from=render_from,
        bake_size=bake_size,
        seed=seed,
        novel_directions=novel_directions,
    )
    from cubecloud_cli.export.stage import export_scene  # torch: imported when the stage runs

    runtime = runtime_from_options(device, threads)
    with stage_bar(stage_dir_name("export", name)) as on_progress:
        manifest = export_scene(
            work, settings, force=force, runtime=runtime, name=name, cunerf_name=cunerf_name, on_progress=on_progress
        )
    log.info(f"wrote {Path(work) / stage_dir_name('export', name)}: {describe_export(manifest)}")


def describe_export(manifest: dict) -> str:
    metrics = manifest["metrics"]
    psnr = metrics.get("cunerf_vs_reference_psnr")
    psnr_text = f"{psnr:.2f} dB" if isinstance(psnr, (int, float)) else str(psnr)
    return (
        f"{metrics['views']} views ({metrics['test_views']} held out), {metrics['points']} points, "
        f"CuNeRF vs reference on test views {psnr_text}, {manifest['timings_s']['total']:.0f} s"
    )
