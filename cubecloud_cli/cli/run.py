"""`cubecloud run`: the whole pipeline with one command."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Annotated, Optional

import typer

from cubecloud_cli.cli.common import (
    DeviceOption,
    FitOption,
    ForceOption,
    HuMaxOption,
    HuMinOption,
    InterpolationOption,
    ModalityOption,
    PercentilesOption,
    PresetOption,
    QuietOption,
    ResolutionOption,
    ScanArgument,
    SeriesOption,
    SizeOption,
    SpacingOption,
    ThreadsOption,
    ViewOption,
    ViewsOption,
    VolumeIndexOption,
    WindowOption,
    WorkOption,
    configure_logging,
    preprocess_settings,
    reports_errors,
    runtime_from_options,
    scan_or_sample,
)
from cubecloud_cli.cli.cunerf import describe_metrics
from cubecloud_cli.cli.export import describe_export
from cubecloud_cli.cli.options import build_settings, settings_option
from cubecloud_cli.cli.progress_bar import PipelineProgress, stage_bar
from cubecloud_cli.cli.splat import describe_splat
from cubecloud_cli.core.artifacts import read_manifest
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.cunerf.precision import Precision
from cubecloud_cli.cunerf.settings import CunerfSettings
from cubecloud_cli.eval.settings import EvalSettings
from cubecloud_cli.export.settings import ExportSettings
from cubecloud_cli.presets import DEFAULT_PRESET, resolve_scalar_run, scalar_run_note
from cubecloud_cli.splat.settings import SplatSettings

log = logging.getLogger("cubecloud")


@reports_errors
def run_command(
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
    cunerf_iterations: Annotated[
        Optional[int], settings_option(CunerfSettings, "iterations", "--cunerf-iterations")
    ] = None,
    cunerf_precision: Annotated[
        Optional[Precision], settings_option(CunerfSettings, "precision", "--cunerf-precision")
    ] = None,
    splat_iterations: Annotated[
        Optional[int], settings_option(SplatSettings, "iterations", "--splat-iterations")
    ] = None,
    views: ViewsOption = None,
    resolution: ResolutionOption = None,
    view: ViewOption = None,
    device: DeviceOption = None,
    threads: ThreadsOption = None,
    scalar: Annotated[
        bool,
        typer.Option(
            "--scalar",
            help="Train one scalar scene (`splat --scalar`) under a set of transfer functions, instead of the baked "
            "scene and its random-init baseline, so the scene shows any tissue in `view` without retraining; eval "
            f"scores it under transfer functions it never saw. {scalar_run_note()} Preprocess with a window "
            "that keeps every tissue, such as --hu-min -1000 --hu-max 1000.",
        ),
    ] = False,
    stage: Annotated[
        Optional[str],
        typer.Option(
            "--stage",
            help="Run only this stage (preprocess, cunerf, export, splat, splat-random or eval), once the stages "
            "it reads are complete and current: one job of `cubecloud cohort`.",
            show_default=False,
        ),
    ] = None,
    force: ForceOption = False,
    quiet: QuietOption = False,
) -> None:
    """Run every stage on a scan, skipping stages already complete with the same settings.

    Takes the options of `cubecloud preprocess`; --preset also sets the cunerf, export and splat stages. Stages: preprocess, cunerf, export, splat (Cube-Cloud init), splat-random (the paper's baseline, random init), eval; with --scalar, one scalar splat run and no baseline. On a CPU the two splat runs train side by side, each on its share of the cores, unless --threads is given. An interrupted cunerf, export or splat stage continues from its saved work. Ends with each stage's time and the table of eval/report.md, headed by the novel-view score.

    Examples:

      cubecloud run -o work            # bundled CT, preset fast (about 4 min on 2 cores)

      cubecloud run scan.nii.gz -o work --preset balanced

      cubecloud run -o scalar --scalar --hu-min -1000 --hu-max 1000   # one scene for every tissue
    """
    configure_logging(quiet)
    preprocess = preprocess_settings(
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
    from cubecloud_cli.pipeline.runner import only_stage, run_stages  # the stages: torch
    from cubecloud_cli.pipeline.table import stage_table

    cunerf = build_settings(CunerfSettings, preset, {"iterations": cunerf_iterations, "precision": cunerf_precision})
    export_options = {"views": views, "resolution": resolution, "view": view}
    splat_options = {"iterations": splat_iterations}
    if scalar:
        export_options, splat_options = _scalar_options(preset, export_options, splat_options)
    export = build_settings(ExportSettings, preset, export_options)
    splat = build_settings(SplatSettings, preset, splat_options)
    if scalar:
        _check_scalar_run(output, export, splat)
    stages = stage_table(
        scan_or_sample(scan),
        output,
        preprocess,
        cunerf,
        export,
        splat,
        EvalSettings(),
        runtime_from_options(device, threads),
        baseline=not scalar,
    )
    if stage is not None:
        stages = only_stage(stages, stage)
    started = time.perf_counter()
    with PipelineProgress(len(stages), "run " + " → ".join(s.folder for s in stages)) as display:
        outcomes = run_stages(
            stages,
            output,
            force=force,
            progress=stage_bar,
            on_stage=lambda outcome: _stage_done(display, outcome, output, preset),
        )
    _report(outcomes, output, time.perf_counter() - started, whole=stage is None)


def _scalar_options(preset: str, export: dict, splat: dict) -> tuple[dict, dict]:
    try:
        return resolve_scalar_run(preset, "export", export), resolve_scalar_run(preset, "splat", splat)
    except ValueError as exc:
        raise CubecloudError(
            f"{exc}: use --preset fast, or run export --transfer-set and splat --scalar yourself (README)"
        ) from None


def _check_scalar_run(output: Path, export: ExportSettings, splat: SplatSettings) -> None:
    """Refuse, before any stage runs, what would fail only after preprocess and cunerf: settings
    the scalar set does not fit (a --view or --views it cannot use), and a baked baseline in the
    work directory, which eval would score beside the scalar scene."""
    from cubecloud_cli.pipeline.table import BASELINE_NAME

    export.validate()
    splat.validate()
    baseline = Path(output) / f"splat-{BASELINE_NAME}"
    if baseline.exists():
        raise CubecloudError(
            f"{baseline} is the baseline of a baked run, which eval would score beside the scalar scene: "
            "run --scalar in another -o, or remove that folder"
        )


def _stage_done(display, outcome, output: Path, preset: str) -> None:
    display.stage_done(outcome.stage, outcome.status)
    if outcome.stage == "preprocess" and preset == "detail":
        from cubecloud_cli.pipeline.cost import describe_cost

        size = int(read_manifest(Path(output) / "preprocess")["volume"]["shape"][0])
        line = describe_cost(size)
        if line:
            log.info(line)


def _report(outcomes: list, output: Path, wall_seconds: float, whole: bool = True) -> None:
    for outcome in outcomes:
        when = f"{outcome.seconds:7.1f} s" if outcome.status != "skipped" else "skipped (already complete)"
        note = "  (resumed from its saved work)" if outcome.status == "resumed" else ""
        log.info(f"  {outcome.stage:<12} {when}{note}")
    # The wall time, not the stages' sum: the splat runs may have trained side by side.
    log.info(f"  {'total':<12} {wall_seconds:7.1f} s   results in {output}")
    if not whole:
        return
    log.info(f"cunerf: {describe_metrics(read_manifest(Path(output) / 'cunerf'))}")
    log.info(f"export: {describe_export(read_manifest(Path(output) / 'export'))}")
    log.info(f"splat: {describe_splat(read_manifest(Path(output) / 'splat'))}")
    if (Path(output) / "splat-random").is_dir():  # not after run --scalar, which trains no baseline
        log.info(f"splat-random: {describe_splat(read_manifest(Path(output) / 'splat-random'))}")
    results = json.loads((Path(output) / "eval" / "metrics.json").read_text())["results"]
    from cubecloud_cli.eval.outputs import held_out_transfer_results, held_out_transfer_table, table_rows

    table = "\n".join(table_rows(results))
    log.info(
        f"novel and held-out views against the volume's reference renders ({Path(output) / 'eval' / 'report.md'}):\n{table}"
    )
    transferred, not_scored = held_out_transfer_results(results)
    if transferred:  # a scalar scene: what it shows under the tissue it never trained on
        lines = held_out_transfer_table(transferred, not_scored)
        header = next((index for index, line in enumerate(lines) if line.startswith("|")), 0)
        table = "\n".join(lines[header:])  # report.md's table without its heading and prose
        log.info(f"transfer functions it never trained under, novel views 0.75–1.33×:\n{table}")
