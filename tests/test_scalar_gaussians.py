"""The scalar Gaussians' transfer-function map (splat/scalar_gaussians.py): its gradients against
finite differences, its extremes, its start and reset, and its PLY columns."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.splat.gaussian_ply import (
    read_gaussians_ply,
    read_scalar_gaussians,
    read_scalar_properties,
    scalar_properties,
    write_gaussians_ply,
)
from cubecloud_cli.splat.scalar_gaussians import (
    INITIAL_OPACITY,
    RESET_OPACITY,
    ScalarGaussians,
    most_opaque,
    scalar_gaussians_from_points,
    transfer_opacities,
)
from cubecloud_cli.transfer.function import TransferFunction

BONE = TransferFunction(0.7, 0.9, 12.0)
SOFT = TransferFunction(0.3, 0.6, 1.5)
LUNG_BAND = TransferFunction(0.2, 0.3, 2.0, 0.5, 0.7)


def test_opacity_is_the_light_a_slab_stops():
    values = torch.tensor([0.1, 0.45, 0.6, 0.95], dtype=torch.float64)
    log_lengths = torch.log(torch.tensor([0.2, 0.2, 0.5, 0.1], dtype=torch.float64))
    expected = [0.0, 1 - math.exp(-1.5 * 0.5 * 0.2), 1 - math.exp(-1.5 * 0.5), 1 - math.exp(-1.5 * 0.1)]
    assert transfer_opacities(values, log_lengths, SOFT).tolist() == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("transfer, on", [(SOFT, "rise"), (BONE, "rise"), (TransferFunction(0.0, 1.0, 40.0), "rise"),
                                           (LUNG_BAND, "rise"), (LUNG_BAND, "fall")])  # fmt: skip
def test_gradients_match_finite_differences(transfer, on):
    generator = torch.Generator().manual_seed(3)
    # Values inside a ramp (rising, or a band's falling one), away from its kinks, where the map is smooth.
    start, end = (transfer.low, transfer.high) if on == "rise" else (transfer.fall_low, transfer.fall_high)
    values = start + (end - start) * (0.1 + 0.8 * torch.rand(12, generator=generator))
    values = values.double().requires_grad_(True)
    log_lengths = (torch.rand(12, generator=generator, dtype=torch.float64) * 4 - 3).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v, l: transfer_opacities(v, l, transfer), (values, log_lengths))


def test_gradients_reach_the_value_through_a_sigmoid_and_the_map():
    gaussians = scalar_gaussians_from_points(np.random.default_rng(0).uniform(-1, 1, (16, 3)), np.full(16, 0.8), [BONE])
    logits = gaussians.value_logits.double().requires_grad_(True)
    lengths = gaussians.log_lengths.double().requires_grad_(True)

    def drawn(logit, length):
        value = torch.sigmoid(logit)
        return transfer_opacities(value, length, BONE) * value  # what a Gaussian adds to a pixel, to first order

    assert torch.autograd.gradcheck(drawn, (logits, lengths))


@settings(max_examples=200, deadline=None)
@given(
    low=st.floats(0.0, 1.0),
    width=st.sampled_from([0.0, 1e-9, 1e-6, 0.3, 1.0]),
    density=st.sampled_from([0.0, 1e-30, 1.0, 1e3, 999_999.0]),
    value=st.floats(-5.0, 5.0),
    log_length=st.floats(-200.0, 200.0),
    fall=st.sampled_from([None, (0.0, 0.0), (0.0, 1e-9), (0.1, 0.4), (1.0, 1.0)]),
)
def test_the_map_stays_finite_at_its_extremes(low, width, density, value, log_length, fall):
    """A window of zero width (a step), opacity 0 (no density) and near 1 (huge density, long
    slabs), values outside the window and outside [0, 1], bands whose top or fall has no width:
    opacity in [0, 1], loss and gradients finite."""
    high = min(1.0, low + width)
    # A fall (offsets past the top, capped at 1), so that the band stays valid.
    fall_low, fall_high = (None, None) if fall is None else (min(1.0, high + fall[0]), min(1.0, high + fall[1]))
    transfer = TransferFunction(low, high, density, fall_low, fall_high)
    transfer.validate()
    values = torch.tensor([value], requires_grad=True)
    log_lengths = torch.tensor([log_length], requires_grad=True)
    opacity = transfer_opacities(values, log_lengths, transfer)
    assert 0.0 <= opacity.item() <= 1.0
    loss = ((opacity.clamp(max=0.99) * values - 0.5) ** 2).sum()
    loss.backward()
    assert math.isfinite(loss.item()) and torch.isfinite(values.grad).all() and torch.isfinite(log_lengths.grad).all()
    if density == 0.0:
        assert opacity.item() == 0.0


def test_a_value_outside_the_window_is_clear_and_inside_it_is_seen():
    values = torch.tensor([0.0, 0.69, 0.71, 1.0])
    opacity = transfer_opacities(values, torch.zeros(4), BONE)
    assert opacity[0] == 0 and opacity[1] == 0 and 0 < opacity[2] < opacity[3] < 1


def test_a_band_is_clear_below_its_rise_and_above_its_fall_and_level_between():
    values = torch.tensor([0.1, 0.25, 0.3, 0.4, 0.5, 0.6, 0.7, 0.9], dtype=torch.float64)
    ramp = LUNG_BAND.ramp(values)
    assert ramp.tolist() == pytest.approx([0.0, 0.5, 1.0, 1.0, 1.0, 0.5, 0.0, 0.0], abs=1e-12)


def test_the_start_is_ten_percent_opaque_under_the_most_opaque_transfer_function():
    xyz = np.random.default_rng(1).uniform(-1, 1, (5, 3))
    values = np.array([0.05, 0.5, 0.8, 0.999999, 0.0])
    gaussians = scalar_gaussians_from_points(xyz, values, [SOFT, BONE])
    opacity = most_opaque(gaussians.values(), gaussians.log_lengths, [SOFT, BONE])
    assert opacity[1:4].tolist() == pytest.approx([INITIAL_OPACITY] * 3, rel=1e-4)
    assert opacity[0] == 0 and opacity[4] == 0  # below both windows: nothing gives it opacity
    assert torch.isfinite(gaussians.value_logits).all() and torch.isfinite(gaussians.log_lengths).all()
    with pytest.raises(ValueError, match="at least one transfer function"):
        scalar_gaussians_from_points(xyz, values, [])


def test_the_reset_caps_every_trained_transfer_function_at_one_percent():
    gaussians = scalar_gaussians_from_points(
        np.zeros((3, 3)) + [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [0.5, 0.8, 0.1], [SOFT, BONE]
    )
    gaussians.log_lengths = gaussians.log_lengths + 3.0  # grown opaque in training
    reset = gaussians.reset_transparency(gaussians.log_lengths)
    opacity = most_opaque(gaussians.values(), reset, [SOFT, BONE])
    assert opacity[:2].tolist() == pytest.approx([RESET_OPACITY] * 2, rel=1e-4)
    assert reset[2] == gaussians.log_lengths[2]  # clear under both: left as it was
    assert torch.equal(gaussians.reset_transparency(reset), reset)  # already below: unchanged


def test_drawn_under_another_transfer_function_only_the_opacities_change():
    gaussians = scalar_gaussians_from_points(
        np.random.default_rng(2).uniform(-1, 1, (8, 3)), np.linspace(0.3, 1, 8), [SOFT]
    )
    bone = gaussians.drawn_as(BONE)
    assert torch.equal(bone.colours(), gaussians.colours()) and torch.equal(bone.scales(), gaussians.scales())
    assert not torch.equal(bone.opacities(), gaussians.opacities())


def test_the_ply_opens_as_a_reference_scene_and_keeps_the_scan_values(tmp_path):
    xyz = np.random.default_rng(4).uniform(-1, 1, (20, 3))
    gaussians = scalar_gaussians_from_points(xyz, np.linspace(0.35, 0.95, 20), [SOFT, BONE])
    gaussians.smoothing = torch.full((20,), 1e-4)
    path = tmp_path / "point_cloud.ply"
    write_gaussians_ply(path, gaussians.baked(), scalar_properties(gaussians))
    reference = read_gaussians_ply(path)  # what any splat viewer sees: the scene under SOFT
    torch.testing.assert_close(reference.opacities(), gaussians.opacities(), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(reference.colours(), gaussians.colours(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(reference.scales(), gaussians.scales(), rtol=1e-5, atol=1e-7)
    scalar = read_scalar_properties(path)
    assert scalar.drawn_under == SOFT and scalar.trained_under == [SOFT, BONE]
    np.testing.assert_allclose(scalar.values, gaussians.values().numpy(), rtol=1e-6)
    np.testing.assert_allclose(scalar.log_lengths, gaussians.log_lengths.numpy(), rtol=1e-6)
    # Read back, the scene draws under another transfer function as the trained one does, its 3D
    # filter folded into the scales and the opacities' attenuation.
    again = read_scalar_gaussians(path)
    torch.testing.assert_close(
        again.drawn_as(BONE).opacities(), gaussians.drawn_as(BONE).opacities(), rtol=1e-5, atol=1e-7
    )
    torch.testing.assert_close(again.scales(), gaussians.scales(), rtol=1e-5, atol=1e-7)
    write_gaussians_ply(tmp_path / "plain.ply", reference)
    assert (
        read_scalar_properties(tmp_path / "plain.ply") is None and read_scalar_gaussians(tmp_path / "plain.ply") is None
    )


def test_a_scalar_model_is_drawn_by_every_rasterizer_as_a_baked_one():
    from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
    from cubecloud_cli.raster.backends import NUMBA, TORCH
    from cubecloud_cli.splat.trainer import render_camera

    cameras = orbit_cameras(OrbitSpec(views=2, resolution=32))
    gaussians = scalar_gaussians_from_points(
        np.random.default_rng(5).uniform(-0.5, 0.5, (40, 3)), np.linspace(0.3, 1, 40), [SOFT]
    )
    assert isinstance(gaussians, ScalarGaussians)
    for rasterizer in (NUMBA, TORCH):
        scalar = render_camera(gaussians, cameras, 0, 0, rasterizer).image
        baked = render_camera(gaussians.baked(), cameras, 0, 0, rasterizer).image
        torch.testing.assert_close(scalar, baked, rtol=1e-4, atol=1e-5)
        assert scalar.max() > 0.01
