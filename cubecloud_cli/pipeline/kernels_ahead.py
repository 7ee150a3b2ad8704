"""The rasterizer's first compilation, ahead of the splat stages (`cubecloud run` on a CPU).

A new user's first splat run compiled the rasterizer's kernels at its first step: about 22 s on
both cores (the forward side in the trainer, the backward side in its helper,
``raster/cpu/backward_compile.py``). The stages before splat leave cycles idle: importing, reading the
scan, numpy passes, compilations on one core. So `run` starts one helper process at the lowest
priority (nice 19) that takes one training step of a tiny scene through the trainer's own code;
numba writes what it compiles to its cache, and the splat runs load it from there. At nice 19
the helper takes only the cycles the stages leave. The splat runs wait for it (a trainer
starting beside it would compile the same kernels again), then start together. With a warm
cache the helper only loads the kernels and exits within seconds. What to compile a stage says
(``Stage.compile_ahead``; a splat run's is ``splat/on_cpu.py``'s), so this module knows no stage.
Short runs and a single stage compile their own, as before. (Compiling cunerf's and the
march's kernels ahead too gained nothing: those stages reached them before the helper did.)

The kernels see inputs of the trainer's own dtypes and layouts, so they compile the signatures
training calls. A kernel called with other types is compiled by its stage as before: the
helper can save time but never change a result (a kernel compiled in the process and one loaded
from the cache give the same bits, ``cubecloud_cli/numerics/jit.py``).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from typing import Callable

# Longer than any first compilation measured (about 30 s on the slower host); a helper still
# running then is stopped, and the stages compile what is left themselves.
WAIT_SECONDS = 300.0


def warm_up(job: Callable[[], object]) -> None:
    """Compile what ``job`` compiles (a stage's ``compile_ahead()``) into numba's cache."""
    job()


def _helper(job: Callable[[], object]) -> None:
    # A process group of its own, so that stopping it stops its backward helper too (and a Ctrl-C
    # on the terminal reaches only the stages, which stop it).
    os.setpgrp()
    os.nice(19)
    import torch

    torch.set_num_threads(1)  # compiling is serial; the stages have the cores
    warm_up(job)


class Warmup:
    """The helper process of one pipeline run."""

    def __init__(self, process: multiprocessing.process.BaseProcess | None):
        self.process = process

    @classmethod
    def start(cls, job: Callable[[], object] | None) -> "Warmup":
        """A helper at nice 19 that runs ``job`` (picklable: it crosses into a spawned process)."""
        from cubecloud_cli.pipeline.side_by_side import without_main_module

        if job is None:
            return cls(None)
        context = multiprocessing.get_context("spawn")  # a fork would copy torch's thread pools
        process = context.Process(target=_helper, args=(job,), name="cubecloud-warmup", daemon=False)
        with without_main_module():
            process.start()
        return cls(process)

    def wait(self, timeout: float = WAIT_SECONDS) -> bool:
        """Let the helper finish (the stages then load every kernel), or stop it after ``timeout``.
        Returns whether it compiled everything it was given (once: later calls return False)."""
        if self.process is None:
            return False
        self.process.join(timeout)
        compiled = self.process.exitcode == 0
        self.stop()
        return compiled

    def stop(self) -> None:
        """Stop the helper if it still runs (numba writes each cache file whole, so none is left
        half-written)."""
        if self.process is not None and self.process.is_alive():
            try:
                os.killpg(self.process.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                self.process.kill()
            self.process.join()
        self.process = None
