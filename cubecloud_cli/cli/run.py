"""`cubecloud run`: the whole pipeline with one command."""

from __future__ import annotations

import inspect
import json
import logging
from pathlib import Path
from typing import Annotated, Optional

import typer

from cubecloud_cli.artifacts import read_manifest
from cubecloud_cli.cli.cunerf import Device, describe_metrics, train_cunerf_with_progress
from cubecloud_cli.cli.export import View, describe_export, export_settings, export_with_progress
from cubecloud_cli.cli.eval import evaluate_with_progress
from cubecloud_cli.cli.splat import describe_splat, splat_settings, train_splat_with_progress
from cubecloud_cli.eval.report import table_rows
from cubecloud_cli.cli.preprocess import run_preprocess_with_progress, scan_command
from cubecloud_cli.cunerf import CunerfSettings, Runtime
from cubecloud_cli.pipeline import run_pipeline
from cubecloud_cli.preprocess import PreprocessSettings
from cubecloud_cli.presets import preset_note, resolve_cunerf
from cubecloud_cli.cli.progress import PipelineProgress

log = logging.getLogger("cubecloud")


def _option(name: str, annotation, default) -> inspect.Parameter:
    return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=annotation)


RUN_OPTIONS = [
    _option("cunerf_iterations", Annotated[Optional[int], typer.Option("--cunerf-iterations", help=f"Training iterations of the cunerf stage. {preset_note('cunerf', 'iterations')}", show_default=False)], None),
    _option("splat_iterations", Annotated[Optional[int], typer.Option("--splat-iterations", help=f"Training iterations of the splat stage. {preset_note('splat', 'iterations')}", show_default=False)], None),
    _option("views", Annotated[Optional[int], typer.Option("--views", help=f"Training cameras of the export stage (the paper: 60). {preset_note('export', 'views')}", show_default=False)], None),
    _option("resolution", Annotated[Optional[int], typer.Option("--resolution", help=f"Width and height of the exported images. {preset_note('export', 'resolution')}", show_default=False)], None),
    _option("view", Annotated[Optional[View], typer.Option("--view", help=f"Image model of the exported views: dvr, slice (the paper's) or mip. {preset_note('export', 'view')}", show_default=False)], None),
    _option("device", Annotated[Device, typer.Option("--device", help="auto (CUDA when available), cpu or cuda, for cunerf and export.")], Device.auto),
    _option("threads", Annotated[Optional[int], typer.Option("--threads", help="CPU threads for torch (default: torch's choice).", show_default=False)], None),
]


def _run(scan: Path, output: Path, settings: PreprocessSettings, force: bool, preset: str, extras: dict) -> None:
    cunerf_settings = CunerfSettings(**resolve_cunerf(preset, None, {"iterations": extras["cunerf_iterations"]}))
    export = export_settings(preset, views=extras["views"], resolution=extras["resolution"], view=extras["view"].value if extras["view"] else None)
    splat = splat_settings(preset, iterations=extras["splat_iterations"])
    with PipelineProgress(len(RUN_STAGES), "run " + " → ".join(RUN_STAGES)) as display:
        outcomes = _run_stages(scan, output, settings, force, extras, cunerf_settings, export, splat, display)
    _report(outcomes, output)


RUN_STAGES = ("preprocess", "cunerf", "export", "splat", "splat-random", "eval")


def _run_stages(scan, output, settings, force, extras, cunerf_settings, export, splat, display) -> list:
    return run_pipeline(
        scan,
        output,
        settings,
        cunerf_settings,
        export,
        splat,
        force=force,
        runtime=Runtime(extras["device"].value, extras["threads"]),
        run_preprocess=run_preprocess_with_progress,
        run_cunerf=lambda work, s, f, resume, runtime: train_cunerf_with_progress(work, s, f, resume, runtime),
        run_export=lambda work, s, f, runtime: export_with_progress(work, s, f, runtime),
        run_splat=lambda work, s, f, resume, runtime, name: train_splat_with_progress(work, s, None, f, resume, runtime, name),
        run_eval=lambda work, s, f, runtime: evaluate_with_progress(work, s, f, runtime),
        on_stage=lambda outcome: display.stage_done(outcome.stage, outcome.status),
    )


def _report(outcomes: list, output: Path) -> None:
    for outcome in outcomes:
        when = f"{outcome.seconds:7.1f} s" if outcome.status != "skipped" else "skipped (already complete)"
        note = "  (resumed from its saved work)" if outcome.status == "resumed" else ""
        log.info(f"  {outcome.stage:<12} {when}{note}")
    log.info(f"  {'total':<12} {sum(o.seconds for o in outcomes):7.1f} s   results in {output}")
    log.info(f"cunerf: {describe_metrics(read_manifest(Path(output) / 'cunerf'))}")
    log.info(f"export: {describe_export(read_manifest(Path(output) / 'export'))}")
    log.info(f"splat: {describe_splat(read_manifest(Path(output) / 'splat'))}")
    log.info(f"splat-random: {describe_splat(read_manifest(Path(output) / 'splat-random'))}")
    results = json.loads((Path(output) / "eval" / "metrics.json").read_text())["results"]
    table = "\n".join(table_rows(results))
    log.info(f"novel and held-out views against the volume's reference renders ({Path(output) / 'eval' / 'report.md'}):\n{table}")


run_command = scan_command(
    _run,
    """Run every stage on a scan, skipping stages already complete with the same settings.

    Takes the options of `cubecloud preprocess`; --preset also sets the cunerf, export and splat stages. Stages: preprocess, cunerf, export, splat (Cube-Cloud init), splat-random (the paper's baseline, random init), eval. An interrupted cunerf, export or splat stage continues from its saved work. Ends with each stage's time and the table of eval/report.md, headed by the novel-view score.

    Examples:

      cubecloud run -o work            # bundled CT, preset fast (about 6 min on 2 cores)

      cubecloud run scan.nii.gz -o work --preset balanced
    """,
    RUN_OPTIONS,
)
