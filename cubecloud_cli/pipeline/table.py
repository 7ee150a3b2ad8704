"""`cubecloud run`'s stages: preprocess → cunerf → export → splat (Cube-Cloud initialisation) →
splat-random (the paper's baseline: the same training from random points) → eval, each a
:class:`~cubecloud_cli.core.stage.Stage` of its own package."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Callable, ContextManager

from cubecloud_cli.core.progress import ProgressCallback
from cubecloud_cli.core.runtime import Runtime
from cubecloud_cli.core.stage import Stage
from cubecloud_cli.cunerf.settings import CunerfSettings
from cubecloud_cli.cunerf.stage import CunerfStage
from cubecloud_cli.eval.settings import EvalSettings
from cubecloud_cli.eval.stage import EvalStage
from cubecloud_cli.export.settings import ExportSettings
from cubecloud_cli.export.stage import ExportStage
from cubecloud_cli.pipeline.runner import StageOutcome, no_bars, run_stages
from cubecloud_cli.preprocess.settings import PreprocessSettings
from cubecloud_cli.preprocess.stage import PreprocessStage
from cubecloud_cli.splat.settings import SplatSettings
from cubecloud_cli.splat.stage import SplatStage

BASELINE_NAME = "random"


def stage_table(
    scan: Path,
    work: Path,
    preprocess: PreprocessSettings,
    cunerf: CunerfSettings,
    export: ExportSettings,
    splat: SplatSettings,
    evaluation: EvalSettings,
    runtime: Runtime,
    baseline: bool = True,
) -> list[Stage]:
    """The stages of a pipeline over ``scan`` in ``work``, in order (the random-init baseline too,
    unless ``baseline`` is False)."""
    work = Path(work)
    stages: list[Stage] = [
        PreprocessStage(Path(scan), work, preprocess, runtime),
        CunerfStage(work, cunerf, runtime),
        ExportStage(work, export, runtime),
        SplatStage(work, splat, runtime),
    ]
    if baseline:
        stages.append(SplatStage(work, replace(splat, init="random"), runtime, name=BASELINE_NAME))
    stages.append(EvalStage(work, evaluation, runtime, upstream=tuple(stage.folder for stage in stages)))
    return stages


def run_pipeline(
    scan: Path,
    work: Path,
    preprocess_settings: PreprocessSettings,
    cunerf_settings: CunerfSettings,
    export_settings: ExportSettings = ExportSettings(),
    splat_settings: SplatSettings = SplatSettings(),
    *,
    eval_settings: EvalSettings = EvalSettings(),
    force: bool = False,
    runtime: Runtime = Runtime(),
    baseline: bool = True,
    progress: Callable[[str], ContextManager[ProgressCallback]] = no_bars,
    on_stage: Callable[[StageOutcome], None] = lambda outcome: None,
) -> list[StageOutcome]:
    """Every stage on a scan, for scripts: what `cubecloud run` does."""
    stages = stage_table(
        scan,
        work,
        preprocess_settings,
        cunerf_settings,
        export_settings,
        splat_settings,
        eval_settings,
        runtime,
        baseline,
    )
    return run_stages(stages, work, force=force, progress=progress, on_stage=on_stage)
