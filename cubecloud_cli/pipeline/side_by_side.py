"""Splat runs of one scene trained side by side, each in a process of its own, on its share of
the cores.

On a 2-core CPU one run on both cores does not train twice as fast as on one: part of each
iteration (Python, autograd, the optimiser's small tensors) is serial. Two runs, one core each,
finish the pair sooner, by 5–25 % in the runs measured (docs/results.md, "The two splat runs
side by side").

The second run starts once the first has taken a training step: by then the first has compiled
every rasterizer kernel into numba's cache, so the second loads them instead of compiling them
again on the same cores. When `run` compiled them ahead (``cubecloud_cli/pipeline/kernels_ahead.py``), both start
at once. A run's bits depend on torch's thread count only (never on the
kernels'), so a run trained here repeats bit for bit with `cubecloud splat --threads N`, N being
its share of the cores (1 on 2 cores).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import sys
import threading
import time
import traceback
import types
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from typing import Iterator

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.progress import ProgressCallback
from cubecloud_cli.core.stage import Stage

WIDEN = "SIGUSR1"


def available_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def side_by_side_runs(stages: list[Stage]) -> dict[str, Stage]:
    """The stages that run side by side, each in a process of its own, when more than one of them
    has to run: by folder, each as it runs on its share of the cores (``Stage.beside``)."""
    cores = available_cores()
    able = [stage for stage in stages if stage.beside(1, cores) is not None]
    copies = {stage.folder: stage.beside(len(able) - 1, cores) for stage in able}
    return {folder: copy for folder, copy in copies.items() if copy is not None}


def _widen_kernels_on_signal() -> None:
    """When the other run ends, the parent sends WIDEN: the rasterizer's kernels then take every
    core. Their results do not depend on their thread count (torch's do, and torch keeps its one
    thread), so the run's bits stay those of `cubecloud splat --threads 1`."""
    if not hasattr(signal, WIDEN):
        return

    def widen(signum, frame) -> None:
        import numba

        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)

    signal.signal(getattr(signal, WIDEN), widen)


@contextmanager
def without_main_module() -> Iterator[None]:
    """Hide the caller's ``__main__`` from spawn while a child starts. The child needs nothing of
    it, and spawn would run the caller's script again in the child: a script that calls
    ``run_pipeline`` without ``if __name__ == "__main__":`` would start a second pipeline there."""
    main = sys.modules["__main__"]
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


@contextmanager
def _start_ignoring_ctrl_c() -> Iterator[None]:
    """A child started now inherits SIGINT ignored, until its own handler is in place: a Ctrl-C
    while it is still importing would end it with a traceback and nothing saved. The parent
    stops such a child itself (``run_side_by_side``)."""
    if threading.current_thread() is not threading.main_thread():
        yield  # only the main thread may set handlers; spawn's children then start as usual
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _child(connection: Connection, stage: Stage, force: bool, resume: bool, log_level: int) -> None:
    """A child's whole life: run the stage, and say how it ended through ``connection``."""
    _widen_kernels_on_signal()
    logger = logging.getLogger("cubecloud")
    logger.setLevel(log_level)
    logger.addHandler(logging.StreamHandler())
    logger.propagate = False

    def report(phase: str, done: float, total: float, fields) -> None:
        connection.send(("progress", (phase, done, total, dict(fields))))

    # Started with Ctrl-C ignored (see _start_ignoring_ctrl_c); from here on it saves and stops.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        connection.send(("ready", None))
        manifest = stage.run(force, resume, report)
        connection.send(("done", manifest))
    except CubecloudError as exc:
        connection.send(("error", str(exc)))
    except KeyboardInterrupt as exc:  # the stage's own message says how far it got and how to go on
        connection.send(("interrupted", str(exc)))
    except MemoryError:
        connection.send(("memory", ""))
    except BaseException:  # a bug: the parent shows its traceback
        connection.send(("crash", traceback.format_exc()))
    finally:
        connection.close()


@dataclass
class _Running:
    folder: str
    process: multiprocessing.process.BaseProcess
    connection: Connection
    on_progress: ProgressCallback
    started: float
    ready: bool = False  # its Ctrl-C handler is in place: SIGINT makes it save and stop
    stepped: bool = False
    signalled: bool = False  # a second SIGINT would cut its checkpoint short
    widened: bool = False
    ending: tuple[str, object] | None = None
    seconds: float = 0.0


def run_side_by_side(
    jobs: list[tuple[Stage, bool, bool, ProgressCallback]], staggered: bool = True
) -> dict[str, tuple[dict, float]]:
    """Run each (stage, force, resume, on_progress) in a child process (a splat run, with the
    threads of its runtime); returns each stage folder's manifest and seconds. The first job starts at
    once, the others one by one, each after the ones before have taken a training step; or,
    when not ``staggered`` (numba's cache holds the kernels already), all at once."""
    context = multiprocessing.get_context("spawn")  # a fork would copy torch's and numba's thread pools
    waiting = list(jobs)
    running: list[_Running] = []
    interrupted = False

    def start_next() -> None:
        stage, force, resume, on_progress = waiting.pop(0)
        folder = stage.folder
        ours, theirs = context.Pipe(duplex=False)
        process = context.Process(
            target=_child,
            args=(theirs, stage, force, resume, logging.getLogger("cubecloud").getEffectiveLevel()),
            name=f"cubecloud {folder}",
        )
        with without_main_module(), _start_ignoring_ctrl_c():
            process.start()
        theirs.close()
        running.append(_Running(folder, process, ours, on_progress, time.perf_counter()))

    def stop_all() -> None:
        waiting.clear()
        for run in running:  # Ctrl-C on a terminal reached them too; a signal to us alone did not
            if run.ending is None and not run.signalled and run.process.is_alive():
                run.signalled = True
                if run.ready:
                    os.kill(run.process.pid, signal.SIGINT)
                else:  # still starting, with nothing to save: it ignores SIGINT until ready
                    run.process.terminate()

    start_next()
    while waiting and not staggered:
        start_next()
    while any(run.ending is None for run in running):
        try:
            _collect(running)
        except KeyboardInterrupt:
            interrupted = True
            stop_all()
            continue
        if any(run.ending and run.ending[0] in ("error", "memory", "crash") for run in running):
            stop_all()  # the pair cannot complete: the others save their work and stop too
        if waiting and all(run.stepped or run.ending for run in running):
            start_next()
        elif not waiting and not interrupted:
            _widen_the_last(running)
    for run in running:
        run.process.join()
    return _outcomes(running, interrupted)


def _widen_the_last(running: list[_Running]) -> None:
    """Once one run is left, it gets the cores the others had."""
    alive = [run for run in running if run.ending is None]
    # Only once it has stepped: by then it has its handler (the signal's default would end it).
    if len(alive) == 1 and alive[0].stepped and not alive[0].widened and hasattr(signal, WIDEN):
        alive[0].widened = True
        os.kill(alive[0].process.pid, getattr(signal, WIDEN))


def _collect(running: list[_Running]) -> None:
    """Handle every message ready from the children (blocking until one is)."""
    by_connection = {run.connection: run for run in running if run.ending is None}
    for connection in wait(list(by_connection)):
        run = by_connection[connection]
        try:
            kind, payload = connection.recv()
        except EOFError:  # died without a word: stopped by us while starting, or killed
            if run.signalled and not run.ready:
                run.ending = ("interrupted", f"{run.folder} was stopped before it started training")
            else:
                run.ending = ("crash", f"the process training {run.folder} ended with exit code {run.process.exitcode}")
            continue
        if kind == "ready":
            run.ready = True
        elif kind == "progress":
            phase, done, total, fields = payload
            run.stepped = run.stepped or (phase == "train" and done >= 1)
            run.on_progress(phase, done, total, fields)
        else:
            run.ending = (kind, payload)
            run.seconds = time.perf_counter() - run.started


def _outcomes(running: list[_Running], interrupted: bool) -> dict[str, tuple[dict, float]]:
    endings = {run.folder: run.ending for run in running}
    for folder, (kind, payload) in endings.items():
        if kind == "crash":
            raise RuntimeError(f"{folder}: {payload}")
        if kind == "memory":
            raise MemoryError
    errors = [f"{folder}: {payload}" for folder, (kind, payload) in endings.items() if kind == "error"]
    if errors:
        raise CubecloudError("; ".join(errors))
    stopped = [f"{folder}: {payload}" for folder, (kind, payload) in endings.items() if kind == "interrupted"]
    if stopped or interrupted:
        raise KeyboardInterrupt("; ".join(stopped) or "interrupted before the splat runs started")
    return {run.folder: (run.ending[1], run.seconds) for run in running}
