"""The numba dvr march through a voxel grid against the torch march it replaces on the CPU."""

import numpy as np
import pytest
import torch
from conftest import body_phantom
from hypothesis import example, given, settings
from hypothesis import strategies as st

from cubecloud_cli.cameras import OrbitSpec, PinholeCameras, orbit_cameras
from cubecloud_cli.render import renderer
from cubecloud_cli.render.image_models import MIN_RAMP_WIDTH, ImageModel, TransferFunction
from cubecloud_cli.render.samplers import GridField


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


@pytest.mark.parametrize("index", [0, 3, 7])
def test_the_fused_march_draws_the_torch_march_s_image(monkeypatch, index):
    field = GridField(padded_phantom())
    cameras = orbit_cameras(OrbitSpec(views=8, resolution=32, elevation=20.0))
    model = ImageModel("dvr", TransferFunction(0.2, 0.7, 8.0), step=2.0 / 32)
    fused, reference = both_marches(monkeypatch, field, cameras, index, model, subpixel=(0.25, 0.75))
    assert reference.max() > 0.2  # the body is in view
    assert torch.allclose(fused, reference, atol=2e-6, rtol=0)


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
