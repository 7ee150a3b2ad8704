"""Ctrl-C during a long training stage (cunerf, splat): finish the step, save, and say how to
resume; and the checkpoint rhythm both stages share."""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

import torch

from cubecloud_cli.core.errors import CubecloudError

# What a scheduler sends to stop a job (SLURM at its time limit or on pre-emption): handled as Ctrl-C.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@contextmanager
def _stop_signals_handled_by(handler: Callable) -> Iterator[None]:
    """``handler`` for Ctrl-C and SIGTERM in the main thread, restored afterwards. A signal that was
    ignored (nohup, a parent that keeps Ctrl-C to itself) stays ignored."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be set from the main thread
        return
    previous = {number: signal.getsignal(number) for number in STOP_SIGNALS}
    for number, before in previous.items():
        if before not in (signal.SIG_IGN, None):  # None: a handler set from C, left alone
            signal.signal(number, handler)
    try:
        yield
    finally:
        for number, before in previous.items():
            if before not in (signal.SIG_IGN, None):
                signal.signal(number, before)


@contextmanager
def deferred_interrupt() -> Iterator[dict]:
    """Ctrl-C or SIGTERM sets a flag that the loop reads between steps, so the checkpoint it then
    saves is the state after a whole step. A second one interrupts at once."""
    flag = {"requested": False}

    def handler(signum, frame) -> None:
        if flag["requested"]:
            raise KeyboardInterrupt
        flag["requested"] = True

    with _stop_signals_handled_by(handler):
        yield flag


@contextmanager
def remembered_interrupt() -> Iterator[dict]:
    """Ctrl-C or SIGTERM interrupts at once, as Python's own handler does, and also sets a flag for
    ``raise_if_interrupted``. Python can only print a KeyboardInterrupt raised inside a ctypes
    callback, and numba compiles through one: the flag makes the next check raise it after all."""
    flag = {"requested": False}

    def handler(signum, frame) -> None:
        flag["requested"] = True
        raise KeyboardInterrupt

    with _stop_signals_handled_by(handler):
        yield flag


def raise_if_interrupted(flag: dict | None) -> None:
    """Raise the interrupt ``remembered_interrupt`` recorded, if one came and was lost."""
    if flag is not None and flag["requested"]:
        raise KeyboardInterrupt


def saved_iteration(checkpoint: Path) -> int | None:
    try:
        return int(torch.load(checkpoint, map_location="cpu", weights_only=False)["iteration"])
    except Exception:
        return None


def interrupted(checkpoint: Path) -> KeyboardInterrupt:
    """The interrupt to report: where the saved checkpoint stands, or that there is none."""
    iteration = saved_iteration(checkpoint) if checkpoint.is_file() else None
    if iteration is None:
        return NothingToResume("interrupted before the first checkpoint: run the command again")
    return CubecloudInterrupted(checkpoint, iteration)


class NothingToResume(KeyboardInterrupt):
    """Ctrl-C before any checkpoint was written."""


class CubecloudInterrupted(KeyboardInterrupt):
    """Ctrl-C during the stage, with where its checkpoint stands."""

    def __init__(self, checkpoint: Path, iteration: int):
        super().__init__(
            f"interrupted: iteration {iteration} is saved in {checkpoint}; continue with the same "
            f"command and --resume (`cubecloud run` resumes by itself)"
        )
        self.checkpoint = checkpoint
        self.iteration = iteration


@contextmanager
def checkpointed_loop(checkpoint: Path, divergence_fix: str) -> Iterator[dict]:
    """Run a training loop with Ctrl-C deferred to step boundaries; turns a second Ctrl-C into
    the resume message and a FloatingPointError into a one-line divergence error."""
    with deferred_interrupt() as interrupt:
        try:
            yield interrupt
        except (CubecloudInterrupted, NothingToResume):
            raise
        except KeyboardInterrupt:
            # A second Ctrl-C, mid-step: the state may be half-updated, so keep the last save.
            raise interrupted(checkpoint) from None
        except FloatingPointError as exc:
            raise CubecloudError(f"training diverged: {exc}; {divergence_fix}") from None


def save_on_schedule(
    save: Callable[[Path], None], checkpoint: Path, iteration: int, every: int, total: int, interrupt: dict
) -> None:
    """Save every ``every`` iterations, after the last one (a resume then goes straight to the
    stage's end) and on Ctrl-C, then stop if Ctrl-C was pressed."""
    if iteration % every == 0 or iteration == total or interrupt["requested"]:
        save(checkpoint)
    if interrupt["requested"]:
        raise CubecloudInterrupted(checkpoint, iteration)


def checkpoint_to_resume(checkpoint: Path, resume: bool, force: bool) -> dict | None:
    """The saved state to continue from with ``--resume`` (refusing a missing or unreadable one),
    or None to start afresh; without --resume or --force, refuses to discard a waiting run.
    The stage then checks that the state fits its inputs and settings."""
    if resume:
        if not checkpoint.is_file():
            raise CubecloudError(
                f"there is no interrupted run to resume ({checkpoint} is missing): run without --resume"
            )
        try:
            return torch.load(checkpoint, map_location="cpu", weights_only=False)
        except Exception as exc:  # torch raises many types for a damaged file
            raise CubecloudError(
                f"{checkpoint} is unreadable ({type(exc).__name__}): start again with --force"
            ) from None
    if checkpoint.is_file() and not force:
        raise CubecloudError(
            f"an interrupted run is waiting in {checkpoint.parent}: pass --resume to continue it, or --force to start again"
        )
    return None
