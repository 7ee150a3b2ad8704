"""The chord ratio r a scalar Gaussian's optical length is scaled by (splat/chord.py): its numba
kernels against the torch formula and finite differences, its geometry, its extremes, and the
scalar model drawn with it (splat/scalar_gaussians.py, the PLY, the viewer's fixed opacities)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from kernel_oracle import assert_matches_formula

from cubecloud_cli.splat.chord import (
    LOG_RATIO_LIMIT,
    chord_log_ratio,
    chord_log_ratio_reference,
    sphere_directions,
    sphere_mean_log_ratio,
)
from cubecloud_cli.splat.gaussian_ply import (
    read_gaussians_ply,
    read_scalar_gaussians,
    scalar_properties,
    write_gaussians_ply,
)
from cubecloud_cli.splat.scalar_gaussians import scalar_gaussians_from_points
from cubecloud_cli.transfer.function import TransferFunction

SOFT = TransferFunction(0.3, 0.6, 1.5)
BONE = TransferFunction(0.7, 0.9, 12.0)


def _random_gaussians(seed: int, count: int, dtype=torch.float64, spread: float = 1.0):
    generator = torch.Generator().manual_seed(seed)
    means = torch.randn(count, 3, generator=generator, dtype=dtype)
    quaternions = torch.randn(count, 4, generator=generator, dtype=dtype)
    scales = torch.exp(torch.randn(count, 3, generator=generator, dtype=dtype) * spread - 3.0)
    return means, quaternions, scales


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), spread=st.sampled_from([0.1, 1.0, 3.0]), dtype=st.sampled_from(["32", "64"]))
def test_the_kernels_match_the_torch_formula_and_its_gradients(seed, spread, dtype):
    dtype = torch.float32 if dtype == "32" else torch.float64
    means, quaternions, scales = _random_gaussians(seed, 64, dtype, spread)
    centre = torch.tensor([0.2, -0.4, 4.0], dtype=dtype)
    quaternions.requires_grad_(True)
    scales.requires_grad_(True)
    kernel = chord_log_ratio(means, quaternions, scales, centre)
    formula = chord_log_ratio_reference(means, quaternions, scales, centre)
    tolerance = {"rtol": 1e-4, "atol": 1e-4} if dtype == torch.float32 else {"rtol": 1e-9, "atol": 1e-9}
    assert_matches_formula(kernel, formula, (quaternions, scales), seed, tolerance, gradient_atol=1e-3)


def test_the_kernels_gradients_match_finite_differences():
    means, quaternions, scales = _random_gaussians(3, 6)
    centre = torch.tensor([0.0, 0.5, 5.0], dtype=torch.float64)
    assert torch.autograd.gradcheck(
        lambda q, s: chord_log_ratio(means, q, s, centre),
        (quaternions.requires_grad_(True), scales.requires_grad_(True)),
    )


def test_a_round_gaussian_is_one_and_a_flat_one_long_edge_on_and_short_face_on():
    means = torch.zeros(3, 3, dtype=torch.float64)
    identity = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=torch.float64)
    scales = torch.tensor([[0.1, 0.1, 0.1], [0.2, 0.2, 0.01], [0.2, 0.2, 0.01]], dtype=torch.float64)
    face_on = chord_log_ratio(means[:2], identity[:2], scales[:2], torch.tensor([0.0, 0, 3], dtype=torch.float64))
    edge_on = chord_log_ratio(means[2:], identity[2:], scales[2:], torch.tensor([3.0, 0, 0], dtype=torch.float64))
    geometric = (0.2 * 0.2 * 0.01) ** (1 / 3)
    torch.testing.assert_close(face_on, torch.tensor([0.0, math.log(0.01 / geometric)], dtype=torch.float64))
    torch.testing.assert_close(edge_on, torch.tensor([math.log(0.2 / geometric)], dtype=torch.float64))
    # A turn of the Gaussian is a turn of the view: a quarter turn about y shows the flat one edge-on.
    quarter = torch.tensor([[math.cos(math.pi / 4), 0, math.sin(math.pi / 4), 0]], dtype=torch.float64)
    turned = chord_log_ratio(means[2:], quarter, scales[2:], torch.tensor([0.0, 0, 3], dtype=torch.float64))
    torch.testing.assert_close(turned, edge_on)


@pytest.mark.parametrize(
    "mean, quaternion, scale",
    [
        ([0.0, 0.0, 3.0], [1.0, 0, 0, 0], [0.1, 0.1, 0.1]),  # at the camera
        ([0.0, 0.0, 0.0], [0.0, 0, 0, 0], [0.1, 0.2, 0.3]),  # no rotation
        ([math.nan, 0.0, 0.0], [1.0, 0, 0, 0], [0.1, 0.2, 0.3]),
        ([0.0, 0.0, 0.0], [math.inf, 0, 0, 0], [0.1, 0.2, 0.3]),
        ([math.inf, 0.0, 0.0], [1.0, 0, 0, 0], [0.1, 0.2, 0.3]),
        ([0.0, 0.0, 0.0], [1.0, 0, 0, 0], [0.1, 0.2, math.nan]),
        ([0.0, 0.0, 0.0], [1.0, 0, 0, 0], [0.0, 0.2, 0.3]),
    ],
)
def test_where_r_is_undefined_it_is_one_with_no_gradient(mean, quaternion, scale):
    for function in (chord_log_ratio, chord_log_ratio_reference):
        for dtype in (torch.float32, torch.float64):
            q = torch.tensor([quaternion], dtype=dtype, requires_grad=True)
            s = torch.tensor([scale], dtype=dtype, requires_grad=True)
            value = function(torch.tensor([mean], dtype=dtype), q, s, torch.tensor([0.0, 0, 3], dtype=dtype))
            assert value.item() == 0.0
            value.sum().backward()
            assert torch.isfinite(q.grad).all() and torch.isfinite(s.grad).all()
            assert not q.grad.any()


@settings(max_examples=40, deadline=None)
@given(
    log_scales=st.lists(st.floats(-10.0, 10.0), min_size=3, max_size=3),
    direction=st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).filter(lambda d: sum(x * x for x in d) > 1e-6),
)
def test_r_stays_finite_and_clamped_at_the_scales_limits(log_scales, direction):
    """Scales from e^-10 to e^10 (LOG_SCALE_LIMIT) in float32: log r finite, within its limit,
    and a gradient that is finite (0 where it is clamped)."""
    means = torch.zeros(1, 3)
    centre = -torch.tensor(direction, dtype=torch.float32) * 5.0
    q = torch.tensor([[0.9, 0.1, -0.3, 0.2]], requires_grad=True)
    s = torch.exp(torch.tensor([log_scales], dtype=torch.float32)).requires_grad_(True)
    value = chord_log_ratio(means, q, s, centre)
    assert torch.isfinite(value).all() and value.abs().item() <= LOG_RATIO_LIMIT
    value.sum().backward()
    assert torch.isfinite(q.grad).all() and torch.isfinite(s.grad).all()
    if value.abs().item() == LOG_RATIO_LIMIT:
        assert not q.grad.any() and not s.grad.any()


def test_the_sphere_mean_is_zero_for_a_round_gaussian_and_the_mean_over_many_directions():
    log_scales = torch.tensor([[-2.0, -2.0, -2.0], [-1.0, -2.0, -4.0], [-3.0, -3.0, -0.5]], dtype=torch.float64)
    fine = torch.as_tensor(sphere_directions(20_000), dtype=torch.float64)
    identity = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).repeat(len(fine), 1)
    expected = [
        chord_log_ratio(-fine, identity, torch.exp(row).repeat(len(fine), 1), torch.zeros(3, dtype=torch.float64))
        .mean()
        .item()
        for row in log_scales
    ]
    mean = sphere_mean_log_ratio(log_scales)
    assert mean[0].abs().item() < 1e-9
    np.testing.assert_allclose(mean.numpy(), expected, atol=0.02)
    assert torch.isfinite(sphere_mean_log_ratio(torch.tensor([[-10.0, 10.0, 0.0]]))).all()


def _flat_scene(chord: bool):
    xyz = np.random.default_rng(4).uniform(-0.5, 0.5, (20, 3))
    gaussians = scalar_gaussians_from_points(xyz, np.linspace(0.35, 0.95, 20), [SOFT, BONE], chord_lengths=chord)
    gaussians.log_scales = gaussians.log_scales + torch.tensor([0.5, 0.0, -1.5])  # flat: r differs by view
    gaussians.smoothing = torch.full((20,), 1e-4)
    return gaussians


def test_chord_lengths_change_the_opacity_with_the_view_and_without_them_nothing_does():
    from cubecloud_cli.cameras import OrbitSpec, orbit_cameras

    centres = torch.as_tensor(orbit_cameras(OrbitSpec(views=4, resolution=32)).centres(), dtype=torch.float32)
    fixed, chord = _flat_scene(False), _flat_scene(True)
    for centre in centres:
        torch.testing.assert_close(fixed.opacities(centre), fixed.opacities())
    seen = torch.stack([chord.opacities(centre) for centre in centres])
    assert (seen.amax(0) - seen.amin(0)).max() > 0.01
    # Drawn under another transfer function, moved or read back, it keeps its chord lengths.
    assert chord.drawn_as(BONE).chord_lengths and chord.to("cpu").chord_lengths


def test_the_ply_draws_r_as_its_mean_over_the_sphere_and_reads_back_with_chord_lengths(tmp_path):
    gaussians = _flat_scene(True)
    path = tmp_path / "point_cloud.ply"
    write_gaussians_ply(path, gaussians.baked(), scalar_properties(gaussians))
    reference = read_gaussians_ply(path)  # what any splat viewer draws: one opacity per Gaussian
    with torch.no_grad():
        mean = gaussians.log_lengths + sphere_mean_log_ratio(gaussians.scales().log())
        expected = gaussians.drawn_as(SOFT)
        expected = type(expected)(**{**expected.__dict__, "log_lengths": mean, "chord_lengths": False})
    torch.testing.assert_close(reference.opacities(), expected.opacities(), rtol=1e-5, atol=1e-7)
    again = read_scalar_gaussians(path)
    assert again.chord_lengths
    centre = torch.tensor([0.0, 0.0, 4.0])
    torch.testing.assert_close(again.opacities(centre), gaussians.opacities(centre), rtol=1e-4, atol=1e-6)
    fixed = _flat_scene(False)
    write_gaussians_ply(tmp_path / "fixed.ply", fixed.baked(), scalar_properties(fixed))
    assert not read_scalar_gaussians(tmp_path / "fixed.ply").chord_lengths


def test_the_viewer_draws_a_chord_scene_as_the_trainer_does_from_its_camera_and_as_the_ply_without_one():
    from cubecloud_cli.view.transfer_view import DrawnValues

    gaussians = _flat_scene(True)
    drawn = DrawnValues.of(gaussians)
    expected = gaussians.baked().opacities().numpy()
    np.testing.assert_allclose(drawn.opacities(SOFT), expected, rtol=1e-4, atol=1e-6)
    for centre in ([0.0, 0.0, 4.0], [3.0, -2.0, 0.5]):
        with torch.no_grad():
            seen = gaussians.opacities(torch.tensor(centre)).numpy()
        np.testing.assert_allclose(drawn.opacities(SOFT, np.asarray(centre)), seen, rtol=1e-4, atol=1e-6)
    assert DrawnValues.of(_flat_scene(False)).chord is None
