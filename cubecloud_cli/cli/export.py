"""`cubecloud export`: options and the call into cubecloud_cli.export."""

from __future__ import annotations

import logging
from enum import Enum
from pathlib import Path
from typing import Annotated, Optional

import typer

from cubecloud_cli.artifacts import stage_dir_name
from cubecloud_cli.cameras.novel import DEFAULT_DIRECTIONS
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
from cubecloud_cli.cunerf import Runtime
from cubecloud_cli.export import ExportSettings, export_scene
from cubecloud_cli.export.transfer import TRANSFER_PRESETS
from cubecloud_cli.presets import PRESETS, preset_note, resolve
from cubecloud_cli.cli.progress import stage_progress

log = logging.getLogger("cubecloud")


class Axis(str, Enum):
    si = "si"
    ap = "ap"
    lr = "lr"


class View(str, Enum):
    dvr = "dvr"
    slice = "slice"
    mip = "mip"


class CameraPath(str, Enum):
    sphere = "sphere"
    orbit = "orbit"
    stack = "stack"


class RenderFrom(str, Enum):
    grid = "grid"
    field = "field"


Transfer = Enum("Transfer", {name: name for name in TRANSFER_PRESETS}, type=str)  # type: ignore[misc]
_PRESET_HELP = "; ".join(f"{name}: {preset.description}" for name, preset in TRANSFER_PRESETS.items())


WorkArgument = Annotated[Path, typer.Argument(help="Work directory holding preprocess/ and cunerf/.")]
CubeOption = Annotated[int, typer.Option("--cube", help="Cube side in voxels for point sampling (the paper: 16).")]
PointsPerCubeOption = Annotated[Optional[int], unset_option("--points-per-cube", f"Points drawn uniformly in each cube. {preset_note('export', 'points_per_cube')}")]
MaxPointsOption = Annotated[Optional[int], unset_option("--max-points", f"Point budget, filled where the field has structure (edges) first; 0 keeps every non-air point. {preset_note('export', 'max_points')}")]
AirOption = Annotated[float, typer.Option("--air-threshold", help="Points whose CuNeRF intensity is at or below this are air and dropped.")]
CamerasOption = Annotated[Optional[CameraPath], unset_option("--cameras", f"sphere: --views cameras spread evenly over the whole sphere of directions, --axis up (DESIGN §2). orbit: --views cameras on a ring around --axis (the paper's). stack: the paper's 3DGS baseline, --views parallel slices across --axis (lr: sagittal) all seen from one camera pose; needs --view slice. {preset_note('export', 'cameras')}")]
ViewsOption = Annotated[Optional[int], unset_option("--views", f"Training cameras (the paper: 60); every 8th is held out for testing. {preset_note('export', 'views')}")]
AxisOption = Annotated[Optional[Axis], unset_option("--axis", f"Orbit axis, or the sphere's pole axis and image up: si (long axis, head up), ap (the paper's sagittal axis), lr. With --cameras stack, the slice normal instead: lr sagittal (its default), ap coronal, si axial. {preset_note('export', 'axis')}")]
RadiusOption = Annotated[float, typer.Option("--radius", help="Camera distance from the volume's centre, in world units (the volume spans -1..1).")]
FovOption = Annotated[Optional[float], unset_option("--fov", "Field of view in degrees (default: just wide enough for the whole volume in every view).")]
ResolutionOption = Annotated[Optional[int], unset_option("--resolution", f"Image width and height in pixels. {preset_note('export', 'resolution')}")]
ElevationOption = Annotated[float, typer.Option("--elevation", help="--cameras orbit: degrees the orbit is raised out of its plane (all views alike).")]
ViewOption = Annotated[Optional[View], unset_option("--view", f"Image model: dvr (volume rendering through a transfer function), slice (the cross-section facing the camera, the paper's images) or mip (maximum intensity). {preset_note('export', 'view')}")]
TransferOption = Annotated[Transfer, typer.Option("--transfer", help=f"dvr transfer function preset, in HU for CT: {_PRESET_HELP}.")]  # type: ignore[valid-type]
TfLowOption = Annotated[Optional[float], unset_option("--tf-low", "dvr: intensity (0..1) where tissue starts to absorb; overrides the preset.")]
TfHighOption = Annotated[Optional[float], unset_option("--tf-high", "dvr: intensity (0..1) of full absorption; overrides the preset.")]
TfDensityOption = Annotated[Optional[float], unset_option("--tf-density", "dvr: extinction per world unit at full absorption; higher is more opaque.")]
StepOption = Annotated[float, typer.Option("--step", help="Ray-march step in voxels of the preprocessed volume.")]
RenderFromOption = Annotated[RenderFrom, typer.Option("--render-from", help="grid: bake CuNeRF to a grid once, then render (fast). field: query CuNeRF's cube renders at every ray sample (slow; exact).")]
BakeSizeOption = Annotated[Optional[int], unset_option("--bake-size", "Grid side for --render-from grid (default: the volume's size).")]
SeedOption = Annotated[int, typer.Option("--seed", help="Seed of the point sampling.")]
NovelDirectionsOption = Annotated[int, typer.Option("--novel-directions", help="Directions of the novel-view test (from the head, from the feet, then fixed random ones), each rendered from the volume at magnifications 0.5, 0.75, 1, 1.33 and 2 with pixel-area references; eval scores every run on them. 0 for none.")]
CunerfNameOption = Annotated[Optional[str], unset_option("--cunerf-name", "Export WORK/cunerf-NAME/ instead of WORK/cunerf/.")]
NameOption = Annotated[Optional[str], unset_option("--name", "Write WORK/export-NAME/ instead of WORK/export/.")]


def export_settings(preset: str, **options) -> ExportSettings:
    """Preset values with every option that was given applied on top."""
    if options.get("cameras") == "stack" and options.get("axis") is None:
        options["axis"] = "lr"  # the paper's baseline: sagittal slices, whatever the preset's orbit axis
    preset_keys = PRESETS["export"][preset]
    values = resolve("export", preset, {k: v for k, v in options.items() if k in preset_keys})
    return ExportSettings(**values, **{k: v for k, v in options.items() if k not in preset_keys})


@reports_errors
def export_command(
    work: WorkArgument = Path("work"),
    preset: PresetOption = DEFAULT_PRESET_VALUE,
    cube: CubeOption = 16,
    points_per_cube: PointsPerCubeOption = None,
    max_points: MaxPointsOption = None,
    air_threshold: AirOption = 0.02,
    cameras: CamerasOption = None,
    views: ViewsOption = None,
    axis: AxisOption = None,
    radius: RadiusOption = 4.0,
    fov: FovOption = None,
    resolution: ResolutionOption = None,
    elevation: ElevationOption = 0.0,
    view: ViewOption = None,
    transfer: TransferOption = Transfer("tissue"),  # type: ignore[valid-type]
    tf_low: TfLowOption = None,
    tf_high: TfHighOption = None,
    tf_density: TfDensityOption = None,
    step: StepOption = 1.0,
    render_from: RenderFromOption = RenderFrom.grid,
    bake_size: BakeSizeOption = None,
    seed: SeedOption = 0,
    novel_directions: NovelDirectionsOption = DEFAULT_DIRECTIONS,
    device: DeviceOption = Device.auto,
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
    """
    configure_logging(quiet)
    settings = export_settings(
        preset.value,
        cube=cube, points_per_cube=points_per_cube, max_points=max_points, air_threshold=air_threshold,
        cameras=cameras.value if cameras else None, views=views, axis=axis.value if axis else None, radius=radius, fov=fov, resolution=resolution,
        elevation=elevation, view=view.value if view else None, transfer=transfer.value, tf_low=tf_low, tf_high=tf_high,
        tf_density=tf_density, step=step, render_from=render_from.value, bake_size=bake_size, seed=seed,
        novel_directions=novel_directions,
    )
    manifest = export_with_progress(work, settings, force, Runtime(device.value, threads), name, cunerf_name)
    log.info(f"wrote {Path(work) / stage_dir_name('export', name)}: {describe_export(manifest)}")


def describe_export(manifest: dict) -> str:
    metrics = manifest["metrics"]
    psnr = metrics.get("cunerf_vs_reference_psnr")
    psnr_text = f"{psnr:.2f} dB" if isinstance(psnr, (int, float)) else str(psnr)
    return (
        f"{metrics['views']} views ({metrics['test_views']} held out), {metrics['points']} points, "
        f"CuNeRF vs reference on test views {psnr_text}, {manifest['timings_s']['total']:.0f} s"
    )


def export_with_progress(work: Path, settings: ExportSettings, force: bool, runtime: Runtime,
                         name: str | None = None, cunerf_name: str | None = None) -> dict:
    """The stage with a bar over the rendered views (CuNeRF, reference, novel), with rate and ETA."""
    with stage_progress("export", unit="view") as on_progress:
        return export_scene(work, settings, force=force, runtime=runtime, name=name, cunerf_name=cunerf_name,
                            on_progress=on_progress)
