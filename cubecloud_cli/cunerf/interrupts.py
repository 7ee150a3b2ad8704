"""Ctrl-C during a long stage: finish the step, save, and say how to resume."""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch


@contextmanager
def deferred_interrupt() -> Iterator[dict]:
    """Ctrl-C sets a flag that the loop reads between steps, so the checkpoint it then saves
    is the state after a whole step. A second Ctrl-C interrupts at once."""
    flag = {"requested": False}
    if threading.current_thread() is not threading.main_thread():
        yield flag  # signal handlers can only be set from the main thread
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous in (signal.SIG_IGN, None):  # Ctrl-C ignored (nohup), or a handler set from C
        yield flag
        return

    def handler(signum, frame) -> None:
        if flag["requested"]:
            raise KeyboardInterrupt
        flag["requested"] = True

    signal.signal(signal.SIGINT, handler)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, previous)


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
