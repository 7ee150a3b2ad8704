"""A splat run on a CPU that other work shares: its share of the cores when it trains beside another
run (docs/design.md §1, "Two runs at once"), and the rasterizer's kernels that a helper may compile
ahead of it while the stages before it leave cores idle ("Kernels ahead"). The pipeline asks the
stage (``SplatStage.beside``, ``SplatStage.compile_ahead``) and runs the processes."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cubecloud_cli.core.runtime import Runtime, resolve_device
from cubecloud_cli.splat.settings import SplatSettings

# Starting a process (importing torch, loading the scene) costs a few seconds; shorter runs are
# trained in turn. A test's 3-iteration run is one of them.
SIDE_BY_SIDE_MIN_ITERATIONS = 300
# The helper's own start (a process importing torch, then loading or compiling) costs a few
# seconds of CPU; below this many iterations (a test's, a quick look) the splat stage compiles its own.
COMPILE_AHEAD_MIN_ITERATIONS = 300
# Pixels per side of the tiny scene: every array keeps more than one element per axis, so its
# layout (C-contiguous or not) is the one full-size training arrays have.
TINY_IMAGE = 16


def threads_each(runtime: Runtime, settings: SplatSettings, runs: int, cores: int) -> int | None:
    """Threads for each of ``runs`` splat runs trained side by side, or None to train them in
    turn: on a GPU, when the user chose --threads, with fewer cores than runs, or for short runs."""
    if runs < 2 or cores < runs or runtime.threads is not None or settings.iterations < SIDE_BY_SIDE_MIN_ITERATIONS:
        return None
    if resolve_device(runtime.device).type != "cpu":
        return None
    return cores // runs


@dataclass(frozen=True)
class SplatKernels:
    """The rasterizer's kernels as a splat run with ``settings`` calls them: what a helper process
    compiles into numba's cache ahead of the run (picklable)."""

    settings: SplatSettings

    def __call__(self) -> None:
        compile_splat_kernels(self.settings)


def kernels_to_compile_ahead(settings: SplatSettings, runtime: Runtime) -> SplatKernels | None:
    """The kernels of a CPU run long enough to repay the helper; None otherwise."""
    if settings.iterations < COMPILE_AHEAD_MIN_ITERATIONS or resolve_device(runtime.device).type != "cpu":
        return None
    return SplatKernels(settings)


def compile_splat_kernels(settings: SplatSettings) -> None:
    """The rasterizer's kernels as splat training calls them: one training step of a tiny scene
    (whose first step compiles the backward side in its own helper) and one evaluation."""
    import numpy as np
    import torch

    from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
    from cubecloud_cli.splat.densify import strategy_for
    from cubecloud_cli.splat.gaussians import gaussians_from_points
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
    if settings.scalar:
        compile_scalar_kernels()


def compile_scalar_kernels() -> None:
    """What a scalar run adds: the read of the scan and its gradient at the centres, and the chord
    ratio, the scan's spread and the Gaussians' appearance both ways, with training's dtypes and
    layouts."""
    import numpy as np
    import torch

    from cubecloud_cli.numerics.trilinear import sample_cube_gradient_into, sample_cube_into
    from cubecloud_cli.splat.chord import chord_log_ratio
    from cubecloud_cli.splat.value_spread import value_spread_loss

    sample_cube_into(np.zeros((4, 4, 4), np.float32), np.zeros((2, 3), np.float32), np.empty(2, np.float32))
    sample_cube_gradient_into(
        np.zeros((4, 4, 4), np.float32), np.zeros((2, 3), np.float32), np.empty((2, 3), np.float32)
    )
    quaternions = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, requires_grad=True)
    scales = torch.full((2, 3), 0.1, requires_grad=True)
    chord_log_ratio(torch.zeros(2, 3), quaternions, scales, torch.tensor([0.0, 0.0, 3.0])).sum().backward()
    value_spread_loss(quaternions, torch.log(scales), torch.ones(2, 3)).backward()
    compile_scalar_appearance(torch.float32)


def compile_scalar_appearance(dtype) -> None:
    """The scalar appearance kernels both ways for parameters of ``dtype`` (training's float32;
    the suite's oracle tests also take float64)."""
    import torch

    from cubecloud_cli.splat.scalar_appearance import scalar_appearance
    from cubecloud_cli.transfer.function import TransferFunction

    def trained(tensor):
        return tensor.to(dtype).requires_grad_(True)

    quaternions, log_scales = trained(torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2)), trained(torch.full((2, 3), -2.0))
    values, lengths = trained(torch.zeros(2)), trained(torch.zeros(2))
    drawn = scalar_appearance(
        torch.zeros(2, 3, dtype=dtype), quaternions, log_scales, values, lengths, torch.zeros(2, dtype=dtype),
        TransferFunction(), torch.tensor([0.0, 0.0, 3.0], dtype=dtype), True,
    )  # fmt: skip
    sum(part.sum() for part in drawn).backward()
