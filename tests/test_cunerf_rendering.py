"""CuNeRF's isotropic cube rendering: hand-computed weights, ties, bounds and extremes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cunerf.rendering import render_cubes, shell_edges, shell_intervals


def _offsets_at(radii, half_diagonal=1.0):
    """Samples along +x at the given radii (in half-diagonals), one cube."""
    r = torch.tensor(radii, dtype=torch.float64) * half_diagonal
    return torch.stack((r, torch.zeros_like(r), torch.zeros_like(r)), dim=-1)[None]


def test_weights_match_a_hand_computed_cube():
    # Radii given out of order to exercise the sort: 0.5, 0.2, 0.8 (half-diagonals).
    offsets = _offsets_at([0.5, 0.2, 0.8], half_diagonal=2.0)
    intensity = torch.tensor([[0.3, 0.9, 0.6]], dtype=torch.float64)
    density = torch.tensor([[2.0, 1.0, 4.0]], dtype=torch.float64)
    out = render_cubes(offsets, intensity, density, half_diagonal=2.0, bounded=False)

    # Sorted: r̂ = 0.2, 0.5, 0.8 with σ = 1, 2, 4 and c = 0.9, 0.3, 0.6.
    r, sigma, c = [0.2, 0.5, 0.8], [1.0, 2.0, 4.0], [0.9, 0.3, 0.6]
    delta = [0.3, 0.3, 0.3]  # gaps, the last repeating the one before
    area = [4 * math.pi * x * x for x in r]
    depth = [a * s * d for a, s, d in zip(area, sigma, delta)]
    transmittance = [1.0, math.exp(-depth[0]), math.exp(-depth[0] - depth[1])]
    alpha = [a * (1 - math.exp(-s * d)) for a, s, d in zip(area, sigma, delta)]
    weights = [t * a for t, a in zip(transmittance, alpha)]
    expected = sum(w * x for w, x in zip(weights, c))

    np.testing.assert_allclose(out.radii[0].numpy(), r, rtol=1e-12)
    np.testing.assert_allclose(out.weights[0].numpy(), weights, rtol=1e-12)
    assert out.value.item() == pytest.approx(expected, rel=1e-12)
    assert out.order[0].tolist() == [1, 0, 2]


def test_bounded_render_divides_only_when_weights_exceed_one():
    # The first shell, at r̂ = 0.5, has area π > 1: one opaque sample already weighs π.
    offsets = _offsets_at([0.6, 0.5, 0.9])
    intensity = torch.tensor([[1.0, 1.0, 1.0]], dtype=torch.float64)
    density = torch.full((1, 3), 50.0, dtype=torch.float64)
    raw = render_cubes(offsets, intensity, density, 1.0, bounded=False)
    assert raw.weights.sum() > 1 and raw.value.item() > 1  # the official quirk (issue #9)
    bounded = render_cubes(offsets, intensity, density, 1.0, bounded=True)
    assert bounded.value.item() == pytest.approx(1.0)
    thin = render_cubes(offsets, intensity, torch.full((1, 3), 0.01, dtype=torch.float64), 1.0)
    thin_raw = render_cubes(offsets, intensity, torch.full((1, 3), 0.01, dtype=torch.float64), 1.0, bounded=False)
    assert thin.value.item() == thin_raw.value.item() < 1


def test_tied_samples_share_their_shell_and_ignore_the_sort():
    # Two samples at r̂ = 0.5 (different directions) and one at 0.9.
    offsets = torch.tensor([[[0.5, 0, 0], [0, 0.5, 0], [0.9, 0, 0]]], dtype=torch.float64)
    density = torch.tensor([[3.0, 3.0, 1.0]], dtype=torch.float64)
    a = render_cubes(offsets, torch.tensor([[0.2, 0.8, 0.5]], dtype=torch.float64), density, 1.0)
    b = render_cubes(offsets, torch.tensor([[0.8, 0.2, 0.5]], dtype=torch.float64), density, 1.0)
    assert a.value.item() == pytest.approx(b.value.item(), rel=1e-12)
    assert a.weights[0, 0].item() == pytest.approx(a.weights[0, 1].item(), rel=1e-12)

    delta, shell = shell_intervals(a.radii)
    # The shell at 0.5 is 0.4 thick, shared by two; the last repeats the thickness before it.
    np.testing.assert_allclose(delta[0].numpy(), [0.2, 0.2, 0.4])
    assert shell[0].tolist() == [0, 0, 1]


def test_without_ties_the_intervals_are_the_official_ones():
    radii = torch.tensor([[0.1, 0.25, 0.7, 0.75]])
    tie_aware, _ = shell_intervals(radii, tie_aware=True)
    official, _ = shell_intervals(radii, tie_aware=False)
    np.testing.assert_allclose(tie_aware.numpy(), [[0.15, 0.45, 0.05, 0.05]], rtol=1e-6)
    np.testing.assert_allclose(official.numpy(), tie_aware.numpy())


def test_a_single_shell_reaches_the_half_diagonal():
    delta, _ = shell_intervals(torch.tensor([[0.4, 0.4, 0.4]]))
    np.testing.assert_allclose(delta.numpy(), [[0.2, 0.2, 0.2]], rtol=1e-6)


def test_empty_and_saturated_cubes_stay_finite():
    offsets = torch.rand(4, 27, 3, dtype=torch.float64) * 2 - 1
    intensity = torch.rand(4, 27, dtype=torch.float64)
    empty = render_cubes(offsets, intensity, torch.zeros(4, 27, dtype=torch.float64), math.sqrt(3))
    assert torch.equal(empty.value, torch.zeros(4, dtype=torch.float64))
    huge = render_cubes(offsets, intensity, torch.full((4, 27), 1e30, dtype=torch.float64), math.sqrt(3))
    assert torch.isfinite(huge.value).all() and (huge.value >= 0).all() and (huge.value <= 1).all()


def test_rejects_a_degenerate_cube():
    with pytest.raises(ValueError, match="half-diagonal"):
        render_cubes(torch.zeros(1, 2, 3), torch.zeros(1, 2), torch.zeros(1, 2), 0.0)


def test_gradients_flow_to_density_and_intensity():
    offsets = _offsets_at([0.3, 0.6, 0.9]).float()
    intensity = torch.tensor([[0.2, 0.5, 0.7]], requires_grad=True)
    density = torch.tensor([[1.0, 2.0, 0.5]], requires_grad=True)
    render_cubes(offsets, intensity, density, 1.0).value.sum().backward()
    assert torch.isfinite(intensity.grad).all() and intensity.grad.abs().sum() > 0
    assert torch.isfinite(density.grad).all() and density.grad.abs().sum() > 0


def test_shell_edges_are_mid_radii():
    np.testing.assert_allclose(shell_edges(torch.tensor([[0.0, 0.2, 0.6]])).numpy(), [[0.1, 0.4]])


finite_floats = st.floats(min_value=0.0, max_value=1.0, allow_nan=False, width=32)


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 12),
    scale=st.sampled_from([1e-6, 1e-3, 1.0, 1e3]),
    log_density=st.floats(-12, 12),
    seed=st.integers(0, 10_000),
    float16=st.booleans(),
)
def test_bounded_render_stays_in_unit_range(n, scale, log_density, seed, float16):
    generator = torch.Generator().manual_seed(seed)
    offsets = (torch.rand(3, n, 3, generator=generator) * 2 - 1) * scale
    intensity = torch.rand(3, n, generator=generator)
    density = torch.rand(3, n, generator=generator) * 10.0**log_density
    if float16:
        offsets, intensity, density = offsets.half().float(), intensity.half().float(), density.half().float()
    out = render_cubes(offsets, intensity, density, half_diagonal=scale * math.sqrt(3))
    assert torch.isfinite(out.value).all()
    assert (out.value >= 0).all() and (out.value <= 1 + 1e-6).all()
    assert torch.isfinite(out.weights).all() and (out.weights >= 0).all()
