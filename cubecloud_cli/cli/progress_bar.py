"""Progress on the terminal: a bar with rate, elapsed time, ETA and live fields (loss, PSNR).

Stage code stays free of terminal concerns: it calls a plain callback
(cubecloud_cli/core/progress.py), and the command line decides whether to draw (only when stderr is
a terminal and the run is not --quiet, so logs and CI output stay clean).
"""

from __future__ import annotations

import logging
import sys
from contextlib import contextmanager
from types import TracebackType
from typing import ContextManager, Iterator

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskProgressColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text

from cubecloud_cli.core.progress import ProgressCallback, ProgressFields


def terminal_wants_progress() -> bool:
    return sys.stderr.isatty() and logging.getLogger("cubecloud").getEffectiveLevel() <= logging.INFO


class _Counts(MofNCompleteColumn):
    """M/N, for tasks counted in units (a bar in arbitrary work units hides it)."""

    def render(self, task) -> Text:
        return super().render(task) if task.fields.get("counts", True) else Text("")


def _columns() -> tuple:
    """Fresh column objects for each display (rich columns may cache per-task state)."""
    return (
        TextColumn("{task.description}"),
        BarColumn(),
        _Counts(),
        TaskProgressColumn(),
        TextColumn("{task.fields[rate]}"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[status]}"),
    )


_shared: Progress | None = None  # the display of a whole pipeline, when one is open


class PipelineProgress:
    """One display for a whole pipeline: a line for the stages done so far, and under it the bar
    of the stage running now (each ``ProgressBar`` opened meanwhile joins this display)."""

    def __init__(self, stages: int, description: str = "run", enabled: bool | None = None):
        self.enabled = terminal_wants_progress() if enabled is None else enabled
        self.stages = stages
        self.description = description
        self._progress: Progress | None = None
        self._task = None

    def __enter__(self) -> "PipelineProgress":
        global _shared
        if self.enabled:
            self._progress = Progress(*_columns(), console=Console(stderr=True), transient=False)
            self._progress.__enter__()
            self._task = self._progress.add_task(self.description, total=self.stages, rate="", status="")
            _shared = self._progress
        return self

    def stage_done(self, stage: str, status: str) -> None:
        if self._progress is not None:
            self._progress.update(self._task, advance=1, status=f"{stage} {status}")

    def __exit__(self, *exc_info) -> None:
        global _shared
        if self._progress is not None:
            _shared = None
            self._progress.__exit__(*exc_info)


class ProgressBar:
    """``with ProgressBar(total, "training") as bar: bar.advance(1, loss=0.1)``; silent when disabled."""

    def __init__(self, total: float, description: str, unit: str | None = "it", enabled: bool | None = None):
        """``unit=None`` hides the rate and the M/N count (for bars in arbitrary work units)."""
        # Inside a pipeline's display, stderr is rich's proxy, which is no terminal: the display
        # being open already says that the terminal wants progress.
        self.enabled = (_shared is not None or terminal_wants_progress()) if enabled is None else enabled
        self.total = total
        self.description = description
        self.unit = unit
        self._progress: Progress | None = None
        self._task = None

    def __enter__(self) -> "ProgressBar":
        self._owned = False
        if self.enabled and _shared is not None:
            self._progress = _shared
        elif self.enabled:
            self._progress = Progress(*_columns(), console=Console(stderr=True), transient=False)
            self._progress.__enter__()
            self._owned = True
        if self._progress is not None:
            self._task = self._progress.add_task(
                self.description, total=self.total, rate="", status="", counts=bool(self.unit)
            )
        return self

    def update(self, done: float, description: str | None = None, **fields: float | str) -> None:
        """Show ``done`` units of work finished, with the live ``fields``."""
        if self._progress is None:
            return
        status = "  ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in fields.items())
        speed = next((task.speed for task in self._progress.tasks if task.id == self._task), None)
        rate = f"{speed:.3g} {self.unit}/s" if speed and self.unit else ""
        self._progress.update(
            self._task, completed=done, description=description or self.description, rate=rate, status=status
        )

    def restart(self, total: float) -> None:
        """Count anew to ``total`` (a phase counted in other units), forgetting the rate so far."""
        self.total = total
        if self._progress is not None:
            self._progress.reset(self._task, total=total, completed=0)

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._progress is not None and self._owned:
            self._progress.__exit__(exc_type, exc, tb)
        elif self._progress is not None:
            self._progress.remove_task(self._task)  # the pipeline's line shows the stage as done


@contextmanager
def stage_progress(
    label: str, unit: str | None = "it", total: float = 1, enabled: bool | None = None
) -> Iterator[ProgressCallback]:
    """A bar for one stage and the callback that drives it: each phase shows as "LABEL: phase",
    and a phase that counts to another total restarts the count."""
    with ProgressBar(total, label, unit=unit, enabled=enabled) as bar:

        def on_progress(phase: str, done: float, total: float, fields: ProgressFields) -> None:
            if total != bar.total:
                bar.restart(total)
            bar.update(done, f"{label}: {phase}", **fields)

        yield on_progress


# The unit each stage counts in; cunerf and splat count iterations.
STAGE_UNITS = {"preprocess": None, "export": "view", "eval": "frame"}


def stage_bar(folder: str) -> ContextManager[ProgressCallback]:
    """The bar of the stage writing WORK/``folder`` (splat-random counts like splat)."""
    return stage_progress(folder, unit=STAGE_UNITS.get(folder.split("-")[0], "it"))
