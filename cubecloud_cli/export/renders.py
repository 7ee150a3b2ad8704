"""The export's renders: CuNeRF's training views (under each transfer function of the set), the
volume's views of the same cameras, the novel views' references and the point cloud, each phase
timed, each view saved as it is done so that an interrupted export continues."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.cameras.novel import NovelViewSet, headline_views
from cubecloud_cli.core.artifacts import StageWriter, stage_dir_name
from cubecloud_cli.core.progress import ProgressCallback
from cubecloud_cli.cunerf.api import CunerfField
from cubecloud_cli.export.cunerf_bake import saved_bake
from cubecloud_cli.export.finished_views import ExportProgress
from cubecloud_cli.export.novel_references import render_novel_references
from cubecloud_cli.export.point_cloud import PointCloud, build_point_cloud
from cubecloud_cli.export.settings import ExportSettings
from cubecloud_cli.render import FunctionField, GridField, ImageModel, Support, render_view
from cubecloud_cli.render.renderer import render_view_under
from cubecloud_cli.transfer.training_set import HeldOutSet, NamedTransfer, member_slot, member_views


@dataclass(frozen=True)
class ExportJob:
    """What one export works from, checked before anything is written."""

    work: Path
    settings: ExportSettings
    cameras: PinholeCameras
    novel: NovelViewSet
    image_model: ImageModel
    preprocess: dict  # the preprocess manifest
    cunerf: dict  # the cunerf manifest
    size: int  # the volume's side in voxels
    device: torch.device
    cunerf_name: str | None
    transfers: tuple[NamedTransfer, ...]  # the training views' transfer functions; the first is image_model's
    held_out: HeldOutSet | None = None  # those the novel views are also rendered under, for eval

    @property
    def cunerf_dir(self) -> Path:
        return self.work / stage_dir_name("cunerf", self.cunerf_name)

    @property
    def training_renders(self) -> int:
        """The training views rendered: all under the export's own transfer function, a share under each other."""
        others = len(member_views(1, self.settings.transfer_stride, len(self.cameras)))
        return len(self.cameras) + (len(self.transfers) - 1) * others

    @property
    def held_out_views(self) -> NovelViewSet:
        """The novel views the held-out transfer functions are rendered at: eval scores them at
        the headline magnifications only (0.75–1.33×)."""
        return headline_views(self.novel)

    @property
    def total_views(self) -> int:
        held_out = len(self.held_out.transfers) if self.held_out else 0
        return self.training_renders + len(self.cameras) + len(self.novel) + held_out * len(self.held_out_views)


@dataclass
class ExportRenders:
    """The rendered views and the point cloud, ready to be written."""

    images: np.ndarray  # CuNeRF's renders: the training images
    transfer_images: np.ndarray | None  # (K, N, H, W) under each training transfer function, K > 1
    reference: np.ndarray  # the volume's renders of the same views
    novel_reference: np.ndarray
    held_out_references: list[tuple[NamedTransfer, np.ndarray]]  # the novel views under each held-out one
    cloud: PointCloud


def render_export(
    job: ExportJob,
    volume: np.ndarray,
    field: CunerfField,
    writer: StageWriter,
    progress: ExportProgress,
    on_progress: ProgressCallback,
) -> ExportRenders:
    """CuNeRF's views, the volume's views and novel references, and the point cloud, each phase timed."""
    cameras, device, views = job.cameras, job.device, job.total_views

    def count_views(phase: str, before: int):
        return lambda done, total: on_progress(phase, before + done, views, {})

    with writer.phase("bake"):
        on_progress("bake", 0, views, {})
        cunerf_images_field = _cunerf_scalar_field(field, job, writer, progress, on_progress)
    with writer.phase("render_images"):
        images = _render_saving_views(
            cunerf_images_field, cameras, job.image_model, device, progress, "images", count_views("images", 0)
        )
    transfer_images = None
    if len(job.transfers) > 1:
        with writer.phase("render_transfers"):
            stride = job.settings.transfer_stride
            members = _render_members_by_view(
                cunerf_images_field, job, device, progress, count_views("transfers", len(cameras))
            )
            transfer_images = np.stack([images[member_views(0, stride, len(cameras))], *members])
    rendered = job.training_renders
    # One field for both: its support and clear cells are made once.
    volume_field = GridField(volume, device)
    with writer.phase("render_reference"):
        reference = _render_saving_views(
            volume_field,
            cameras,
            job.image_model,
            device,
            progress,
            "reference",
            count_views("reference", rendered),
        )
    with writer.phase("render_novel"):
        # The novel views face the origin: a stack's per-view slice planes do not apply to them.
        novel_reference = render_novel_references(
            volume_field,
            job.novel,
            [replace(job.image_model, slice_offsets=())],
            device,
            progress,
            count_views("novel", rendered + len(cameras)),
        )[0]
    held_out = []
    if job.held_out and job.held_out.transfers:
        with writer.phase("render_held_out"):
            held_out = _held_out_references(
                volume_field, job, progress, count_views("held-out", rendered + len(cameras) + len(job.novel))
            )
    with writer.phase("point_cloud"):
        on_progress("points", views, views, {})
        cloud = _cube_cloud(field, cunerf_images_field, job)
    return ExportRenders(images, transfer_images, reference, novel_reference, held_out, cloud)


def _held_out_references(
    volume_field: GridField, job: ExportJob, progress: ExportProgress, on_views: Callable[[int, int], None]
) -> list[tuple[NamedTransfer, np.ndarray]]:
    """The volume under each held-out transfer function at the headline novel views, for eval."""
    transfers = job.held_out.transfers
    references = render_novel_references(
        volume_field,
        job.held_out_views,
        [replace(job.image_model, transfer=named.function, slice_offsets=()) for named in transfers],
        job.device,
        progress,
        on_views,
        # Saved under another prefix than the all-magnification views of earlier exports.
        prefixes=[f"held_out_{index}_headline" for index in range(len(transfers))],
    )
    return list(zip(transfers, references))


def _cube_cloud(field: CunerfField, images_field, job: ExportJob) -> PointCloud:
    """The Cube-Cloud points, sampled cube by cube from CuNeRF's intensity and density, the budget
    steered by the gradient of the field the training views were rendered from."""
    settings = job.settings
    return build_point_cloud(
        field.cube_values,
        field.point_density,
        images_field,
        job.size,
        settings.cube,
        settings.points_per_cube,
        settings.max_points or None,
        settings.air_threshold,
        settings.seed,
        job.device,
    )


def _render_saving_views(
    field,
    cameras: PinholeCameras,
    model: ImageModel,
    device: torch.device,
    progress: ExportProgress,
    prefix: str,
    on_progress,
) -> np.ndarray:
    """render_views, saving each view as it is done and reusing views an interrupted run saved."""
    images = np.empty((len(cameras), cameras.height, cameras.width), dtype=np.float32)
    support = None
    with torch.no_grad():
        for index in range(len(cameras)):
            saved = progress.load(f"{prefix}_view_{index:05d}")
            if saved is not None and saved.shape == images.shape[1:]:
                images[index] = saved
            else:
                if support is None and model.kind != "slice":
                    support = field.support(model.support_threshold)
                images[index] = render_view(field, cameras, index, model, support, device).cpu().numpy()
                progress.save(f"{prefix}_view_{index:05d}", images[index])
            on_progress(index + 1, len(cameras))
    return images


def _render_members_by_view(field, job: ExportJob, device, progress: ExportProgress, on_progress) -> list[np.ndarray]:
    """The training views under each member of the transfer-function set after the first, at the
    member's share of the views (:func:`member_views`), as (views // stride, H, W) per member.
    A view's members are marched together: each voxel on a ray is read once for all of them."""
    cameras, stride = job.cameras, job.settings.transfer_stride
    members = range(1, len(job.transfers))
    models = {m: replace(job.image_model, transfer=job.transfers[m].function) for m in members}
    shares = {m: set(member_views(m, stride, len(cameras))) for m in members}
    images = {m: np.empty((len(shares[m]), cameras.height, cameras.width), dtype=np.float32) for m in members}
    supports, done, total = {}, 0, sum(len(share) for share in shares.values())
    # A strided member's saved views are its own: an export resumed with another stride redraws them.
    prefix = "tf{}" if stride == 1 else f"tf{{}}_every{stride}"
    with torch.no_grad():
        for view in range(len(cameras)):
            shown = [m for m in members if view in shares[m]]
            slots = [member_slot(m, view, stride) for m in shown]
            names = [f"{prefix.format(m)}_view_{slot:05d}" for m, slot in zip(shown, slots)]
            saved, missing = progress.load_views(names, (cameras.height, cameras.width))
            for position, image in saved.items():
                images[shown[position]][slots[position]] = image
            if missing:
                drawn = [shown[position] for position in missing]
                for m in drawn:
                    if m not in supports:
                        supports[m] = field.support(models[m].support_threshold)
                rendered = render_view_under(
                    field, cameras, view, [models[m] for m in drawn], [supports[m] for m in drawn], device
                )
                for position, image in zip(missing, rendered.cpu().numpy()):
                    images[shown[position]][slots[position]] = image
                    progress.save(names[position], image)
            done += len(shown)
            on_progress(done, total)
    return [images[m] for m in members]


def _cunerf_scalar_field(
    field: CunerfField, job: ExportJob, writer: StageWriter, progress: ExportProgress, on_progress
):
    """The field the training images are rendered from: CuNeRF baked to a grid (fast; the
    cunerf stage's own bake where it is the same grid), or its cube renders queried at every ray
    sample (``--render-from field``)."""
    settings, size, device = job.settings, job.size, job.device
    if settings.render_from == "grid":
        bake_size = settings.bake_resolution(size)
        baked = progress.load("bake")
        if baked is None or baked.shape != (bake_size,) * 3:
            saved = saved_bake(job.cunerf_dir, job.cunerf, bake_size, device)
            if saved is not None:  # its hash checked against the cunerf manifest: recorded, not taken again
                baked, path, digest = saved
                writer.add_input(path, f"{job.cunerf_dir.name}/{path.name}", digest)
            else:
                baked = field.bake(bake_size, on_progress=lambda f: on_progress("bake", f, 1.0, {}))
            progress.save("bake", baked)  # a resumed export renders from this grid, whatever its threads
        return GridField(baked, device)
    occupancy = field.occupancy
    if occupancy is not None and occupancy.blocks.shape[0] * occupancy.block == size:
        # The field reads exactly 0 in air blocks (their renders are skipped), so they need no marching.
        support = Support.from_blocks(occupancy.blocks.to(device))
    else:
        support = Support.everywhere(device)
    return FunctionField(field.cube_values, size, support)
