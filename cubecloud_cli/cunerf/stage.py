"""The cunerf stage: train the cube-based field on the preprocessed volume and write it out.

WORK/cunerf/ holds
  model.pt        the field's weights with the configuration that rebuilds it (CunerfField.load)
  recon.nii.gz    the field rendered at --export-scale × the volume's resolution, with the
                  affine that lays it over the original scan
  preview.png     mid-slices: volume, reconstruction, |difference| × 4
  log.csv         iteration, seconds, loss, learning rate and validation metrics
  manifest.json   parameters, input sha256, timings, 3D and held-out metrics

While training, WORK/.cunerf.partial/checkpoint.pt is written every --checkpoint-every
iterations and on Ctrl-C; `--resume` continues from it exactly.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.core.artifacts import (
    StageWriter,
    partial_dir,
    read_manifest,
    require_stage,
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
    saved_iteration,
)
from cubecloud_cli.core.pictures import write_preview_rows
from cubecloud_cli.core.progress import ProgressCallback, no_progress
from cubecloud_cli.core.runtime import Runtime, peak_memory_mb, reset_peak_memory
from cubecloud_cli.core.stage import Stage
from cubecloud_cli.cunerf.api import MODEL_FILE, CunerfField
from cubecloud_cli.cunerf.grid_init import initialise_from_volume
from cubecloud_cli.cunerf.model import CubeModel
from cubecloud_cli.cunerf.settings import CunerfSettings
from cubecloud_cli.cunerf.supervision import TrainingVoxels, holdout_slices
from cubecloud_cli.cunerf.training import Trainer
from cubecloud_cli.numerics.metrics import volume_metrics
from cubecloud_cli.volume.nifti import write_nifti

log = logging.getLogger("cubecloud")

CHECKPOINT_FILE = "checkpoint.pt"


def input_files(work: Path) -> list[Path]:
    """The files a cunerf stage is trained from; with its settings, they make it current."""
    return [Path(work) / "preprocess" / "volume.npy"]


@dataclass(frozen=True)
class CunerfStage(Stage):
    """The cunerf stage of a pipeline (docs/design.md §1)."""

    work: Path
    settings: CunerfSettings
    runtime: Runtime = Runtime()
    folder = "cunerf"
    upstream = ("preprocess",)

    @property
    def checkpoint(self) -> Path:
        return partial_dir(self.work, self.folder) / CHECKPOINT_FILE

    def input_files(self) -> list[Path]:
        return input_files(self.work)

    def recorded_params(self) -> dict:
        return self.settings.as_dict()

    def run(self, force: bool, resume: bool, on_progress: ProgressCallback) -> dict:
        return train_cunerf(
            self.work, self.settings, force=force, resume=resume, runtime=self.runtime, on_progress=on_progress
        )


RECON_FILE = "recon.nii.gz"
PREVIEW_FILE = "preview.png"
LOG_FILE = "log.csv"
LOG_COLUMNS = ("iteration", "seconds", "loss", "lr", "val_psnr", "val_ssim", "val_psnr_body", "val_ssim_body")


def _check_memory(settings: CunerfSettings, size: int, device: torch.device) -> None:
    """Refuse before allocating when training clearly cannot fit."""
    needed = settings.training_bytes(size)
    try:
        if device.type == "cuda":
            available = torch.cuda.get_device_properties(device).total_memory
        else:
            available = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError, RuntimeError):
        return
    if needed > 0.8 * available:
        raise CubecloudError(
            f"training needs about {needed / 2**30:.1f} GiB and the {device.type} has "
            f"{available / 2**30:.1f} GiB: lower --batch-size (now {settings.batch_size}), "
            f"--samples-per-axis or --importance"
        )


def _out_of_memory(exc: BaseException) -> bool:
    text = str(exc)
    torch_oom = getattr(torch, "OutOfMemoryError", getattr(torch.cuda, "OutOfMemoryError", MemoryError))
    return isinstance(exc, (MemoryError, torch_oom)) or "can't allocate memory" in text or "out of memory" in text


def _check_resume(
    checkpoint: Path,
    settings: CunerfSettings,
    volume_sha256: str,
    device: torch.device,
    resume: bool,
    force: bool,
) -> dict | None:
    """The checkpoint to continue from, or None to start afresh; refuses to guess."""
    state = checkpoint_to_resume(checkpoint, resume, force)
    if state is not None:
        recorded = state.get("settings", {})
        trained_on = state.get("context", {}).get("device", device.type)
        if trained_on != device.type:
            raise CubecloudError(
                f"the interrupted run trained on {trained_on}: resume it with --device {trained_on}, "
                f"or start again with --force"
            )
        if state.get("context", {}).get("volume_sha256") != volume_sha256:
            raise CubecloudError("preprocess/ changed since the interrupted run started: start again with --force")
        changed = [k for k, v in settings.as_dict().items() if k != "iterations" and recorded.get(k) != v]
        if changed:
            raise CubecloudError(
                f"the interrupted run used other settings ({', '.join(sorted(changed))}): resume with the "
                f"same options, or start again with --force"
            )
    return state


def train_cunerf(
    work: Path,
    settings: CunerfSettings,
    *,
    force: bool = False,
    resume: bool = False,
    runtime: Runtime = Runtime(),
    name: str | None = None,
    on_progress: ProgressCallback = no_progress,
) -> dict:
    """Run the stage; returns the manifest written to WORK/cunerf/manifest.json.

    ``on_progress(phase, done, total, fields)`` reports the "fit" of a volume start, "train" iterations (with loss and the
    latest validation PSNR in ``fields``) and then the "reconstruct" and "write" phases.
    """
    work = Path(work)
    settings.validate()
    preprocess = require_stage(work, "preprocess")
    size = int(preprocess["volume"]["shape"][0])
    settings.check_for_volume(size)
    device = runtime.apply()
    settings.check_for_device(device.type)
    reset_peak_memory(device)

    _check_memory(settings, size, device)

    writer = StageWriter(
        work, "cunerf", settings.as_dict(), force=force, name=name, keep_partial=True, transient=(CHECKPOINT_FILE,)
    )
    writer.check_can_start()
    checkpoint = writer.directory / CHECKPOINT_FILE
    volume_path = work / "preprocess" / "volume.npy"
    volume_sha256 = preprocess["files"]["volume.npy"]["sha256"]
    state = _check_resume(checkpoint, settings, volume_sha256, device, resume, force)
    if state is None and writer.directory.exists():
        shutil.rmtree(writer.directory)

    # Ctrl-C anywhere up to the commit (hashing the outputs included) leaves the checkpoint.
    try:
        with writer:
            phase = "load"
            try:
                with writer.phase("load"):
                    context = {"volume_sha256": volume_sha256, "device": device.type}
                    trainer, voxels, volume_np, held_out = _prepare(
                        writer, volume_path, settings, size, device, state, context
                    )
                if settings.grid_init == "volume" and state is None:
                    with writer.phase("fit"):
                        on_progress("fit", 0, 1, {})
                        remaining = initialise_from_volume(trainer.model, voxels)
                        if remaining is not None:
                            writer.metrics["volume_fit_rms"] = remaining
                phase = "train"
                with writer.phase("train"):
                    _train(trainer, checkpoint, on_progress)
                phase = "reconstruct"
                field, metrics, export_size = _reconstruct_and_write(
                    writer, trainer, voxels, volume_np, preprocess, on_progress
                )
            except (RuntimeError, MemoryError) as exc:
                if not _out_of_memory(exc):
                    raise
                raise CubecloudError(_out_of_memory_advice(phase, settings, checkpoint)) from None
            _record_results(writer, trainer, voxels, field, metrics, export_size, held_out, device)
    except (CubecloudInterrupted, NothingToResume):
        raise
    except KeyboardInterrupt:
        raise interrupted(checkpoint) from None
    return read_manifest(writer.final_dir)


def _record_results(
    writer: StageWriter,
    trainer: Trainer,
    voxels: TrainingVoxels,
    field: CunerfField,
    metrics: dict,
    export_size: int,
    held_out: list[int],
    device: torch.device,
) -> None:
    """Metrics and descriptions for manifest.json."""
    model, settings = trainer.model, trainer.settings
    final = trainer.history[-1] if trainer.history else {}
    writer.metrics.update({f"{k}_3d": v for k, v in metrics.items()})
    writer.metrics.update({k: v for k, v in final.items() if k.startswith("val_")})
    writer.metrics.update(
        {
            "iterations": trainer.iteration,
            "train_seconds": round(trainer.elapsed_s, 2),
            "seconds_per_1000_iterations": round(1000 * trainer.elapsed_s / max(trainer.iteration, 1), 2),
            "parameters": sum(p.numel() for p in model.parameters()),
            **peak_memory_mb(device),
        }
    )
    writer.extra.update(
        {
            "runtime": {"device": str(device), "threads": torch.get_num_threads(), "torch": torch.__version__},
            "data": {
                "volume_size": voxels.size,
                "training_voxels": voxels.training_voxels,
                "body_voxels": voxels.body_voxels,
                "held_out_slices": held_out,
                "air_blocks_skipped": None if field.occupancy is None else round(1 - field.occupancy.fraction(), 4),
            },
            "model": {"field": model.field_config.as_dict(), "render": model.render_config.as_dict()},
            "reconstruction": {"file": RECON_FILE, "shape": [export_size] * 3, "scale": settings.export_scale},
        }
    )


def _prepare(
    writer: StageWriter,
    volume_path: Path,
    settings: CunerfSettings,
    size: int,
    device: torch.device,
    state: dict | None,
    context: dict,
) -> tuple[Trainer, TrainingVoxels, np.ndarray, list[int]]:
    """Load the volume, build the model and its trainer, and restore a checkpoint if any."""
    remake = f"cubecloud preprocess SCAN -o {volume_path.parent.parent} --force"
    writer.add_input(volume_path, "preprocess/volume.npy", remake=remake)
    volume_np = np.load(volume_path)
    if volume_np.ndim != 3 or len(set(volume_np.shape)) != 1 or not np.isfinite(volume_np).all():
        raise CubecloudError(f"{volume_path} is not a finite S³ volume: rerun `cubecloud preprocess --force`")
    if not volume_np.any():
        raise CubecloudError(
            f"{volume_path} is 0 everywhere (all air, or a constant scan): there is nothing to train; check the scan "
            "and --window, or rerun `cubecloud preprocess --force` with a --size that keeps a thin scan (it named one)"
        )
    volume = torch.from_numpy(np.asarray(volume_np, dtype=np.float32)).to(device)  # no copy of a float32 volume
    held_out = holdout_slices(volume_np, settings.holdout, settings.train_scale)
    voxels = TrainingVoxels(volume, settings.train_scale, held_out, settings.body_fraction)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(settings.seed)
        model = CubeModel(settings.field_config(size), settings.render_config(size)).to(device)
    model.set_precision(settings.precision)
    generator = torch.Generator(device=device).manual_seed(settings.seed)
    trainer = Trainer(model, voxels, settings, generator, context=context)
    if state is not None:
        trainer.restore(state)
        log.info(f"resuming at iteration {trainer.iteration} of {settings.iterations}")
    if voxels.body_voxels == 0:
        log.warning("the volume holds no non-zero voxel: the field will learn empty space only")
    return trainer, voxels, volume_np, held_out


def _out_of_memory_advice(phase: str, settings: CunerfSettings, checkpoint: Path) -> str:
    if phase == "train" or phase == "load":
        return (
            f"out of memory while {'training' if phase == 'train' else 'loading'}: lower --batch-size "
            f"(now {settings.batch_size}), --samples-per-axis or --importance, and pass --force"
        )
    saved = saved_iteration(checkpoint) if checkpoint.is_file() else None
    where = (
        f"training is saved (iteration {saved}): free memory and rerun with --resume"
        if saved
        else "free memory and rerun"
    )
    return f"out of memory while rendering the trained field; {where}"


def _reconstruct_and_write(
    writer: StageWriter,
    trainer: Trainer,
    voxels: TrainingVoxels,
    volume_np: np.ndarray,
    preprocess: dict,
    on_progress: ProgressCallback,
) -> tuple[CunerfField, dict, int]:
    """Render the field at every voxel, score it, and write the stage's files."""
    settings, model, size = trainer.settings, trainer.model, voxels.size
    field = CunerfField(
        model,
        size,
        np.asarray(preprocess["geometry"]["voxel_to_scanner"]),
        voxels.occupancy() if settings.skip_air else None,
        settings.as_dict(),
    )
    with writer.phase("reconstruct"):
        recon = field.bake(size, on_progress=lambda f: on_progress("reconstruct", int(f * 100), 100, {}))
        device = voxels.volume.device
        metrics = volume_metrics(volume_np, recon, device=None if device.type == "cpu" else device)
        export_size = round(size * settings.export_scale)
        exported = recon if export_size == size else field.bake(export_size)

    with writer.phase("write"):
        on_progress("write", 0, 1, {})
        field.to_file(writer.directory / MODEL_FILE)
        write_nifti(
            exported,
            field.bake_affine(export_size),
            writer.directory / RECON_FILE,
            f"cubecloud cunerf x{settings.export_scale:g}",
        )
        # In place: one volume-sized array where four temporaries would be 2 GB at 512³.
        difference = np.subtract(recon, volume_np)
        np.abs(difference, out=difference)
        np.multiply(difference, 4.0, out=difference)
        np.clip(difference, 0.0, 1.0, out=difference)
        write_preview_rows(
            [("volume", volume_np), ("cunerf", recon), ("|diff|x4", difference)], writer.directory / PREVIEW_FILE
        )
        write_csv_log(writer.directory / LOG_FILE, LOG_COLUMNS, trainer.history)
    return field, metrics, export_size


def _train(trainer: Trainer, checkpoint: Path, on_progress: ProgressCallback) -> None:
    settings = trainer.settings
    total = settings.iterations
    log_every = max(1, total // 200)
    latest: dict = {}
    if total == 0:  # the fitted start alone: validated once, as training's last step would be
        trainer.history.append({"iteration": 0, "seconds": 0.0, "loss": None, "lr": None, **trainer.held_out_scores()})
        return
    with checkpointed_loop(checkpoint, "lower --lr and pass --force to start again") as interrupt:
        while trainer.iteration < total:
            trainer.step()
            it = trainer.iteration
            validate = it % settings.val_every == 0 or it == total
            if validate or it % log_every == 0:
                trainer.flush_losses()  # the row's loss is this iteration's, and the wait is training time
                if validate:
                    latest = trainer.held_out_scores()
                trainer.history.append(
                    {
                        "iteration": it,
                        "seconds": round(trainer.elapsed_s, 3),
                        "loss": trainer.smoothed_loss,
                        "lr": trainer.optimizer.param_groups[0]["lr"],
                        **(latest if validate else {}),
                    }
                )
            running = trainer.smoothed_loss
            fields = {"loss": running}
            if "val_psnr" in latest:
                fields["val PSNR"] = latest["val_psnr"]
            on_progress("train", it, total, fields)
            save_on_schedule(trainer.save, checkpoint, it, settings.checkpoint_every, total, interrupt)
