"""The renderer: image models against closed forms, skipping that changes no pixel, extremes."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
from cubecloud_cli.render import GridField, ImageModel, render_views
from cubecloud_cli.render.rays import ray_box
from cubecloud_cli.transfer.function import TransferFunction

S = 32


def blob_volume(centre_voxel=(20, 9, 23), size=S) -> np.ndarray:
    volume = np.zeros((size,) * 3, dtype=np.float32)
    i, j, k = centre_voxel
    volume[i - 1 : i + 2, j - 1 : j + 2, k - 1 : k + 2] = 0.6
    volume[i, j, k] = 1.0
    return volume


def world_of(voxel, size=S) -> np.ndarray:
    return (2.0 * np.asarray(voxel, dtype=float) + 1.0) / size - 1.0


@pytest.mark.parametrize("kind", ["dvr", "mip"])
@pytest.mark.parametrize("axis", ["si", "ap", "lr"])
def test_a_known_point_is_drawn_where_it_projects(kind, axis):
    volume = blob_volume()
    cameras = orbit_cameras(OrbitSpec(views=8, axis=axis, resolution=48, elevation=15.0))
    model = ImageModel(kind=kind, transfer=TransferFunction(0.1, 1.0, 30.0), step=1.0 / S)
    images = render_views(GridField(volume), cameras, model)
    for view in range(len(cameras)):
        pixel, _ = cameras.project(view, world_of((20, 9, 23))[None])
        row, column = np.unravel_index(np.argmax(images[view]), images[view].shape)
        assert abs(column - math.floor(pixel[0, 0])) <= 1 and abs(row - math.floor(pixel[0, 1])) <= 1


def test_slice_samples_the_plane_through_the_origin():
    # Intensity rises along x only; the first si view looks along −y, so its slice plane is y = 0.
    ramp = np.broadcast_to(np.linspace(0.05, 0.95, S, dtype=np.float32)[:, None, None], (S, S, S)).copy()
    cameras = orbit_cameras(OrbitSpec(views=4, axis="si", resolution=33))
    image = render_views(GridField(ramp), cameras, ImageModel(kind="slice"))[0]
    centre_row = image[16]
    inside = centre_row > 0
    # +x (patient's right) is on the image left; the outermost pixels fade into the air outside.
    assert np.all(np.diff(centre_row[inside][1:-1]) < 0)
    # The pixel through the origin reads the volume at the origin.
    assert image[16, 16] == pytest.approx(float(GridField(ramp)(torch.zeros(1, 3))[0]), abs=1e-6)


@pytest.mark.parametrize("radius", [1.76, 4.0, 1e4])  # from just outside the corners to the cap
def test_dvr_of_a_constant_volume_matches_the_closed_form(radius):
    value, density = 0.8, 1.3
    volume = np.full((S, S, S), value, dtype=np.float32)
    cameras = orbit_cameras(OrbitSpec(views=4, axis="si", radius=radius, resolution=33))  # odd: a pixel on the axis
    model = ImageModel(kind="dvr", transfer=TransferFunction(0.0, 1.0, density), step=2.0 / S)
    images = render_views(GridField(volume), cameras, model)
    # The central ray crosses 2 world units, its samples all on voxel centres along the axis.
    expected = value * (1.0 - math.exp(-density * value * 2.0))
    np.testing.assert_allclose(images[:, 16, 16], expected, rtol=1e-5 if radius < 100 else 1e-3)
    mip = render_views(GridField(volume), cameras, ImageModel(kind="mip", step=2.0 / S))
    np.testing.assert_allclose(mip[:, 16, 16], value, rtol=1e-6)


def brute_force(volume: np.ndarray, cameras, model: ImageModel) -> np.ndarray:
    """Every sample from cube entry to exit, no skipping and no early stop: an independent march."""
    field = GridField(volume)
    images = []
    for view in range(len(cameras)):
        origin = torch.as_tensor(cameras.centres()[view], dtype=torch.float32)
        directions = torch.as_tensor(cameras.pixel_directions(view), dtype=torch.float32)
        entry, exit_ = ray_box(origin, directions, torch.full((3,), -1.0), torch.ones(3))
        count = int(torch.ceil((exit_ - entry).max() / model.step).item()) + 1
        t = entry[:, None] + (torch.arange(count) + 0.5) * model.step
        inside = t < exit_[:, None]
        values = field((origin + t[..., None] * directions[:, None, :]).reshape(-1, 3)).view(-1, count) * inside
        if model.kind == "mip":
            pixel = values.amax(dim=1)
        else:
            alpha = 1.0 - torch.exp(-model.transfer.extinction(values) * model.step)
            transmittance = torch.cumprod(torch.cat([torch.ones(len(alpha), 1), 1.0 - alpha[:, :-1]], dim=1), dim=1)
            pixel = (transmittance * alpha * values).sum(dim=1)
        images.append(pixel.view(cameras.height, cameras.width).numpy())
    return np.stack(images)


@pytest.mark.parametrize("kind", ["dvr", "mip"])
@pytest.mark.parametrize("size", [S, 29])  # 29: support blocks overhang the volume
def test_skipping_empty_space_changes_no_pixel(kind, size):
    rng = np.random.default_rng(3)
    volume = np.zeros((size, size, size), dtype=np.float32)
    volume[6:20, 10:28, 4:14] = rng.random((14, 18, 10))
    volume[25, 3, 28] = 1.0  # an isolated voxel far from the rest
    # A cylinder cut by the z faces, as an axially cropped CT is; and a voxel in a corner.
    x, y = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    volume[(x - 20) ** 2 + (y - 20) ** 2 < 16] = 0.9
    volume[0, size - 1, 0] = 1.0
    model = ImageModel(kind=kind, transfer=TransferFunction(0.2, 0.8, 6.0), step=1.0 / size)
    for axis, elevation in (("lr", -25.0), ("si", 0.0), ("ap", 60.0)):
        cameras = orbit_cameras(OrbitSpec(views=5, axis=axis, resolution=48, elevation=elevation))
        skipped = render_views(GridField(volume), cameras, model)
        np.testing.assert_allclose(skipped, brute_force(volume, cameras, model), atol=2e-4 if kind == "dvr" else 1e-6)
        assert skipped.max() > 0.1


def test_empty_and_float16_volumes():
    one_pixel = render_views(GridField(blob_volume()), orbit_cameras(OrbitSpec(views=2, resolution=1)), ImageModel())
    assert one_pixel.shape == (2, 1, 1) and np.isfinite(one_pixel).all()
    cameras = orbit_cameras(OrbitSpec(views=2, resolution=16))
    for kind in ("dvr", "mip", "slice"):
        empty = render_views(GridField(np.zeros((S, S, S), np.float32)), cameras, ImageModel(kind=kind))
        assert empty.shape == (2, 16, 16) and not empty.any()
    volume = blob_volume()
    half = render_views(GridField(volume.astype(np.float16)), cameras, ImageModel(kind="mip"))
    single = render_views(GridField(volume), cameras, ImageModel(kind="mip"))
    np.testing.assert_allclose(half, single, atol=1e-3)


@settings(max_examples=25, deadline=None)
@given(
    low=st.floats(0.0, 1.0),
    width=st.floats(0.0, 1.0),
    density=st.sampled_from([0.0, 1e-8, 1e-3, 1.0, 50.0, 1e4, 999_999.0]),
    seed=st.integers(0, 2**16),
)
def test_dvr_stays_in_range_for_any_transfer_function(low, width, density, seed):
    volume = np.random.default_rng(seed).random((8, 8, 8)).astype(np.float32)
    transfer = TransferFunction(low, min(1.0, low + width), density)
    cameras = orbit_cameras(OrbitSpec(views=2, resolution=12))
    images = render_views(GridField(volume), cameras, ImageModel("dvr", transfer, step=0.25))
    assert np.isfinite(images).all() and images.min() >= 0.0 and images.max() <= 1.0
    if density == 0.0:
        assert not images.any()


def test_opaque_dvr_shows_the_first_surface():
    # Two slabs along the first si view's ray (camera at +y): the near one hides the far one.
    volume = np.zeros((S, S, S), dtype=np.float32)
    volume[:, 24:28, :] = 0.5  # nearer the camera (larger y)
    volume[:, 4:8, :] = 1.0
    cameras = orbit_cameras(OrbitSpec(views=2, axis="si", resolution=33))
    opaque = TransferFunction(0.4, 0.45, 1e5)  # fully opaque from 0.45 on
    image = render_views(GridField(volume), cameras, ImageModel("dvr", opaque, step=1.0 / S))[0]
    assert 0.45 <= image[16, 16] <= 0.5


def test_rays_parallel_to_box_faces():
    origin = torch.tensor([0.5, -5.0, 0.5])
    directions = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    origins = torch.stack([origin, torch.tensor([2.0, -5.0, 0.0]), origin])
    near, far = ray_box(origins, directions, torch.full((3,), -1.0), torch.ones(3))
    assert torch.isfinite(near).all() and torch.isfinite(far).all()
    assert near[0] == pytest.approx(4.0) and far[0] == pytest.approx(6.0)
    assert near[1] >= far[1]  # passes beside the box
    assert near[2] >= far[2]  # points away from it, never backwards


@pytest.mark.parametrize(
    "bad", [ImageModel(kind="xray"), ImageModel(step=0.0), ImageModel(transfer=TransferFunction(0.8, 0.2))]
)
def test_invalid_image_models_are_refused(bad):
    cameras = orbit_cameras(OrbitSpec(views=2, resolution=4))
    with pytest.raises(ValueError):
        render_views(GridField(np.zeros((4, 4, 4), np.float32)), cameras, bad)


def test_pycolmap_projects_a_point_to_the_pixel_where_we_draw_it(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    from cubecloud_cli.scene import write_colmap_model

    cameras = orbit_cameras(OrbitSpec(views=6, axis="ap", resolution=40, elevation=-20.0))
    names = [f"view_{k:03d}.png" for k in range(len(cameras))]
    write_colmap_model(tmp_path, cameras, names, np.zeros((0, 3)), np.zeros((0, 3), np.uint8))
    reconstruction = pycolmap.Reconstruction(str(tmp_path))
    model = ImageModel(kind="mip", step=1.0 / S)
    images = render_views(GridField(blob_volume()), cameras, model)
    point = world_of((20, 9, 23))
    for image in reconstruction.images.values():
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        camera = reconstruction.cameras[image.camera_id]
        pixel = np.asarray(camera.img_from_cam(pose * point)).reshape(-1)[:2]  # COLMAP: centres at +0.5
        drawn = images[names.index(image.name)]
        row, column = np.unravel_index(np.argmax(drawn), drawn.shape)
        assert (column, row) == (math.floor(pixel[0]), math.floor(pixel[1]))


def test_support_margin_reaches_outside_the_cube():
    from cubecloud_cli.render import Support

    blocks = torch.zeros(4, 4, 4, dtype=torch.bool)
    blocks[3, 1, 1] = True  # touches the x = +1 face
    support = Support.from_blocks(blocks)
    points = torch.tensor([[1.2, -0.25, -0.25], [0.1, -0.25, -0.25], [-0.1, -0.25, -0.25], [1.2, 0.9, 0.9]])
    assert support.contains(points).tolist() == [True, True, False, False]
    low, high = support.bounds()
    assert torch.allclose(low, torch.tensor([0.0, -1.0, -1.0])) and torch.allclose(high, torch.tensor([1.5, 0.5, 0.5]))
    everywhere = Support.everywhere()
    assert everywhere.contains(torch.tensor([[-1.9, 0.0, 1.9], [0.0, 0.0, 0.0]])).all()
    empty = Support.from_blocks(torch.zeros(2, 2, 2, dtype=torch.bool))
    assert not empty.contains(torch.zeros(1, 3)).any()


@pytest.mark.parametrize("size", [5, 8, 16, 19, 33])
def test_the_support_found_row_by_row_is_the_one_pass_max_pool(size):
    import torch.nn.functional as F

    from cubecloud_cli.render.samplers import SUPPORT_BLOCK, Support, support_of_volume

    rng = np.random.default_rng(size)
    volume = torch.from_numpy((rng.random((size,) * 3) < 0.02).astype(np.float32))
    count = -(-size // SUPPORT_BLOCK)
    padded = F.pad((volume > 0.5).float()[None, None], (1, count * SUPPORT_BLOCK - size + 1) * 3)
    pooled = F.max_pool3d(padded, kernel_size=SUPPORT_BLOCK + 2, stride=SUPPORT_BLOCK)[0, 0, :count, :count, :count]
    expected = Support.from_blocks(pooled > 0, extent=2.0 * count * SUPPORT_BLOCK / size)
    got = support_of_volume(volume, 0.5)
    assert torch.equal(got.blocks, expected.blocks) and (got.origin, got.extent) == (expected.origin, expected.extent)


def test_a_memory_mapped_volume_renders_as_the_loaded_one_without_a_copy(tmp_path):
    volume = blob_volume()
    np.save(tmp_path / "volume.npy", volume)
    mapped = np.load(tmp_path / "volume.npy", mmap_mode="r")
    field = GridField(mapped)
    assert np.shares_memory(field.volume.numpy(), mapped)
    cameras = orbit_cameras(OrbitSpec(views=2, resolution=24))
    np.testing.assert_array_equal(
        render_views(field, cameras, ImageModel()), render_views(GridField(volume.copy()), cameras, ImageModel())
    )
