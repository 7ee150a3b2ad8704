"""`cubecloud run`: the whole pipeline with one command."""

from __future__ import annotations

import logging
from pathlib import Path

from cubecloud_cli.cli.common import (
    DEFAULT_PRESET_VALUE,
    ForceOption,
    PresetOption,
    QuietOption,
    ScanArgument,
    WorkOption,
    configure_logging,
    reports_errors,
)
from cubecloud_cli.cli.preprocess import (
    FitOption,
    HuMaxOption,
    HuMinOption,
    InterpolationOption,
    Modality,
    ModalityOption,
    PercentilesOption,
    SizeOption,
    SpacingOption,
    VolumeIndexOption,
    WindowOption,
    run_preprocess_with_progress,
    scan_or_sample,
    settings_from_options,
)
from cubecloud_cli.pipeline import run_pipeline

log = logging.getLogger("cubecloud")


@reports_errors
def run_command(
    scan: ScanArgument = None,
    output: WorkOption = Path("work"),
    preset: PresetOption = DEFAULT_PRESET_VALUE,
    size: SizeOption = None,
    fit: FitOption = None,
    window: WindowOption = None,
    hu_min: HuMinOption = None,
    hu_max: HuMaxOption = None,
    modality: ModalityOption = Modality.auto,
    percentiles: PercentilesOption = "0.5,99.5",
    interpolation: InterpolationOption = None,
    spacing: SpacingOption = None,
    volume_index: VolumeIndexOption = None,
    force: ForceOption = False,
    quiet: QuietOption = False,
) -> None:
    """Run every stage on a scan, skipping stages already complete with the same settings.

    Takes the options of `cubecloud preprocess`. Stages run today: preprocess (cunerf, export,
    splat and eval join as they land).

    Examples:

      cubecloud run -o work                       # the bundled abdomen CT, preset fast

      cubecloud run scan.nii.gz -o work --preset balanced
    """
    configure_logging(quiet)
    settings = settings_from_options(
        preset.value, size, fit, window, hu_min, hu_max, modality, percentiles, interpolation, spacing, volume_index
    )
    outcomes = run_pipeline(
        scan_or_sample(scan), output, settings, force=force, run_preprocess=run_preprocess_with_progress
    )
    for outcome in outcomes:
        when = f"{outcome.seconds:7.1f} s" if outcome.status == "ran" else "skipped (already complete)"
        log.info(f"  {outcome.stage:<12} {when}")
    log.info(f"  {'total':<12} {sum(o.seconds for o in outcomes):7.1f} s   results in {output}")
