"""`cubecloud preprocess`: options and the call into cubecloud_cli.preprocess."""

from __future__ import annotations

import logging
from pathlib import Path

from cubecloud_cli.cli.common import (
    FitOption,
    ForceOption,
    HuMaxOption,
    HuMinOption,
    InterpolationOption,
    ModalityOption,
    PercentilesOption,
    PresetOption,
    QuietOption,
    ScanArgument,
    SeriesOption,
    SizeOption,
    SpacingOption,
    VolumeIndexOption,
    WindowOption,
    WorkOption,
    configure_logging,
    preprocess_settings,
    reports_errors,
    scan_or_sample,
)
from cubecloud_cli.cli.progress_bar import stage_bar
from cubecloud_cli.presets import DEFAULT_PRESET

log = logging.getLogger("cubecloud")


@reports_errors
def preprocess_command(
    scan: ScanArgument = None,
    output: WorkOption = Path("work"),
    preset: PresetOption = DEFAULT_PRESET,
    size: SizeOption = None,
    fit: FitOption = None,
    window: WindowOption = None,
    hu_min: HuMinOption = None,
    hu_max: HuMaxOption = None,
    modality: ModalityOption = None,
    percentiles: PercentilesOption = None,
    interpolation: InterpolationOption = None,
    spacing: SpacingOption = None,
    volume_index: VolumeIndexOption = None,
    series: SeriesOption = None,
    force: ForceOption = False,
    quiet: QuietOption = False,
) -> None:
    """Normalize a CT or MR scan into the cube volume every later stage reads.

    Reorients to RAS+, clips to an intensity window, maps it to [0, 1] and resamples to an isotropic S³ cube. Writes WORK/preprocess/: volume.npy (float32), volume.nii.gz (lies over the original scan in 3D Slicer or ITK-SNAP), preview.png and manifest.json.

    Examples:

      cubecloud preprocess -o work                      # the bundled abdomen CT

      cubecloud preprocess scan.nii.gz -o work --size 256 --window bone

      cubecloud preprocess dicom_folder/ -o work --hu-min -1000 --hu-max 1000

      cubecloud preprocess array.npy -o work --spacing 0.7,0.7,2.5
    """
    configure_logging(quiet)
    settings = preprocess_settings(
        preset,
        size=size,
        fit=fit,
        window=window,
        hu_min=hu_min,
        hu_max=hu_max,
        modality=modality,
        percentiles=percentiles,
        interpolation=interpolation,
        spacing=spacing,
        volume_index=volume_index,
        series=series,
    )
    from cubecloud_cli.preprocess.stage import preprocess_scan  # imported when the stage runs

    with stage_bar("preprocess") as on_progress:
        manifest = preprocess_scan(scan_or_sample(scan), output, settings, force=force, on_progress=on_progress)
    log.info(describe_result(manifest, output))


def describe_result(manifest: dict, work: Path) -> str:
    geometry = manifest["geometry"]
    size = geometry["size"]
    voxel = "×".join(f"{v:.3g}" for v in geometry["voxel_size_mm"])
    return (
        f"wrote {work / 'preprocess'}: {size}³ volume, {voxel} mm voxels, "
        f"{manifest['intensity']['method']}, {manifest['timings_s']['total']:.1f} s"
    )
