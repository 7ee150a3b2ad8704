"""The rasterizer's first compilation, ahead of the splat stages (`cubecloud run` on a CPU).

A new user's first splat run compiled the rasterizer's kernels at its first step: about 22 s on
both cores (the forward side in the trainer, the backward side in its helper,
``raster/cpu/backward_compile.py``). The stages before splat leave cycles idle: importing, reading the
scan, numpy passes, compilations on one core. So `run` starts one helper process at the lowest
priority (nice 19) that takes one training step of a tiny scene through the trainer's own code;
numba writes what it compiles to its cache, and the splat runs load it from there. At nice 19
the helper takes only the cycles the stages leave. The splat runs wait for it (a trainer
starting beside it would compile the same kernels again), then start together. With a warm
cache the helper only loads the kernels and exits within seconds. Runs shorter than
``MIN_ITERATIONS`` and a single stage compile their own, as before. (Compiling cunerf's and the
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
from dataclasses import dataclass
from pathlib import Path

from cubecloud_cli.core.runtime import resolve_device
from cubecloud_cli.core.stage import Stage
from cubecloud_cli.splat.settings import SplatSettings
from cubecloud_cli.splat.stage import SplatStage

# Longer than any first compilation measured (about 30 s on the slower host); a helper still
# running then is stopped, and the stages compile what is left themselves.
WAIT_SECONDS = 300.0
# The helper's own start (a process importing torch, then loading or compiling) costs a few
# seconds of CPU; below this many iterations (a test's, a quick look) the splat stage compiles its own.
MIN_ITERATIONS = 300
# Pixels per side of the tiny scene: every array keeps more than one element per axis, so its
# layout (C-contiguous or not) is the one full-size training arrays have.
TINY_IMAGE = 16


@dataclass(frozen=True)
class WarmupJob:
    """What to compile ahead: the rasterizer's kernels for these splat settings (None: nothing)."""

    splat: SplatSettings | None = None

    def is_empty(self) -> bool:
        return self.splat is None


def kernels_for(stage: Stage) -> WarmupJob | None:
    """The kernels ``stage`` compiles that a helper may compile ahead: a CPU splat run's, when it
    is long enough to repay the helper."""
    if not isinstance(stage, SplatStage) or stage.settings.iterations < MIN_ITERATIONS:
        return None
    return WarmupJob(splat=stage.settings) if resolve_device(stage.runtime.device).type == "cpu" else None


def compile_splat_kernels(settings) -> None:
    """The rasterizer's kernels as splat training calls them: one training step of a tiny scene
    (whose first step compiles the backward side in its own helper) and one evaluation."""
    import numpy as np
    import torch

    from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
    from cubecloud_cli.splat import gaussians_from_points
    from cubecloud_cli.splat.densify import strategy_for
    from cubecloud_cli.splat.trainer import SplatTrainer
    from cubecloud_cli.splat.training_views import TrainingScene

    cameras = orbit_cameras(OrbitSpec(views=4, resolution=TINY_IMAGE))
    images = torch.rand((4, TINY_IMAGE, TINY_IMAGE, settings.channels), generator=torch.Generator().manual_seed(0))
    scene = TrainingScene(Path("."), cameras, list("abcd"), images, [1, 2, 3], [0], None)
    rng = np.random.default_rng(0)
    start = gaussians_from_points(
        rng.uniform(-0.5, 0.5, (200, 3)),
        rng.uniform(0, 1, (200, settings.channels)),
        settings.channels,
        settings.sh_degree,
    )
    trainer = SplatTrainer(start, scene, settings, torch.device("cpu"), strategy_for(settings, scene.extent))
    trainer.step()
    trainer.evaluate(scene.test)


def warm_up(job: WarmupJob) -> None:
    """Compile the kernels of ``job`` into numba's cache."""
    if job.splat is not None:
        compile_splat_kernels(job.splat)


def _helper(job: WarmupJob) -> None:
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
    def start(cls, job: WarmupJob | None) -> "Warmup":
        from cubecloud_cli.pipeline.side_by_side import without_main_module

        if job is None or job.is_empty():
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
