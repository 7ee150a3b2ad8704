"""`cubecloud run`'s loop: the stages in order, skipping those already complete with the same
settings, resuming those interrupted, redoing those whose upstream stage was redone, running side
by side those that may (``side_by_side.py``) and compiling ahead what a later stage will compile
(``kernels_ahead.py``). It reads each stage through the contract of ``cubecloud_cli/core/stage.py``
only.
"""

from __future__ import annotations

import time
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from itertools import groupby
from pathlib import Path
from typing import Callable, ContextManager, Iterator

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.progress import ProgressCallback, no_progress
from cubecloud_cli.core.stage import Stage
from cubecloud_cli.pipeline.kernels_ahead import Warmup
from cubecloud_cli.pipeline.side_by_side import run_side_by_side, side_by_side_runs


@dataclass(frozen=True)
class StageOutcome:
    stage: str
    status: str  # "ran", "resumed" or "skipped"
    seconds: float


@contextmanager
def no_bars(stage: str) -> Iterator[ProgressCallback]:
    yield no_progress


def run_stages(
    stages: list[Stage],
    work: Path,
    *,
    force: bool = False,
    progress: Callable[[str], ContextManager[ProgressCallback]] = no_bars,
    on_stage: Callable[[StageOutcome], None] = lambda outcome: None,
) -> list[StageOutcome]:
    """Each stage in order: skipped if current, resumed if interrupted, run otherwise; splat runs
    that may train side by side do, when more than one of them has to run.
    ``progress(folder)`` gives the callback a stage reports to (a bar on the terminal).

    With more than one stage to run, the numba kernels of those that will run are compiled ahead
    in a helper at the lowest priority (``kernels_ahead.py``); a stage that compiles them waits for it."""
    outcomes: dict[str, StageOutcome] = {}
    together = side_by_side_runs(stages)
    warmup = Warmup.start(_kernels_ahead(stages, force))
    try:
        for group in _groups(stages, together):
            plans = {stage.folder: _plan(stage, outcomes, work, force) for stage in group}
            for stage in group:
                if plans[stage.folder] is None:
                    outcomes[stage.folder] = StageOutcome(stage.folder, "skipped", 0.0)
                    on_stage(outcomes[stage.folder])
            to_run = [stage for stage in group if plans[stage.folder] is not None]
            kernels_ready = False
            if any(stage.compile_ahead() is not None for stage in to_run):
                kernels_ready = warmup.wait()
            if len(to_run) > 1:
                jobs = [together[stage.folder] for stage in to_run]
                _run_together(jobs, plans, progress, outcomes, on_stage, staggered=not kernels_ready)
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


def _kernels_ahead(stages: list[Stage], force: bool) -> Callable[[], object] | None:
    """The kernels of the stages that will run, when there is a stage before them to hide their
    compilation behind (a single stage, as a workflow engine runs them, compiles its own)."""
    running: set[str] = set()
    job = None
    for stage in stages:
        if force or any(name in running for name in stage.upstream) or not _is_current_as_far_as_known(stage):
            running.add(stage.folder)
            job = job or stage.compile_ahead()  # the splat runs differ in their start only: one job serves all
    return job if len(running) > 1 else None


def _is_current_as_far_as_known(stage: Stage) -> bool:
    """``stage.is_current()``, where a stage made with other settings counts as not current: the
    stage loop raises that in its turn, after the stages before it."""
    try:
        return stage.is_current()
    except CubecloudError:
        return False


def _groups(stages: list[Stage], together: dict[str, Stage]) -> Iterator[list[Stage]]:
    """Consecutive stages that may train side by side together, every other stage alone."""
    for side_by_side, run in groupby(stages, key=lambda stage: stage.folder in together):
        yield from [list(run)] if side_by_side else ([stage] for stage in run)


def _plan(stage: Stage, outcomes: dict[str, StageOutcome], work: Path, force: bool) -> tuple[bool, bool] | None:
    """None when ``stage`` is current (skip it), else the (force, resume) to run it with."""
    # An upstream stage not in this run (a single --stage) was checked to be current.
    upstream_ran = force or any(name in outcomes and outcomes[name].status != "skipped" for name in stage.upstream)
    if not upstream_ran and stage.is_current():
        return None
    checkpoint = stage.checkpoint
    resume = not upstream_ran and checkpoint is not None and checkpoint.is_file()
    return upstream_ran or (Path(work) / stage.folder).exists(), resume


def _run_together(
    stages: list[Stage],
    plans: dict[str, tuple[bool, bool]],
    progress: Callable[[str], ContextManager[ProgressCallback]],
    outcomes: dict[str, StageOutcome],
    on_stage: Callable[[StageOutcome], None],
    staggered: bool = True,
) -> None:
    with ExitStack() as bars:
        jobs = [(stage, *plans[stage.folder], bars.enter_context(progress(stage.folder))) for stage in stages]
        results = run_side_by_side(jobs, staggered)
    for stage in stages:
        manifest, seconds = results[stage.folder]
        status = "resumed" if plans[stage.folder][1] or stage.resumed(manifest) else "ran"
        outcomes[stage.folder] = StageOutcome(stage.folder, status, seconds)
        on_stage(outcomes[stage.folder])


def only_stage(stages: list[Stage], folder: str) -> list[Stage]:
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
