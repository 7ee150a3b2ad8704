"""`cubecloud run`: the stages in order, skipping those already complete with the same settings.

preprocess → cunerf → export → splat (Cube-Cloud initialisation) → splat-random (the paper's
baseline: the same training from random points) → eval.
"""

from __future__ import annotations

import json
import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, replace
from itertools import groupby
from pathlib import Path
from typing import Callable, ContextManager, Iterator

from cubecloud_cli.core.artifacts import PARTIAL_SUFFIX, is_complete, read_manifest, sha256_of_path
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.progress import ProgressCallback, no_progress
from cubecloud_cli.core.runtime import Runtime, resolve_device
from cubecloud_cli.cunerf import CunerfSettings, train_cunerf
from cubecloud_cli.cunerf import stage as cunerf_stage
from cubecloud_cli.eval import EvalSettings, evaluate_work
from cubecloud_cli.eval.stage import eval_is_current
from cubecloud_cli.export import ExportSettings, export_scene
from cubecloud_cli.export import stage as export_stage
from cubecloud_cli.pipeline.kernels_ahead import MIN_ITERATIONS as WARMUP_MIN_ITERATIONS
from cubecloud_cli.pipeline.kernels_ahead import Warmup, WarmupJob
from cubecloud_cli.pipeline.side_by_side import SplatJob, available_cores, run_side_by_side, threads_each
from cubecloud_cli.preprocess import PreprocessSettings, preprocess_scan
from cubecloud_cli.preprocess import stage as preprocess_stage
from cubecloud_cli.splat import stage as splat_stage
from cubecloud_cli.splat.settings import SplatSettings
from cubecloud_cli.splat.stage import train_splat


@dataclass(frozen=True)
class StageOutcome:
    stage: str
    status: str  # "ran", "resumed" or "skipped"
    seconds: float


# Parameters added after stages were first written, with the value that older manifests implied,
# so that `run` does not refuse a work directory made before they existed.
ADDED_PARAMETERS = {"cameras": "orbit", "novel_directions": 0, "antialias": False, "grid_init": "random"}
# Parameters recorded for provenance only: the scene a splat run read is identified by its files'
# hashes, so `-o work` and `-o /abs/work` (or a moved work directory) are the same stage.
PROVENANCE_PARAMETERS = {"scene"}


def _differences(recorded: dict, requested: dict) -> list[str]:
    # A JSON round trip makes tuples lists, as they are in the manifest.
    requested = json.loads(json.dumps(requested))
    recorded = {**{k: v for k, v in ADDED_PARAMETERS.items() if k in requested}, **recorded}
    keys = sorted((set(recorded) | set(requested)) - PROVENANCE_PARAMETERS)
    return [f"{k}: {recorded.get(k)!r} -> {requested.get(k)!r}" for k in keys if recorded.get(k) != requested.get(k)]


def stage_is_current(stage_dir: Path, params: dict, input_paths: list[Path]) -> bool:
    """True when ``stage_dir`` is complete, made with ``params``, from these very inputs.

    A complete stage made otherwise raises: silently redoing it would discard work, silently
    keeping it would mix settings.
    """
    if not is_complete(stage_dir):
        return False
    manifest = read_manifest(stage_dir)
    changes = _differences(manifest.get("params", {}), params)
    recorded_hashes = set(manifest.get("inputs", {}).values())
    for path in input_paths:
        if sha256_of_path(path) not in recorded_hashes:
            # The first stage reads the scan; later ones read files of the stages before them.
            changes.append(
                "the input scan differs"
                if stage_dir.name == "preprocess"
                else f"its input {path.parent.name}/{path.name} changed"
            )
    if changes:
        raise CubecloudError(
            f"{stage_dir} was made with other settings ({'; '.join(changes)}): pass --force to "
            f"redo it, or choose another -o"
        )
    return True


@dataclass(frozen=True)
class PipelineStage:
    """One row of the stage table: whether WORK/folder is current, and how to make it again.

    A stage is redone when a stage it reads from (``upstream``) was, and resumed when it left
    saved work behind and nothing upstream changed.
    """

    folder: str
    upstream: tuple[str, ...]
    is_current: Callable[[], bool]
    run: Callable[[bool, bool, ProgressCallback], dict]  # (force, resume, on_progress) -> manifest
    checkpoint: Path | None = None  # saved work of an interrupted run, resumed when present
    side_by_side: SplatJob | None = None  # set on the splat runs that train side by side when both run
    compiles: WarmupJob | None = None  # its numba kernels, compiled ahead by `run_stages` (long CPU splat runs)
    resumed: Callable[[dict], bool] = lambda manifest: False  # whether the run reused saved work anyway


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
) -> list[PipelineStage]:
    """preprocess → cunerf → export → splat runs → eval, each with what makes it current.

    Long on purpose: one row per stage, so the whole pipeline and its dependencies read in one place."""
    work = Path(work)
    on_cpu = resolve_device(runtime.device).type == "cpu"

    def compiles(settings: SplatSettings) -> WarmupJob | None:
        """The rasterizer's kernels, for a CPU run long enough to repay a helper process."""
        return WarmupJob(splat=settings) if on_cpu and settings.iterations >= WARMUP_MIN_ITERATIONS else None

    def current(folder: str, params: dict, inputs: list[Path]) -> Callable[[], bool]:
        return lambda: stage_is_current(work / folder, params, inputs)

    def checkpoint(folder: str, file: str) -> Path:
        return work / f".{folder}{PARTIAL_SUFFIX}" / file

    stages = [
        PipelineStage(
            "preprocess",
            (),
            current("preprocess", preprocess_stage.recorded_params(preprocess), [Path(scan)]),
            lambda force, resume, on_progress: preprocess_scan(
                scan, work, preprocess, force=force, on_progress=on_progress
            ),
        ),
        PipelineStage(
            "cunerf",
            ("preprocess",),
            current("cunerf", cunerf.as_dict(), cunerf_stage.input_files(work)),
            lambda force, resume, on_progress: train_cunerf(
                work, cunerf, force=force, resume=resume, runtime=runtime, on_progress=on_progress
            ),
            checkpoint=checkpoint("cunerf", cunerf_stage.CHECKPOINT_FILE),
        ),
        PipelineStage(
            "export",
            ("cunerf",),
            current("export", export_stage.recorded_params(export), export_stage.input_files(work)),
            lambda force, resume, on_progress: export_scene(
                work, export, force=force, runtime=runtime, on_progress=on_progress
            ),
            resumed=export_stage.resumed_views,
        ),
    ]
    runs = [("splat", None, splat)] + (
        [(f"splat-{BASELINE_NAME}", BASELINE_NAME, replace(splat, init="random"))] if baseline else []
    )
    threads = threads_each(runtime, splat, len(runs), available_cores())
    for folder, name, settings in runs:
        stages.append(
            PipelineStage(
                folder,
                ("export",),
                current(
                    folder,
                    splat_stage.recorded_params(settings, work / "export"),
                    splat_stage.input_files(work / "export"),
                ),
                lambda force, resume, on_progress, settings=settings, name=name: train_splat(
                    work, settings, force=force, resume=resume, runtime=runtime, name=name, on_progress=on_progress
                ),
                checkpoint=checkpoint(folder, splat_stage.CHECKPOINT_FILE),
                side_by_side=None
                if threads is None
                else SplatJob(work, settings, replace(runtime, threads=threads), name),
                compiles=compiles(settings),
            )
        )
    # eval is cheap and holds no choices worth protecting: one made with other settings or of
    # other runs (a splat-NAME/ the user trained beside them) is simply redone, never refused.
    stages.append(
        PipelineStage(
            "eval",
            tuple(stage.folder for stage in stages),
            lambda: eval_is_current(work, evaluation),
            lambda force, resume, on_progress: evaluate_work(
                work, evaluation, force=force, runtime=runtime, on_progress=on_progress
            ),
        )
    )
    return stages


@contextmanager
def _silent(stage: str) -> Iterator[ProgressCallback]:
    yield no_progress


def run_stages(
    stages: list[PipelineStage],
    work: Path,
    *,
    force: bool = False,
    progress: Callable[[str], ContextManager[ProgressCallback]] = _silent,
    on_stage: Callable[[StageOutcome], None] = lambda outcome: None,
) -> list[StageOutcome]:
    """Each stage in order: skipped if current, resumed if interrupted, run otherwise; splat runs
    marked ``side_by_side`` train together when more than one of them has to run.
    ``progress(folder)`` gives the callback a stage reports to (a bar on the terminal).

    With more than one stage to run, the numba kernels of those that will run are compiled ahead
    in a helper at the lowest priority (``cubecloud_cli/pipeline/kernels_ahead.py``); a splat stage waits for it."""
    outcomes: dict[str, StageOutcome] = {}
    warmup = Warmup.start(_kernels_ahead(stages, force))
    try:
        for group in _groups(stages):
            plans = {stage.folder: _plan(stage, outcomes, work, force) for stage in group}
            for stage in group:
                if plans[stage.folder] is None:
                    outcomes[stage.folder] = StageOutcome(stage.folder, "skipped", 0.0)
                    on_stage(outcomes[stage.folder])
            to_run = [stage for stage in group if plans[stage.folder] is not None]
            kernels_ready = False
            if any(stage.compiles is not None for stage in to_run):
                kernels_ready = warmup.wait()
            if len(to_run) > 1:
                _run_together(to_run, plans, progress, outcomes, on_stage, staggered=not kernels_ready)
                continue
            for stage in to_run:
                start = time.perf_counter()
                stage_force, resume = plans[stage.folder]
                with progress(stage.folder) as on_progress:
                    manifest = stage.run(stage_force, resume, on_progress)
                status = "resumed" if resume or stage.resumed(manifest) else "ran"
                outcomes[stage.folder] = StageOutcome(stage.folder, status, time.perf_counter() - start)
                on_stage(outcomes[stage.folder])
    finally:
        warmup.stop()
    return list(outcomes.values())


def _kernels_ahead(stages: list[PipelineStage], force: bool) -> WarmupJob | None:
    """The kernels of the stages that will run, when there is a stage before them to hide their
    compilation behind (a single stage, as a workflow engine runs them, compiles its own)."""
    running: set[str] = set()
    job = None
    for stage in stages:
        if force or any(name in running for name in stage.upstream) or not _is_current_as_far_as_known(stage):
            running.add(stage.folder)
            job = job or stage.compiles  # the splat runs differ in their start only: one job serves all
    return job if len(running) > 1 else None


def _is_current_as_far_as_known(stage: PipelineStage) -> bool:
    """``stage.is_current()``, where a stage made with other settings counts as not current: the
    stage loop raises that in its turn, after the stages before it."""
    try:
        return stage.is_current()
    except CubecloudError:
        return False


def _groups(stages: list[PipelineStage]) -> Iterator[list[PipelineStage]]:
    """Consecutive side-by-side stages together, every other stage alone."""
    for together, run in groupby(stages, key=lambda stage: stage.side_by_side is not None):
        yield from [list(run)] if together else ([stage] for stage in run)


def _plan(stage: PipelineStage, outcomes: dict[str, StageOutcome], work: Path, force: bool) -> tuple[bool, bool] | None:
    """None when ``stage`` is current (skip it), else the (force, resume) to run it with."""
    # An upstream stage not in this run (a single --stage) was checked to be current.
    upstream_ran = force or any(name in outcomes and outcomes[name].status != "skipped" for name in stage.upstream)
    if not upstream_ran and stage.is_current():
        return None
    resume = not upstream_ran and stage.checkpoint is not None and stage.checkpoint.is_file()
    return upstream_ran or (Path(work) / stage.folder).exists(), resume


def _run_together(
    stages: list[PipelineStage],
    plans: dict[str, tuple[bool, bool]],
    progress: Callable[[str], ContextManager[ProgressCallback]],
    outcomes: dict[str, StageOutcome],
    on_stage: Callable[[StageOutcome], None],
    staggered: bool = True,
) -> None:
    with ExitStack() as bars:
        jobs = [
            (stage.folder, stage.side_by_side, *plans[stage.folder], bars.enter_context(progress(stage.folder)))
            for stage in stages
        ]
        results = run_side_by_side(jobs, staggered)
    for stage in stages:
        manifest, seconds = results[stage.folder]
        status = "resumed" if plans[stage.folder][1] or stage.resumed(manifest) else "ran"
        outcomes[stage.folder] = StageOutcome(stage.folder, status, seconds)
        on_stage(outcomes[stage.folder])


def only_stage(stages: list[PipelineStage], folder: str) -> list[PipelineStage]:
    """The one stage ``folder`` of the table, once every stage it reads from is complete and
    current: what a workflow engine runs as one job."""
    by_folder = {stage.folder: stage for stage in stages}
    if folder not in by_folder:
        raise CubecloudError(f"--stage {folder!r} must be one of {', '.join(by_folder)}")
    for upstream in by_folder[folder].upstream:
        if not by_folder[upstream].is_current():
            raise CubecloudError(
                f"stage {folder} reads {upstream}, which is missing, unfinished or made with other settings: "
                f"run `--stage {upstream}` first"
            )
    return [by_folder[folder]]


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
    progress: Callable[[str], ContextManager[ProgressCallback]] = _silent,
    on_stage: Callable[[StageOutcome], None] = lambda outcome: None,
) -> list[StageOutcome]:
    """Every stage on a scan (the random-init baseline too, unless ``baseline`` is False)."""
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
