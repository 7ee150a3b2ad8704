"""The pipeline's first compilation, ahead of the stages that need it (`cubecloud run` on a CPU).

A new user's first run compiles about a minute of numba kernels (CuNeRF's grid field, export's
march, the rasterizer's forward and backward), each on one core, inside the stage that first
calls it. The stages before splat leave one of the two cores idle for much of their time:
importing, reading the scan, numpy passes, a compilation on the other core. So `run` starts one
helper process at the lowest priority (nice 19) that calls each stage's kernels once, through
the stages' own code on tiny inputs, in the order the stages need them. numba writes what it
compiles to its cache, and each stage loads it from there. At nice 19 the helper takes only the
cycles the stages leave.

The splat runs wait for the helper before they start: the rasterizer is the largest compilation,
and a trainer starting beside the helper would compile the same kernels again. Its forward side
compiles in the helper and its backward side in the helper's own backward helper
(``raster/cpu_warmup.py``), on both cores, as a trainer's first step would. With a warm cache the
helper only loads the kernels and exits within seconds. Runs shorter than ``MIN_ITERATIONS`` and
a single stage compile their own, as before.

The kernels see inputs of the stages' own dtypes and layouts, so they compile the signatures the
stages call. A kernel the stages call with other types is compiled by its stage as before: the
helper can save time but never change a result (a kernel compiled in the process and one loaded
from the cache give the same bits, ``cubecloud_cli/jit.py``).
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from dataclasses import dataclass, replace
from pathlib import Path

# Longer than any first compilation measured (about 40 s on the slower host); a helper still
# running then is stopped, and the stages compile what is left themselves.
WAIT_SECONDS = 300.0
# The helper's own start (a process importing torch, then loading or compiling) costs a few
# seconds of CPU; below this many iterations (a test's, a quick look) the splat stage compiles its own.
MIN_ITERATIONS = 300
TINY_VOLUME = 8  # voxels per axis: every array keeps more than one element per axis, so its layout
TINY_IMAGE = 16  # (C-contiguous or not) is the one the stage's full-size arrays have


@dataclass(frozen=True)
class WarmupJob:
    """The settings of the stages whose kernels to compile (None: a stage not in this run)."""

    cunerf: object | None = None  # CunerfSettings
    export: object | None = None  # ExportSettings
    splat: object | None = None  # SplatSettings

    def is_empty(self) -> bool:
        return self.cunerf is None and self.export is None and self.splat is None


def compile_cunerf_kernels(settings) -> None:
    """The grid field's kernels as the cunerf stage and export call them: a training step (when
    the stage trains), test renders of cubes, and the field at points."""
    import numpy as np
    import torch

    from cubecloud_cli.cunerf.api import CunerfField, grid_centres
    from cubecloud_cli.cunerf.data import TrainingVoxels
    from cubecloud_cli.cunerf.model import CubeModel
    from cubecloud_cli.cunerf.training import Trainer

    if settings.model != "fast":
        return  # the paper's MLP runs in torch: nothing to compile
    size = TINY_VOLUME
    volume = torch.rand((size,) * 3, generator=torch.Generator().manual_seed(0))
    voxels = TrainingVoxels(volume, 1, [], settings.body_fraction)
    model = CubeModel(settings.field_config(size), settings.render_config(size))
    if settings.iterations > 0:
        Trainer(model, voxels, replace(settings, batch_size=16), torch.Generator().manual_seed(0)).step()
    field = CunerfField(model, size, np.eye(4), voxels.occupancy() if settings.skip_air else None, settings.as_dict())
    field.bake(size)
    centres = grid_centres(size, torch.device("cpu"))
    field.cube_values(centres)
    field.point_density(centres)


def compile_march_kernel(settings) -> None:
    """The export's ray march over a voxel grid, for its image model."""
    import torch

    from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
    from cubecloud_cli.render import GridField, ImageModel, render_view

    if settings.view != "dvr":
        return  # only dvr marches a grid in numba
    volume = torch.rand((TINY_VOLUME,) * 3, generator=torch.Generator().manual_seed(0)).numpy()
    cameras = orbit_cameras(OrbitSpec(views=2, resolution=TINY_IMAGE))
    model = ImageModel(settings.view, step=2.0 / TINY_VOLUME)
    render_view(GridField(volume, torch.device("cpu")), cameras, 0, model)


def compile_splat_kernels(settings) -> None:
    """The rasterizer's kernels as splat training calls them: one training step of a tiny scene
    (whose first step compiles the backward side in its own helper) and one evaluation."""
    import numpy as np
    import torch

    from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
    from cubecloud_cli.splat import gaussians_from_points
    from cubecloud_cli.splat.data import TrainingScene
    from cubecloud_cli.splat.training import SplatTrainer

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
    trainer = SplatTrainer(start, scene, settings, torch.device("cpu"))
    trainer.step()
    trainer.evaluate(scene.test)


def warm_up(job: WarmupJob) -> None:
    """Compile every kernel of ``job``'s stages into numba's cache, in the stages' order."""
    if job.cunerf is not None:
        compile_cunerf_kernels(job.cunerf)
    if job.export is not None:
        compile_march_kernel(job.export)
    if job.splat is not None:
        compile_splat_kernels(job.splat)


def _helper(job: WarmupJob) -> None:
    # A group of its own, so that stopping it stops its backward helper too.
    os.setpgrp()
    os.nice(19)
    import torch

    torch.set_num_threads(1)  # compiling is serial; the stages have the cores
    try:
        warm_up(job)
    except KeyboardInterrupt:  # Ctrl-C reaches the whole process group: the run reports it
        pass


class Warmup:
    """The helper process of one pipeline run."""

    def __init__(self, process: multiprocessing.process.BaseProcess | None):
        self.process = process

    @classmethod
    def start(cls, job: WarmupJob) -> "Warmup":
        from cubecloud_cli.side_by_side import without_main_module

        if job.is_empty():
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
