"""The splat stage: train 3D Gaussians on the exported scene (or any COLMAP scene).

WORK/splat[-NAME]/ holds
  point_cloud.ply   the Gaussians in the reference 3DGS layout (viewers open it)
  preview.png       test views: target (top) and render (bottom)
  log.csv           iteration, seconds, loss, test PSNR, Gaussian count
  manifest.json     parameters, inputs, schedule, timings, test metrics, iterations per second

While training, WORK/.splat.partial/checkpoint.pt is written every --checkpoint-every iterations
and on Ctrl-C; `--resume` continues from it exactly.
"""

from __future__ import annotations

import logging
import shutil
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.core.artifacts import (
    StageWriter,
    partial_dir,
    read_manifest,
    require_stage,
    stage_dir_name,
    write_csv_log,
)
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.interrupts import (
    CubecloudInterrupted,
    NothingToResume,
    checkpoint_to_resume,
    checkpointed_loop,
    interrupted,
    save_on_schedule,
)
from cubecloud_cli.core.pictures import to_uint8
from cubecloud_cli.core.progress import ProgressCallback, no_progress
from cubecloud_cli.core.runtime import Runtime, peak_memory_mb, reset_peak_memory
from cubecloud_cli.core.stage import Stage
from cubecloud_cli.core.writes import save_picture
from cubecloud_cli.splat.densify import strategy_for
from cubecloud_cli.splat.gaussian_ply import scalar_properties, write_gaussians_ply
from cubecloud_cli.splat.gaussians import gaussians_from_points, random_points
from cubecloud_cli.splat.on_cpu import SplatKernels, kernels_to_compile_ahead, threads_each
from cubecloud_cli.splat.scalar_gaussians import GaussianModel, ScalarGaussians, scalar_gaussians_from_points
from cubecloud_cli.splat.settings import SplatSettings
from cubecloud_cli.splat.trainer import SplatTrainer
from cubecloud_cli.splat.training_views import TRANSFER_IMAGES, TrainingScene, export_remake, load_scene

log = logging.getLogger("cubecloud")

CHECKPOINT_FILE = "checkpoint.pt"
PLY_FILE = "point_cloud.ply"
LOG_COLUMNS = ("iteration", "seconds", "loss", "test_psnr", "gaussians")


def recorded_params(settings: SplatSettings, scene_dir: Path) -> dict:
    """What a complete splat run must have been made with to be current: its settings and its scene."""
    return {**settings.as_dict(), "scene": str(scene_dir)}


def input_files(scene_dir: Path) -> list[Path]:
    """The scene files a splat run trains from (the point cloud only seeds --init cloud, but a new
    export changes both)."""
    files = [Path(scene_dir) / "images.npy", Path(scene_dir) / "points3D.ply"]
    transfer_images = Path(scene_dir) / TRANSFER_IMAGES
    return files + [transfer_images] if transfer_images.is_file() else files


@dataclass(frozen=True)
class SplatStage(Stage):
    """A splat run of a pipeline, trained on the work directory's export (``name``: a run beside
    the default one, in splat-NAME/). Picklable, so that a run can train in a process of its own."""

    work: Path
    settings: SplatSettings
    runtime: Runtime = Runtime()
    name: str | None = None
    upstream = ("export",)

    @property
    def folder(self) -> str:
        return stage_dir_name("splat", self.name)

    @property
    def checkpoint(self) -> Path:
        return partial_dir(self.work, self.folder) / CHECKPOINT_FILE

    def input_files(self) -> list[Path]:
        return input_files(self.work / "export")

    def recorded_params(self) -> dict:
        return recorded_params(self.settings, self.work / "export")

    def beside(self, others: int, cores: int) -> SplatStage | None:
        threads = threads_each(self.runtime, self.settings, others + 1, cores)
        return None if threads is None else replace(self, runtime=replace(self.runtime, threads=threads))

    def compile_ahead(self) -> SplatKernels | None:
        return kernels_to_compile_ahead(self.settings, self.runtime)

    def run(self, force: bool, resume: bool, on_progress: ProgressCallback) -> dict:
        return train_splat(
            self.work,
            self.settings,
            force=force,
            resume=resume,
            runtime=self.runtime,
            name=self.name,
            on_progress=on_progress,
        )


def _initial_gaussians(scene: TrainingScene, settings: SplatSettings) -> GaussianModel:
    if settings.init == "random":
        xyz, grey = random_points(settings.random_points, settings.seed)
        if settings.scalar:
            return scalar_gaussians_from_points(xyz, grey, _scalar_transfers(scene), settings.chord_lengths)
        return gaussians_from_points(xyz, grey, settings.channels, settings.sh_degree)
    if scene.points is None:
        raise CubecloudError(
            f"{scene.directory} has no point cloud (points3D.ply or sparse/0/points3D): use --init random"
        )
    if len(scene.points[0]) == 0:
        raise CubecloudError(
            f"{scene.directory}'s point cloud is empty: the field is air everywhere (an empty or constant "
            f"scan, or an --air-threshold too high); check the scan and its --window, or use --init random"
        )
    xyz, rgb = scene.points
    if settings.scalar:
        values = scene.point_values if scene.point_values is not None else rgb.mean(axis=1)
        if not np.isfinite(values).all():
            raise CubecloudError(f"the point values of {scene.directory} hold NaN or Inf: re-export the scene")
        return scalar_gaussians_from_points(xyz, values, _scalar_transfers(scene), settings.chord_lengths)
    return gaussians_from_points(xyz, rgb, settings.channels, settings.sh_degree)


def _scalar_transfers(scene: TrainingScene) -> list:
    if not scene.transfers:
        raise CubecloudError(
            f"{scene.directory} does not say which transfer function its images were rendered under: --scalar "
            f"trains on a dvr scene from `cubecloud export` (re-export with --view dvr), or drop --scalar"
        )
    return scene.transfers


# Options that change how often things are reported, not what is trained.
REPORTING_OPTIONS = ("eval_every", "checkpoint_every")


def _check_resume(
    checkpoint: Path, settings: SplatSettings, resume: bool, force: bool, scene: TrainingScene
) -> dict | None:
    state = checkpoint_to_resume(checkpoint, resume, force)
    if state is not None:
        # The schedule scales with --iterations, so it must not change part-way either.
        changed = [
            k for k, v in settings.as_dict().items() if k not in REPORTING_OPTIONS and state["settings"].get(k) != v
        ]
        recorded = {k: v for k, v in state.get("scene", {}).items() if k != "inputs"}  # inputs: checked once hashed
        if recorded != _scene_identity(scene):
            changed.append("scene")
        if changed:
            raise CubecloudError(
                f"the interrupted run used other settings ({', '.join(sorted(changed))}): resume with the same options, or --force"
            )
    return state


def train_splat(
    work: Path,
    settings: SplatSettings,
    *,
    scene_dir: Path | None = None,
    force: bool = False,
    resume: bool = False,
    runtime: Runtime = Runtime(),
    name: str | None = None,
    on_progress: ProgressCallback = no_progress,
) -> dict:
    work = Path(work)
    settings.validate()
    if scene_dir is None:
        require_stage(work, "export")
        scene_dir = work / "export"
    device = runtime.apply()
    _bound_kernel_threads(runtime, device)
    reset_peak_memory(device)
    scene = load_scene(scene_dir, settings.channels, every_transfer=settings.scalar)
    if scene.single_centre:  # said here, not in load_scene, so that eval does not repeat it
        log.warning(
            f"every training camera of {scene_dir} sits in one place: 3DGS cannot tell their images apart "
            f"(the paper's baseline); the scene extent is taken as {scene.extent:.3g}, from the camera's distance to the origin"
        )
    writer = StageWriter(
        work,
        "splat",
        recorded_params(settings, scene_dir),
        force=force,
        name=name,
        keep_partial=True,
        transient=(CHECKPOINT_FILE,),
    )
    writer.check_can_start()
    checkpoint = writer.directory / CHECKPOINT_FILE
    state = _check_resume(checkpoint, settings, resume, force, scene)
    if state is None and writer.directory.exists():
        shutil.rmtree(writer.directory)
    try:
        with writer:
            with writer.phase("load"):
                digests = _record_inputs(writer, scene_dir)
                images_digest = digests.get("images.npy")
                if state is not None and state.get("scene", {}).get("inputs", digests) != digests:
                    raise CubecloudError(
                        f"{scene_dir}'s images or points changed since the interrupted run started from them: "
                        "it cannot resume; start afresh with --force"
                    )
                trainer = _build_trainer(scene, settings, device, state)
                if settings.scalar and (settings.value_anchor > 0 or settings.value_spread > 0):
                    trainer.scan_values = _scan_values(scene_dir, writer, device)
                trainer.identity = {**trainer.identity, "inputs": digests}
            with writer.phase("train"):
                _train(trainer, checkpoint, on_progress)
            with writer.phase("write"):
                on_progress("write", 0, 1, {})
                _write_outputs(trainer, writer.directory)
            _record_results(writer, trainer, scene, scene_dir, work, settings, device, images_digest)
    except (CubecloudInterrupted, NothingToResume):
        raise
    except KeyboardInterrupt:
        raise interrupted(checkpoint) from None
    return read_manifest(writer.final_dir)


def _bound_kernel_threads(runtime: Runtime, device: torch.device) -> None:
    if runtime.threads is not None and device.type == "cpu":
        import numba  # the kernels run on numba's own thread pool, which --threads bounds too

        numba.set_num_threads(min(runtime.threads, numba.config.NUMBA_NUM_THREADS))


def _record_inputs(writer: StageWriter, scene_dir: Path) -> dict[str, str]:
    """Hash the scene's images and points into the manifest, each checked against the sha256 its
    export recorded; returns the digests by file name."""
    digests = {}
    fix = export_remake(scene_dir) or f"re-export the scene {scene_dir}"
    for path in input_files(scene_dir):
        if path.is_file():
            label = str(path.relative_to(scene_dir.parent)) if scene_dir.parent in path.parents else str(path)
            digests[path.name] = writer.add_input(path, label, remake=fix)
    return digests


def _scan_values(scene_dir: Path, writer: StageWriter, device: torch.device) -> torch.Tensor:
    """The preprocessed volume the scene was exported from, memory-mapped, for --value-anchor and
    --value-spread."""
    path = scene_dir.parent / "preprocess" / "volume.npy"
    fix = "train on a work directory's export, or give --value-anchor 0 --value-spread 0"
    recorded = read_manifest(scene_dir, fix).get("inputs", {}).get("preprocess/volume.npy")
    if recorded is None or not path.is_file():
        raise CubecloudError(
            f"--value-anchor and --value-spread hold a scalar scene to the scan, but {path} is not the volume {scene_dir} "
            f"was exported from: {fix}"
        )
    remake = f"cubecloud preprocess SCAN -o {scene_dir.parent} --force"
    if writer.add_input(path, "preprocess/volume.npy", remake=remake) != recorded:
        raise CubecloudError(
            f"{path} changed since {scene_dir} was exported from it: re-export, or give --value-anchor 0 --value-spread 0"
        )
    with warnings.catch_warnings():  # read-only: the map is never written
        warnings.simplefilter("ignore", UserWarning)
        volume = torch.from_numpy(np.load(path, mmap_mode="r"))
    return volume.to(device)  # the map itself on a CPU


def _build_trainer(
    scene: TrainingScene, settings: SplatSettings, device: torch.device, state: dict | None
) -> SplatTrainer:
    """A trainer from the initial Gaussians, restored to a checkpoint's state when resuming."""
    strategy = strategy_for(settings, scene.extent)
    trainer = SplatTrainer(_initial_gaussians(scene, settings), scene, settings, device, strategy)
    trainer.identity = _scene_identity(scene)
    if state is not None:
        trainer.restore(state)
        log.info(f"resuming at iteration {trainer.iteration} of {settings.iterations}")
    return trainer


def _write_outputs(trainer: SplatTrainer, directory: Path) -> None:
    trainer.draw_under_first_transfer()
    # The 3D filter baked in: a viewer shows what eval scores.
    gaussians = trainer.gaussians
    if isinstance(gaussians, ScalarGaussians):
        write_gaussians_ply(directory / PLY_FILE, gaussians.baked(), scalar_properties(gaussians))
    else:
        write_gaussians_ply(directory / PLY_FILE, gaussians.baked())
    write_csv_log(directory / "log.csv", LOG_COLUMNS, trainer.history)
    _write_preview(trainer, directory / "preview.png")


def _record_results(
    writer: StageWriter,
    trainer: SplatTrainer,
    scene: TrainingScene,
    scene_dir: Path,
    work: Path,
    settings: SplatSettings,
    device: torch.device,
    images_digest: str | None,
) -> None:
    """The final test scores, the schedule, the scene trained on and the runtime, into the manifest."""
    final = trainer.evaluate(scene.test)
    writer.metrics.update(
        {
            "test_psnr": final.get("psnr"),
            "test_l1": final.get("l1"),
            "test_views": len(scene.test),
            "gaussians": len(trainer.gaussians),
            "initial_gaussians": trainer.initial_count,
            "iterations": trainer.iteration,
            "train_seconds": round(trainer.elapsed_s, 2),
            "iterations_per_second": round(trainer.iteration / max(trainer.elapsed_s, 1e-9), 3),
            **peak_memory_mb(device),
        }
    )
    writer.extra.update(
        {
            "schedule": trainer.schedule,
            # resolved: eval finds the scene from any working directory; images_sha256 tells
            # it whether the scene there is still the one trained on.
            "scene": {
                "directory": str(scene_dir),
                "resolved": str(Path(scene_dir).resolve()),
                "own_export": Path(scene_dir).resolve() == (work / "export").resolve(),
                "images_sha256": images_digest,
                "views": len(scene.names),
                "train": len(scene.train),
                "test": [scene.names[i] for i in scene.test],
                "width": scene.cameras.width,
                "height": scene.cameras.height,
                "extent": scene.extent,
            },
            "rasterizer": trainer.rasterizer.description,
            "antialias": (
                {
                    "3d_filter": "Mip-Splatting, variance 0.2 × (depth / focal)² of the nearest training camera; "
                    "baked into point_cloud.ply",
                    "2d_filter": "Mip-Splatting, 0.1 px², opacity compensated; a renderer applies it (eval does)",
                }
                if settings.antialias
                else {"dilation_px2": 0.3}
            ),
            "runtime": {
                "device": str(device),
                "threads": torch.get_num_threads(),
                "torch": torch.__version__,
                "kernel_threads": _kernel_threads() if device.type == "cpu" else None,
            },
        }
    )


def _scene_identity(scene: TrainingScene) -> dict:
    """What a checkpoint must have been trained on to be resumed."""
    return {
        "directory": str(Path(scene.directory).resolve()),
        "views": len(scene.names),
        "size": [scene.cameras.width, scene.cameras.height],
        "names": scene.names,
    }


def _kernel_threads() -> int:
    import numba

    return numba.get_num_threads()


def _train(trainer: SplatTrainer, checkpoint: Path, on_progress: ProgressCallback) -> None:
    settings = trainer.settings
    total = settings.iterations
    latest: dict = {}
    with checkpointed_loop(checkpoint, "lower the learning rates and pass --force") as interrupt:
        while trainer.iteration < total:
            trainer.step()
            it = trainer.iteration
            evaluate = it % settings.eval_every == 0 or it == total
            if evaluate or it % max(1, total // 200) == 0:
                trainer.read_back()  # the row's loss is this iteration's
                row = {
                    "iteration": it,
                    "seconds": round(trainer.elapsed_s, 3),
                    "loss": trainer.last_loss,
                    "gaussians": len(trainer.gaussians),
                }
                if evaluate:
                    latest = trainer.evaluate(trainer.scene.test)
                    row["test_psnr"] = latest.get("psnr")
                trainer.history.append(row)
            fields = {"loss": trainer.last_loss, "gaussians": len(trainer.gaussians)}
            if "psnr" in latest:
                fields["test PSNR"] = latest["psnr"]
            on_progress("train", it, total, fields)
            save_on_schedule(trainer.save, checkpoint, it, settings.checkpoint_every, total, interrupt)


@torch.no_grad()
def _write_preview(trainer: SplatTrainer, path: Path) -> None:
    from PIL import Image

    views = (trainer.scene.test or trainer.scene.train)[:4]
    targets = [trainer.images[v].cpu().numpy() for v in views]
    renders = [trainer.render(v).image.clamp(0, 1).cpu().numpy() for v in views]
    rows = [np.concatenate(targets, axis=1), np.concatenate(renders, axis=1)]
    grid = to_uint8(np.concatenate(rows, axis=0))
    save_picture(Image.fromarray(grid[..., 0] if grid.shape[2] == 1 else grid), path)
