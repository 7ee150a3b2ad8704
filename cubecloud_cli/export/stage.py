"""The export stage: the CuNeRF scene as a COLMAP scene that 3DGS tools open as it is.

WORK/export/ holds
  images/view_000.png …     training images rendered from CuNeRF (8-bit grey, stored as RGB)
  images.npy                the same as float32 (N, H, W): what `splat` trains on
  transfer_images.npy       with --transfer-set K > 1: float32 (K, N // S, H, W), the training views under each
                            transfer function the manifest's "transfers" lists (the first is images.npy), member
                            k at views k mod S, + S, + 2S … for --transfer-stride S (all of them at S = 1)
  reference/view_000.png …  the same views rendered from the preprocessed volume (ground truth)
  reference.npy             float32 (N, H, W): what `eval` scores against
  sparse/0/                 cameras, images, points3D (.bin and .txt), points3D.ply, test.txt
  points3D.ply              the cube-sampled cloud: x y z nx ny nz red green blue intensity density
  transforms.json           the cameras for nerfstudio / instant-ngp readers
  split.json                train and test view names (every 8th view is held out)
  sparse_pc.ply             the same points as plain x y z nx ny nz red green blue (transforms.json's
                            ply_file_path: nerfstudio and OpenSplat read it by position, not by name)
  novel/                    the novel-view test: views.json and pixel-area reference.npy (export/novel_references.py)
  contact_sheet.png, contact_sheet_reference.png
  manifest.json             parameters, cameras, image model, timings, point and image metrics
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli import __version__
from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.cameras.novel import NovelViewSet, nearest_angles_deg
from cubecloud_cli.core.artifacts import StageWriter, is_complete, read_manifest, require_stage, stage_dir_name
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.interrupts import raise_if_interrupted, remembered_interrupt
from cubecloud_cli.core.progress import ProgressCallback, no_progress
from cubecloud_cli.core.runtime import Runtime, peak_memory_mb, reset_peak_memory
from cubecloud_cli.core.stage import Stage
from cubecloud_cli.core.writes import save_array
from cubecloud_cli.cunerf.api import MODEL_FILE, CunerfField
from cubecloud_cli.export.finished_views import PROGRESS_DIR, ExportProgress
from cubecloud_cli.export.images import view_names
from cubecloud_cli.export.memory import check_export_memory
from cubecloud_cli.export.novel_references import write_held_out, write_novel
from cubecloud_cli.export.renders import ExportJob, ExportRenders, render_export
from cubecloud_cli.export.scene_files import held_out_views, write_scene
from cubecloud_cli.export.settings import ExportSettings
from cubecloud_cli.numerics.metrics import image_metrics
from cubecloud_cli.render import ImageModel
from cubecloud_cli.transfer.tissue_presets import clipped_away, resolve_transfer
from cubecloud_cli.transfer.training_set import NamedTransfer, held_out_transfers, training_transfers

log = logging.getLogger("cubecloud")

TRANSFER_IMAGES = "transfer_images.npy"


def recorded_params(settings: ExportSettings, cunerf_name: str | None = None) -> dict:
    """What a complete export must have been made with to be current: its settings and its cunerf run."""
    return {**settings.as_dict(), "cunerf": stage_dir_name("cunerf", cunerf_name)}


def input_files(work: Path, cunerf_name: str | None = None) -> list[Path]:
    """The files an export reads: the volume and the trained field."""
    return [Path(work) / "preprocess" / "volume.npy", Path(work) / stage_dir_name("cunerf", cunerf_name) / MODEL_FILE]


def resumed_views(manifest: dict) -> int:
    """How many views an export took from an interrupted run's saved work."""
    return int(manifest.get("resumed", {}).get("views", 0))


@dataclass(frozen=True)
class ExportStage(Stage):
    """The export stage of a pipeline (docs/design.md §1)."""

    work: Path
    settings: ExportSettings
    runtime: Runtime = Runtime()
    folder = "export"
    upstream = ("cunerf",)

    def input_files(self) -> list[Path]:
        return input_files(self.work)

    def recorded_params(self) -> dict:
        return recorded_params(self.settings)

    def run(self, force: bool, resume: bool, on_progress: ProgressCallback) -> dict:
        # An export always continues from the views an interrupted run saved (``resumed``).
        return export_scene(self.work, self.settings, force=force, runtime=self.runtime, on_progress=on_progress)

    def resumed(self, manifest: dict) -> bool:
        return resumed_views(manifest) > 0 or bool(manifest.get("resumed", {}).get("bake"))


def export_scene(
    work: Path,
    settings: ExportSettings,
    *,
    force: bool = False,
    runtime: Runtime = Runtime(),
    name: str | None = None,
    cunerf_name: str | None = None,
    on_progress: ProgressCallback = no_progress,
) -> dict:
    """Run the stage; returns the manifest written to WORK/export/manifest.json.

    ``on_progress`` counts rendered views (CuNeRF's, the reference's, then the novel references)
    through the phases "bake", "images", "reference", "novel", "points" and "write".
    """
    work = Path(work)
    job, cunerf = _plan_export(work, settings, runtime, cunerf_name)
    device, preprocess = job.device, job.preprocess
    params = recorded_params(settings, cunerf_name)
    writer = StageWriter(work, "export", params, force=force, name=name, keep_partial=True, transient=(PROGRESS_DIR,))
    writer.check_can_start()
    fingerprint = {
        "params": params,
        "volume": preprocess["files"]["volume.npy"]["sha256"],
        "model": cunerf["files"].get(MODEL_FILE, {}).get("sha256"),
        "version": __version__,
        # Renders on another device may differ by rounding: views are not mixed across devices.
        "device": device.type,
    }
    progress = ExportProgress(writer.directory, fingerprint)
    saved = progress.prepare()
    total_views = job.total_views
    baked = progress.has("bake")
    if saved or baked:
        kept = [f"{saved} of {total_views} views are already rendered"] if saved else []
        kept += ["the field is already baked"] if baked else []
        log.info(f"continuing the interrupted export: {', and '.join(kept)}")
    writer.extra["resumed"] = {"views": saved, "bake": baked}
    reset_peak_memory(device)
    try:
        with remembered_interrupt() as progress.interrupt:
            return _export(job, writer, progress, on_progress)
    except KeyboardInterrupt:
        if not writer.directory.exists() and is_complete(writer.final_dir):
            raise KeyboardInterrupt(f"interrupted while tidying up: {writer.final_dir} is complete") from None
        raise KeyboardInterrupt(
            f"interrupted: {progress.saved_views()} of {total_views} views are saved in {progress.directory}; "
            f"run the same command to continue"
        ) from None
    except BaseException:
        if writer.directory.exists() and not progress.has_work():
            shutil.rmtree(writer.directory, ignore_errors=True)  # nothing there would save time
        raise


def _plan_export(
    work: Path, settings: ExportSettings, runtime: Runtime, cunerf_name: str | None
) -> tuple[ExportJob, dict]:
    """Check the settings against the volume and the cunerf run, and build the cameras and the image
    model; returns the job and the cunerf manifest."""
    settings.validate()
    preprocess = require_stage(work, "preprocess")
    size = int(preprocess["volume"]["shape"][0])
    settings.check_for_volume(size)
    settings = settings.for_volume(size)
    cunerf = require_stage(work, "cunerf", cunerf_name)
    trained_on = cunerf.get("inputs", {}).get("preprocess/volume.npy")
    if trained_on is not None and trained_on != preprocess["files"]["volume.npy"]["sha256"]:
        raise CubecloudError(
            f"{work / stage_dir_name('cunerf', cunerf_name)} was trained on an earlier preprocess/ volume: "
            f"rerun `cubecloud cunerf {work} --force`"
        )
    cameras = settings.camera_set()
    device = runtime.apply()
    check_export_memory(settings, size)
    transfer = resolve_transfer(
        settings.transfer, preprocess.get("intensity"), settings.tf_low, settings.tf_high, settings.tf_density
    )
    clipped = clipped_away(settings.transfer, preprocess.get("intensity"))
    if settings.view == "dvr" and clipped and settings.tf_low is None and settings.tf_high is None:
        raise CubecloudError(f"--transfer {clipped}, or set --tf-low/--tf-high")
    image_model = ImageModel(
        settings.view, transfer, step=settings.step * 2.0 / size, slice_offsets=settings.slice_offsets()
    )
    try:
        image_model.validate()
    except ValueError as exc:
        raise CubecloudError(f"{exc}: choose a --step below the volume's {size} voxels, e.g. 1") from None
    transfers = training_transfers(
        NamedTransfer(settings.transfer, transfer), settings.transfer_set, preprocess.get("intensity"), settings.seed
    )
    job = ExportJob(
        work,
        settings,
        cameras,
        settings.novel_view_set(),
        image_model,
        preprocess,
        cunerf,
        size,
        device,
        cunerf_name,
        tuple(transfers),
        held_out_transfers(preprocess.get("intensity"), settings.seed, transfers, windows=settings.held_out_windows)
        if settings.transfer_set > 1 and settings.novel_directions > 0
        else None,
    )
    return job, cunerf


def _export(job: ExportJob, writer: StageWriter, progress: ExportProgress, on_progress: ProgressCallback) -> dict:
    with writer:
        with writer.phase("load"):
            volume, field = _load_inputs(job, writer)
        renders = render_export(job, volume, field, writer, progress, on_progress)
        raise_if_interrupted(progress.interrupt)  # one lost after the last view was saved
        if renders.cloud.stats["points"] == 0:
            log.warning("the field is air everywhere: points3D holds no point (lower --air-threshold?)")
        with writer.phase("write"):
            on_progress("write", job.total_views, job.total_views, {})
            names = view_names(len(job.cameras))
            write_scene(writer.directory, job.cameras, names, renders.images, renders.reference, renders.cloud)
            if renders.transfer_images is not None:
                save_array(writer.directory / TRANSFER_IMAGES, renders.transfer_images)
            if len(job.novel):
                write_novel(writer.directory, job.novel, renders.novel_reference)
            if job.held_out is not None and len(job.novel):
                write_held_out(
                    writer.directory,
                    renders.held_out_references,
                    job.held_out.not_scored,
                    job.held_out_views.magnifications,
                )
        _record(writer, job, names, renders)
        if len(job.novel):
            _record_novel(writer, job.cameras, names, job.novel)
    return read_manifest(writer.final_dir)


def _load_inputs(job: ExportJob, writer: StageWriter) -> tuple[np.ndarray, CunerfField]:
    """The volume and the trained field, each checked against the manifest of the stage that wrote it."""
    work, size = job.work, job.size
    volume_path = work / "preprocess" / "volume.npy"
    model_path = job.cunerf_dir / MODEL_FILE
    # The hashes are taken anyway for the manifest; they also catch files changed in place.
    for path, label, fix in (
        (volume_path, "preprocess/volume.npy", f"cubecloud preprocess SCAN -o {work} --force"),
        (model_path, f"{job.cunerf_dir.name}/{MODEL_FILE}", f"cubecloud cunerf {work} --force"),
    ):
        recorded = read_manifest(path.parent)["files"].get(path.name, {}).get("sha256")
        if writer.add_input(path, label) != recorded:
            raise CubecloudError(f"{path} changed since its stage was written: run `{fix}`")
    volume = np.load(volume_path, mmap_mode="r")  # read where rays reach it: no copy of a 512³ volume in memory
    if volume.ndim != 3 or volume.shape != (size,) * 3 or not np.isfinite(volume).all():
        raise CubecloudError(
            f"{volume_path} is not the finite {size}³ volume its manifest says: rerun `cubecloud preprocess --force`"
        )
    field = CunerfField.from_file(model_path, job.device.type)
    if field.volume_size != size:
        raise CubecloudError(
            f"{model_path} was trained on a {field.volume_size}³ volume but preprocess/ holds {size}³: "
            f"rerun `cubecloud cunerf {work} --force`"
        )
    return volume, field


def _record(writer: StageWriter, job: ExportJob, names: list[str], renders: ExportRenders) -> None:
    """The CuNeRF-vs-reference scores, the cameras, the image model and the frames, into the manifest."""
    settings, cameras, cloud, device, preprocess = job.settings, job.cameras, renders.cloud, job.device, job.preprocess
    images, reference = renders.images, renders.reference
    held_out = held_out_views(len(names))
    test_metrics = image_metrics(reference[held_out], images[held_out])
    writer.metrics.update({f"cunerf_vs_reference_{k}": v for k, v in test_metrics.items()})
    writer.metrics.update(
        {"points": cloud.stats["points"], "views": len(names), "test_views": len(held_out), **peak_memory_mb(device)}
    )
    writer.extra.update(
        {
            "cameras": {
                "model": "PINHOLE",
                "width": cameras.width,
                "height": cameras.height,
                "fx": float(cameras.focal),
                "fy": float(cameras.focal),
                "cx": cameras.cx,
                "cy": cameras.cy,
                "fov_deg": float(np.degrees(cameras.fov_x)),
                "convention": "OpenCV/COLMAP: x right, y down, z forward; world-to-camera poses; pixel centres at +0.5",
                "centres": cameras.centres().round(9).tolist(),
            },
            "image_model": {**job.image_model.as_dict(), "step_voxels": settings.step},
            "transfers": [{"name": t.name, **t.function.as_dict()} for t in job.transfers],
            "transfer_stride": settings.transfer_stride,
            "render_source": {
                "training_images": "cunerf grid" if settings.render_from == "grid" else "cunerf field",
                "bake_size": settings.bake_resolution(job.size) if settings.render_from == "grid" else None,
                "reference_images": "preprocess/volume.npy, trilinear",
            },
            "split": {
                "train": [n for i, n in enumerate(names) if i not in held_out],
                "test": [names[i] for i in held_out],
            },
            "point_cloud": cloud.stats,
            "world": {
                "cube": "[-1, 1]^3, RAS axes (docs/design.md §2)",
                "mm_per_world_unit": preprocess.get("geometry", {}).get("mm_per_world_unit"),
                "world_to_scanner": preprocess.get("geometry", {}).get("world_to_scanner"),
            },
            "runtime": {"device": str(device), "threads": torch.get_num_threads(), "torch": torch.__version__},
        }
    )


def _record_novel(writer: StageWriter, cameras: PinholeCameras, names: list[str], novel: NovelViewSet) -> None:
    """What eval needs to read the novel views, and how far they lie from this export's cameras."""
    train = [i for i in range(len(names)) if i not in set(held_out_views(len(names)))]
    angles = nearest_angles_deg(novel.directions, cameras.centres()[train])
    writer.extra["novel"] = {
        "directions": len(novel.directions),
        "magnifications": list(novel.magnifications),
        "views": len(novel),
        "base_focal": novel.base_focal,
        # > 1: the training views are zoomed in further than the novel views' magnification 1.
        "training_zoom": float(cameras.focal / novel.base_focal),
        "nearest_training_camera_deg": {
            "min": float(np.nanmin(angles)),
            "median": float(np.nanmedian(angles)),
            "max": float(np.nanmax(angles)),
        }
        if np.isfinite(angles).any()
        else None,
    }
