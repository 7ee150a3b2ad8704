"""The numba dvr march through a voxel grid against the torch march it replaces on the CPU."""

import numpy as np
import pytest
import torch
from conftest import body_phantom
from hypothesis import example, given, settings
from hypothesis import strategies as st

from cubecloud_cli.cameras import OrbitSpec, PinholeCameras, orbit_cameras
from cubecloud_cli.render import grid_march, renderer
from cubecloud_cli.render.image_models import ImageModel
from cubecloud_cli.render.samplers import GridField
from cubecloud_cli.transfer.function import MIN_RAMP_WIDTH, TransferFunction


def both_marches(monkeypatch, field, cameras, index, model, subpixel=(0.5, 0.5)):
    fused = renderer.render_view(field, cameras, index, model, subpixel=subpixel)
    with monkeypatch.context() as patched:
        patched.setattr(renderer, "fused_grid_dvr", lambda *args: False)
        reference = renderer.render_view(field, cameras, index, model, subpixel=subpixel)
    return fused, reference


def padded_phantom(size=32) -> np.ndarray:
    phantom = body_phantom((size - 6, size - 8, size - 10)).astype(np.float32)
    volume = np.zeros((size,) * 3, dtype=np.float32)
    volume[3:-3, 4:-4, 5:-5] = phantom / max(phantom.max(), 1e-6)
    return volume


@pytest.mark.parametrize(
    "index, transfer",
    [
        (0, TransferFunction(0.2, 0.7, 8.0)),
        (3, TransferFunction(0.2, 0.7, 8.0)),
        (7, TransferFunction(0.2, 0.7, 8.0)),
        (3, TransferFunction(0.1, 0.3, 8.0, 0.5, 0.8)),  # a band: the brightest tissue clear
        (3, TransferFunction(0.1, 0.1, 8.0, 0.6, 0.6)),  # a band with steps for sides
    ],
)
def test_the_fused_march_draws_the_torch_march_s_image(monkeypatch, index, transfer):
    field = GridField(padded_phantom())
    cameras = orbit_cameras(OrbitSpec(views=8, resolution=32, elevation=20.0))
    model = ImageModel("dvr", transfer, step=2.0 / 32)
    fused, reference = both_marches(monkeypatch, field, cameras, index, model, subpixel=(0.25, 0.75))
    assert reference.max() > 0.2  # the body is in view
    # float32 rounding: the band's product is formed in another order (2.01e-6 seen)
    assert torch.allclose(fused, reference, atol=3e-6, rtol=0)


def test_an_opaque_volume_stops_each_ray_where_the_torch_march_does(monkeypatch):
    """Transmittance falls below 1e-4 at the first sample; both stop after that sample's block,
    and a ray's colour is the value where it entered (about ½ at the cube's face)."""
    field = GridField(np.ones((16, 16, 16), dtype=np.float32))
    cameras = orbit_cameras(OrbitSpec(views=4, resolution=16))
    model = ImageModel("dvr", TransferFunction(0.0, 0.0, 1e5), step=2.0 / 64)
    fused, reference = both_marches(monkeypatch, field, cameras, 1, model)
    assert torch.allclose(fused, reference, atol=2e-6, rtol=0) and 0.4 < fused.max() <= 1.0


def camera_inside(position) -> PinholeCameras:
    """A camera at ``position`` looking along +z."""
    rotation = np.eye(3)[None]
    return PinholeCameras(rotation, -(rotation[0] @ np.asarray(position, dtype=np.float64))[None], 16, 16, 12.0)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    low=st.floats(0.0, 1.0),
    width=st.sampled_from([0.0, 1e-9, 1e-3, 0.5]),
    density=st.sampled_from([0.0, 1e-6, 1.0, 50.0, 9.9e5]),
    inside=st.booleans(),
)
@example(seed=0, low=0.0, width=0.0, density=9.9e5, inside=True)
@example(seed=35993, low=0.3125, width=1e-3, density=50.0, inside=False)
@example(seed=19957, low=0.8671875, width=0.5, density=50.0, inside=False)
@example(seed=17927, low=0.625, width=1e-3, density=50.0, inside=False)
def test_fused_march_matches_and_stays_in_range_at_the_extremes(seed, low, width, density, inside):
    rng = np.random.default_rng(seed)
    volume = rng.choice([0.0, 1.0, 0.5], size=(8, 8, 8)).astype(np.float32) * (rng.random((8, 8, 8)) > 0.3)
    field = GridField(volume)
    cameras = camera_inside((0.1, -0.2, -0.3)) if inside else orbit_cameras(OrbitSpec(views=3, resolution=16))
    model = ImageModel("dvr", TransferFunction(low, min(low + width, 1.0), density), step=2.0 / 16)
    model.validate()
    fused = renderer.render_view(field, cameras, 0, model)
    original = renderer.fused_grid_dvr
    renderer.fused_grid_dvr = lambda *args: False
    try:
        reference = renderer.render_view(field, cameras, 0, model)
    finally:
        renderer.fused_grid_dvr = original
    assert torch.isfinite(fused).all() and fused.min() >= 0.0 and fused.max() <= 1.0
    # The two may stop a ray a block apart, once less than `termination` of its light is left
    # (the fused march starts its blocks where the ray enters the support's box). Beyond that,
    # the torch march samples in float32 and this one in float64: a rounding of a sample's
    # position or value moves its opacity by up to density·step/width times as much, so a
    # narrow ramp or a dense medium is ill-conditioned, and a step (width → 0) can flip a sample.
    sensitivity = (1.0 + density * model.step) / max(width, MIN_RAMP_WIDTH)
    if sensitivity < 1e5:
        assert torch.allclose(fused, reference, atol=model.termination + 2e-6 * sensitivity, rtol=0)


def brute_clear_cells(volume: np.ndarray, low: float, shift: int) -> np.ndarray:
    """The definition: a cell is clear when the voxels of [c·n, c·n + n] on each axis are all
    below low − margin (and so is the air beyond the grid, 0)."""
    n, size = 1 << shift, volume.shape[0]
    cells = -(-size // n)
    clear = np.zeros((cells,) * 3, dtype=bool)
    for a, b, c in np.ndindex(clear.shape):
        block = volume[a * n : a * n + n + 1, b * n : b * n + n + 1, c * n : c * n + n + 1]
        clear[a, b, c] = max(float(block.max()), 0.0) <= low - grid_march.CLEAR_MARGIN
    return clear


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**16), size=st.sampled_from([7, 8, 13, 16]), shift=st.sampled_from([1, 2, 3]))
def test_clear_cells_are_the_cells_whose_every_readable_voxel_is_clear(seed, size, shift):
    rng = np.random.default_rng(seed)
    volume = (rng.random((size,) * 3) * (rng.random((size,) * 3) > 0.9)).astype(np.float32)
    low = float(rng.choice([0.0, 1e-7, 0.3, 0.95]))
    np.testing.assert_array_equal(grid_march.clear_cells(volume, low, shift), brute_clear_cells(volume, low, shift))


def march_with(field, cameras, index, model, clear) -> np.ndarray:
    origin, directions = renderer.camera_rays(cameras, index, torch.device("cpu"))
    low, high = field.support(model.support_threshold).bounds()
    transfer = model.transfer
    return grid_march.dvr_view(
        field.volume.numpy(), clear, grid_march.CELL_SHIFT, origin.double().numpy(), directions.numpy(),
        low.numpy().astype(np.float32)[None], high.numpy().astype(np.float32)[None], float(model.step),
        np.array([transfer.march_parameters()]), float(model.termination), renderer.STEPS_PER_BLOCK,
    )[0]  # fmt: skip


@settings(max_examples=20, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    low=st.sampled_from([0.05, 0.4, 0.8]),
    density=st.sampled_from([1.0, 40.0, 1e4]),
    axis_aligned=st.booleans(),
)
def test_stepping_over_clear_cells_changes_no_colour(seed, low, density, axis_aligned):
    """Sparse blobs in air, seen along the axes (direction components exactly 0) or at random:
    the march with clear cells gives the colours of the march that reads every sample, bit for
    bit, dense media stopping rays included."""
    rng = np.random.default_rng(seed)
    size = 40
    volume = np.zeros((size,) * 3, dtype=np.float32)
    for blob in range(4):
        corner = rng.integers(0, size - 8, 3)
        sides = rng.integers(5 if blob == 0 else 2, 8, 3)  # the first one bright and large enough to be hit
        volume[tuple(slice(c, c + side) for c, side in zip(corner, sides))] = 1.0 if blob == 0 else rng.uniform(0.2, 1)
    field = GridField(volume)
    if axis_aligned:
        cameras = PinholeCameras(np.eye(3)[None], np.array([[0.0, 0.0, 4.0]]), 24, 24, 30.0)
    else:
        cameras = orbit_cameras(OrbitSpec(views=5, resolution=24, elevation=float(rng.uniform(-60, 60))))
    model = ImageModel("dvr", TransferFunction(low, min(low + 0.3, 1.0), density), step=2.0 / (size * 1.7))
    clear = field.clear_cells(low)
    assert clear.any() and not clear.all()
    with_cells = march_with(field, cameras, 0, model, clear)
    np.testing.assert_array_equal(with_cells, march_with(field, cameras, 0, model, np.zeros_like(clear)))
    assert with_cells.max() > 0.0


def test_a_ray_that_goes_dark_stops_at_its_block_s_end_even_inside_a_clear_cell():
    """Two slabs across z with air between: after the first, under 1e-4 of the light is left, so
    the march stops at the end of that sample block, which lies in the air. Stepping over the
    air must stop there too, not go on to add the second slab's light (about 3e-5)."""
    size = 40
    volume = np.zeros((size,) * 3, dtype=np.float32)
    volume[:, :, 2:6] = 1.0
    volume[:, :, 36:40] = 1.0  # beyond the first block of 32 steps, which ends in the air
    field = GridField(volume)
    cameras = PinholeCameras(np.eye(3)[None], np.array([[0.0, 0.0, 4.0]]), 8, 8, 20.0)  # every ray crosses both
    model = ImageModel("dvr", TransferFunction(0.4, 0.7, 52.0), step=2.0 / size)
    clear = field.clear_cells(0.4)
    assert clear[:, :, 1:4].all() and not clear[:, :, 0].any()  # cells of 8: the air between is clear
    every_sample = march_with(field, cameras, 0, model, np.zeros_like(clear))
    np.testing.assert_array_equal(march_with(field, cameras, 0, model, clear), every_sample)
    light_left = np.exp(-52.0 * 0.2)  # four voxels of 0.05 at full absorption
    assert light_left < model.termination and every_sample.min() > 0.5


def transfer_from(draw) -> TransferFunction:
    """A ramp or a band anywhere over [0, 1], steps and dense media included."""
    low, high, fall_low, fall_high = sorted(draw[:4])
    density = float(draw[4])
    if draw[5] < 0.5:
        return TransferFunction(low, high, density)
    return TransferFunction(low, high, density, fall_low, fall_high)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**16),
    functions=st.integers(1, 6),
    density=st.sampled_from([0.5, 40.0, 9.9e5]),
    steps=st.sampled_from([0.0, 0.5]),
)
@example(seed=1, functions=3, density=9.9e5, steps=0.5)
def test_a_march_under_several_transfer_functions_is_each_march_alone_to_the_bit(seed, functions, density, steps):
    """Sparse blobs in air under K transfer functions at once, each with its own support box (so
    its own first sample and blocks): the colours are those of K marches with each function's
    own clear cells, bit for bit, rays that go dark at different blocks included."""
    rng = np.random.default_rng(seed)
    size = 40  # clear cells of 8 voxels between the blobs
    volume = np.zeros((size,) * 3, dtype=np.float32)
    for _ in range(5):
        corner, sides = rng.integers(0, size - 8, 3), rng.integers(2, 8, 3)
        volume[tuple(slice(c, c + side) for c, side in zip(corner, sides))] = rng.uniform(0.05, 1.0)
    field = GridField(volume)
    cameras = orbit_cameras(OrbitSpec(views=3, resolution=24, elevation=float(rng.uniform(-60, 60))))
    transfers = [TransferFunction(0.01, 0.3, density)]  # one that shows every blob
    for _ in range(functions - 1):
        draw = rng.uniform(size=6)
        draw[4] = density * rng.uniform(0.5, 1.0)
        transfers.append(transfer_from(draw) if rng.uniform() > steps else TransferFunction(draw[0], draw[0], draw[4]))
    models = [ImageModel("dvr", transfer, step=2.0 / (size * 1.3)) for transfer in transfers]
    supports = [field.support(model.support_threshold) for model in models]
    with pytest.MonkeyPatch.context() as patched:
        patched.setattr(renderer, "STEPS_PER_BLOCK", 3)  # many blocks on a ray: rays go dark between blobs
        together = renderer.march_grid_group(
            field, models, *renderer.camera_rays(cameras, 1, torch.device("cpu")), supports
        ).numpy()
        assert together.shape == (functions, 24 * 24)
        for j, model in enumerate(models):
            alone = march_with(field, cameras, 1, model, field.clear_cells(model.transfer.low))
            np.testing.assert_array_equal(together[j], alone)
    assert together[0].max() > 0.0


def test_a_view_under_several_models_is_each_model_s_image():
    """Grouped marches for dvr through a grid; mip and slice models one image after another."""
    field = GridField(padded_phantom(24))
    cameras = orbit_cameras(OrbitSpec(views=4, resolution=16, elevation=25.0))
    dvr = [ImageModel("dvr", TransferFunction(low, low + 0.2, 9.0), step=2.0 / 24) for low in (0.05, 0.1, 0.5, 0.7)]
    for models in (dvr, [ImageModel("mip", step=2.0 / 24), ImageModel("slice"), dvr[2]]):
        images = renderer.render_view_under(field, cameras, 2, models)
        for image, model in zip(images, models):
            assert torch.equal(image, renderer.render_view(field, cameras, 2, model))
        assert all(float(image.max()) > 0.1 for image in images)


def test_march_groups_keep_a_model_that_reads_far_fewer_cells_apart():
    """A lung window beside a bone window: the bone window alone reads a fraction of the cells
    the lung window reads, so it marches apart; two close windows march together."""
    volume = np.zeros((32,) * 3, dtype=np.float32)
    volume[4:28, 4:28, 4:28] = 0.3  # soft tissue
    volume[12:16, 12:16, 12:16] = 0.9  # a bone
    field = GridField(volume)
    windows = [(0.05, 0.1), (0.5, 0.6), (0.06, 0.12), (0.55, 0.7)]
    models = [ImageModel("dvr", TransferFunction(low, high, 5.0)) for low, high in windows]
    groups = renderer.march_groups(field, models)
    assert sorted(map(sorted, groups)) == [[0, 2], [1, 3]]
    assert renderer.march_groups(field, models[:1]) == [[0]]
