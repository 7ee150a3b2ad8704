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

from typing import Callable, Iterator, Sequence

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
    supports = None if support is None else [support]
    return render_view_under(field, cameras, index, [model], supports, device, subpixel)[0]


def render_view_under(
    field: ScalarField,
    cameras: PinholeCameras,
    index: int,
    models: Sequence[ImageModel],
    supports: Sequence[Support] | None = None,
    device: torch.device | str = "cpu",
    subpixel: tuple[float, float] = (0.5, 0.5),
) -> torch.Tensor:
    """(K, H, W): image ``index`` under each of K image models (``supports[j]`` the support of
    ``models[j]``'s threshold, made here where not given). ``dvr`` through a grid on the CPU
    marches each ray once for each of :func:`march_groups` (each image to the bit as alone);
    other models render one image after another."""
    device = torch.device(device)
    if supports is None:
        supports = [None if model.kind == "slice" else field.support(model.support_threshold) for model in models]
    if len(models) > 1 and not fused_grid_dvr(field, models, device):
        return torch.stack(
            [render_view_under(field, cameras, index, [m], [s], device, subpixel)[0] for m, s in zip(models, supports)]
        )
    origin, directions = camera_rays(cameras, index, device, subpixel)
    if fused_grid_dvr(field, models, device):
        # The kernel walks the air inside the support's box faster than the coarse march that
        # finds each ray's support interval (support_interval) takes; it takes the rays tile by
        # tile, which changes no ray (rays.RAY_TILE).
        order = torch.from_numpy(tiled_order(cameras.height, cameras.width))
        colour = torch.empty(len(models), directions.shape[0])
        colour[:, order] = march_grid_view(field, models, origin, directions[order].contiguous(), supports)
        return colour.clamp(0.0, 1.0).view(len(models), cameras.height, cameras.width)
    return _render_one(field, cameras, index, models[0], supports[0], origin, directions)[None]


def _render_one(field, cameras, index, model, support, origin, directions) -> torch.Tensor:
    """One image through the torch march or the slice planes."""
    if model.kind == "slice":
        normal = torch.as_tensor(cameras.rotations[index][2], dtype=torch.float32, device=directions.device)
        values = torch.cat(
            [
                slice_plane_values(field, origin, directions[s : s + RAYS_PER_CHUNK], normal, model.slice_offset(index))
                for s in range(0, directions.shape[0], RAYS_PER_CHUNK)
            ]
        )
        return values.view(cameras.height, cameras.width)
    cube_low = torch.full((3,), -1.0, device=directions.device)
    entry, exit_ = ray_box(origin, directions, cube_low, -cube_low)
    accumulator = ACCUMULATORS[model.kind](model, directions.shape[0], directions.device)
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


def fused_grid_dvr(field, models: Sequence[ImageModel], device: torch.device) -> bool:
    """Whether the numba march applies: dvr through a voxel grid, on the CPU, every model with
    the same ray step and termination."""
    return (
        isinstance(field, GridField)
        and device.type == "cpu"
        and all(model.kind == "dvr" for model in models)
        and len({(model.step, model.termination) for model in models}) == 1
    )


# A model joins a march whose lowest ``low`` leaves at most this many times the cells its own
# leaves to read: a march reads every cell that is not clear for its lowest member.
SHARED_MARCH_CELLS = 3.0


def march_groups(field: GridField, models: Sequence[ImageModel]) -> list[list[int]]:
    """The models' indices in groups that march together, by ``low``: a model that would read
    far fewer cells alone (a bone window beside a lung window) marches apart."""
    by_low = sorted(range(len(models)), key=lambda j: models[j].transfer.low)
    groups: list[list[int]] = []
    cells = None
    for j in by_low:
        read = int(np.count_nonzero(~field.clear_cells(float(models[j].transfer.low))))
        if groups and read * SHARED_MARCH_CELLS >= cells:
            groups[-1].append(j)
        else:
            groups.append([j])
            cells = read
    return groups


def march_grid_view(
    field: GridField, models: Sequence[ImageModel], origin, directions, supports: Sequence[Support]
) -> torch.Tensor:
    """(K, R): one view's rays under K dvr models, one numba march for each of
    :func:`march_groups`."""
    colours = torch.empty(len(models), directions.shape[0])
    for group in march_groups(field, models):
        marched = march_grid_group(field, [models[j] for j in group], origin, directions, [supports[j] for j in group])
        colours[torch.tensor(group)] = marched
    return colours


def march_grid_group(
    field: GridField, models: Sequence[ImageModel], origin, directions, supports: Sequence[Support]
) -> torch.Tensor:
    """(K, R): one view's rays set up and marched in one numba pass under K dvr models (at 256²
    the torch set-up between chunks took as long as the march itself), each voxel read once for
    all K."""
    bounds = [support.bounds() for support in supports]
    lowest = min(float(model.transfer.low) for model in models)
    colours = dvr_view(
        field.volume.numpy(),
        field.clear_cells(lowest),
        CELL_SHIFT,
        origin.double().numpy(),
        directions.numpy(),
        np.stack([low.numpy() for low, _ in bounds]).astype(np.float32),
        np.stack([high.numpy() for _, high in bounds]).astype(np.float32),
        float(models[0].step),
        np.array([model.transfer.march_parameters() for model in models], dtype=np.float64),
        float(models[0].termination),
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
