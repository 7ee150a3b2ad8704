"""One renderer for every image model and every field (docs/design.md §3).

The same code draws the reference images from the preprocessed volume and the training images
from CuNeRF, so the two differ only by their fields. Marching models sample each ray at
t_k = t_entry + (k + ½)Δ from where it enters the cube, so both fields are sampled at the same
points; the runs of the ray outside the field's support are skipped, which changes no pixel.

`dvr` through a voxel grid on the CPU (the volume, and CuNeRF baked to a grid, the default) runs
as one numba kernel (``grid_march.py``) with the same sums; it agrees with the torch march to
float32 rounding and the termination bound, so a CuNeRF field rendered point by point
(``--render-from field``, the torch march) and the grid references still differ only by their
fields, to within 1e-4.
"""

from __future__ import annotations

from typing import Callable, Iterator

import numpy as np
import torch

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.render.grid_march import CELL_SHIFT, dvr_view
from cubecloud_cli.render.image_models import ACCUMULATORS, ImageModel
from cubecloud_cli.render.rays import camera_rays, ray_box, tiled_order
from cubecloud_cli.render.samplers import GridField, ScalarField, Support

RAYS_PER_CHUNK = 1 << 14
STEPS_PER_BLOCK = 32


def slice_plane_values(
    field: ScalarField, origin: torch.Tensor, directions: torch.Tensor, normal: torch.Tensor, offset: float = 0.0
) -> torch.Tensor:
    """The field where each ray meets the plane {p : p·normal = offset} (unit normal)."""
    facing = directions @ normal
    # Rays inside the field of view have facing = cos(angle to the optical axis) > 0; the guard
    # keeps a grazing ray finite (it lands far outside the cube, where the field is 0).
    facing = torch.where(facing.abs() < 1e-12, torch.full_like(facing, 1e-12), facing)
    t = (offset - origin @ normal) / facing
    return field(origin + t[:, None] * directions)


def support_interval(
    support: Support, origin: torch.Tensor, directions: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """A [start, stop) distance interval per ray that holds every sample in the support."""
    low, high = support.bounds()
    start, stop = ray_box(origin, directions, low, high)
    hit = start < stop
    if not hit.any():
        return start, start
    # A coarse march finds the first and last support block on each ray. Support blocks carry
    # a margin one block thick, so steps just shorter than a block cannot jump over it.
    step = 0.95 * support.block_size
    count = int(torch.ceil(((stop - start)[hit]).max() / step).item()) + 1
    offsets = (torch.arange(count, device=directions.device) + 0.5) * step
    t = start[hit, None] + offsets
    points = origin + t[..., None] * directions[hit, None, :]
    inside = support.contains(points.reshape(-1, 3)).view(-1, count) & (t < stop[hit, None])
    any_inside = inside.any(dim=1)
    first = inside.float().argmax(dim=1)
    last = count - 1 - inside.flip(1).float().argmax(dim=1)
    refined_start = start.clone()
    refined_stop = start.clone()  # empty unless a block is hit
    refined_start[hit] = torch.where(any_inside, start[hit] + offsets[first] - step, start[hit])
    refined_stop[hit] = torch.where(any_inside, start[hit] + offsets[last] + step, start[hit])
    return refined_start.clamp_min(0.0), refined_stop


def render_view(
    field: ScalarField,
    cameras: PinholeCameras,
    index: int,
    model: ImageModel,
    support: Support | None = None,
    device: torch.device | str = "cpu",
    subpixel: tuple[float, float] = (0.5, 0.5),
) -> torch.Tensor:
    """Image ``index`` of ``cameras`` as an (H, W) float tensor in [0, 1], each pixel sampled at
    its centre, or at another point ``subpixel`` of it (fractions of a pixel from its corner)."""
    device = torch.device(device)
    origin, directions = camera_rays(cameras, index, device, subpixel)
    if model.kind == "slice":
        normal = torch.as_tensor(cameras.rotations[index][2], dtype=torch.float32, device=device)
        values = torch.cat(
            [
                slice_plane_values(field, origin, directions[s : s + RAYS_PER_CHUNK], normal, model.slice_offset(index))
                for s in range(0, directions.shape[0], RAYS_PER_CHUNK)
            ]
        )
        return values.view(cameras.height, cameras.width)

    if support is None:
        support = field.support(model.support_threshold)
    if fused_grid_dvr(field, model, device):
        # The kernel walks the air inside the support's box faster than the coarse march that
        # finds each ray's support interval (support_interval) takes; it takes the rays tile by
        # tile, which changes no ray (rays.RAY_TILE).
        order = torch.from_numpy(tiled_order(cameras.height, cameras.width))
        colour = torch.empty(directions.shape[0])
        colour[order] = march_grid_view(field, model, origin, directions[order].contiguous(), support)
        return colour.clamp(0.0, 1.0).view(cameras.height, cameras.width)
    cube_low = torch.full((3,), -1.0, device=device)
    entry, exit_ = ray_box(origin, directions, cube_low, -cube_low)
    accumulator = ACCUMULATORS[model.kind](model, directions.shape[0], device)
    for rays, first, last in _ray_chunks(support, model, origin, directions, entry, exit_):
        _march(field, model, accumulator, rays, origin, directions, entry, first, last)
    return accumulator.result().clamp(0.0, 1.0).view(cameras.height, cameras.width)


def _ray_chunks(support, model, origin, directions, entry, exit_) -> Iterator[tuple[torch.Tensor, ...]]:
    """Per chunk of rays: their indices and the first and last (exclusive) sample each needs,
    from where each ray meets the support."""
    for begin in range(0, directions.shape[0], RAYS_PER_CHUNK):
        rays = torch.arange(begin, min(begin + RAYS_PER_CHUNK, directions.shape[0]), device=directions.device)
        start, stop = support_interval(support, origin, directions[rays])
        stop = torch.minimum(stop, exit_[rays])
        first = torch.floor((start - entry[rays]) / model.step - 0.5).clamp_min(0).long()
        last = torch.ceil((stop - entry[rays]) / model.step - 0.5).long()  # exclusive
        yield rays, first, last


def fused_grid_dvr(field, model: ImageModel, device: torch.device) -> bool:
    """Whether the numba march applies: dvr through a voxel grid, on the CPU."""
    return model.kind == "dvr" and isinstance(field, GridField) and device.type == "cpu"


def march_grid_view(field: GridField, model: ImageModel, origin, directions, support: Support) -> torch.Tensor:
    """One view's rays set up and marched in one numba pass: at 256² the torch set-up between
    chunks took as long as the march itself."""
    transfer = model.transfer
    low, high = support.bounds()
    colours = dvr_view(
        field.volume.numpy(),
        field.clear_cells(float(transfer.low)),
        CELL_SHIFT,
        origin.double().numpy(),
        directions.numpy(),
        low.numpy().astype(np.float32),
        high.numpy().astype(np.float32),
        float(model.step),
        transfer.march_parameters(),
        float(model.termination),
        STEPS_PER_BLOCK,
    )
    return torch.from_numpy(colours)


def _march(field, model, accumulator, rays, origin, directions, entry, first, last) -> None:
    """Sample rays in blocks of STEPS_PER_BLOCK, dropping rays that are done."""
    live = first < last
    rays, first, last = rays[live], first[live], last[live]
    steps = torch.arange(STEPS_PER_BLOCK, device=rays.device)
    while rays.numel():
        k = first[:, None] + steps
        t = entry[rays, None] + (k.float() + 0.5) * model.step
        points = origin + t[..., None] * directions[rays, None, :]
        values = field(points.reshape(-1, 3)).view(-1, STEPS_PER_BLOCK)
        values = torch.where(k < last[:, None], values, torch.zeros_like(values))
        accumulator.add(rays, values)
        first = first + STEPS_PER_BLOCK
        keep = (first < last) & ~accumulator.finished(rays)
        rays, first, last = rays[keep], first[keep], last[keep]


def render_views(
    field: ScalarField,
    cameras: PinholeCameras,
    model: ImageModel,
    device: torch.device | str = "cpu",
    on_progress: Callable[[int, int], None] = lambda done, total: None,
) -> np.ndarray:
    """All views as a (N, H, W) float32 array."""
    model.validate()
    support = None if model.kind == "slice" else field.support(model.support_threshold)
    images = np.empty((len(cameras), cameras.height, cameras.width), dtype=np.float32)
    with torch.no_grad():
        for index in range(len(cameras)):
            images[index] = render_view(field, cameras, index, model, support, device).cpu().numpy()
            on_progress(index + 1, len(cameras))
    return images
