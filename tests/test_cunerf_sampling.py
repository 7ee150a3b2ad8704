"""Cube samplers, sphere directions and inverse-CDF radii: bounds, symmetry, uniformity."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cunerf.sampling import cube_offsets, sample_radii_from_weights, sphere_directions


@pytest.mark.parametrize("layout", ["stratified", "uniform", "lattice", "official-train", "official-lattice"])
@pytest.mark.parametrize("n", [2, 3, 4, 5])
def test_every_layout_stays_inside_the_cube(layout, n):
    generator = torch.Generator().manual_seed(0)
    offsets = cube_offsets(200, n, layout, half_size=0.25, generator=generator)
    assert offsets.shape == (200, n**3, 3)
    assert offsets.abs().max() <= 0.25 + 1e-7


@pytest.mark.parametrize("n", [2, 3, 4, 5, 6])  # the official code crashes for 5 and 6 (cunerf.md §2.2)
def test_test_lattice_is_symmetric_and_deterministic(n):
    lattice = cube_offsets(3, n, "lattice", 1.0)
    points = {tuple(np.round(p, 6)) for p in lattice[0].numpy()}
    assert points == {tuple(np.round(-np.array(p), 6)) for p in points}
    assert torch.equal(lattice[0], lattice[2])
    np.testing.assert_allclose(lattice[0].mean(0).numpy(), 0.0, atol=1e-7)


def test_official_lattice_has_the_high_face_but_not_the_low_one():
    lattice = cube_offsets(1, 4, "official-lattice", 1.0)[0]
    assert lattice.max() == pytest.approx(1.0) and lattice.min() == pytest.approx(-0.5)


def test_stratified_puts_one_point_in_each_sub_cell():
    offsets = cube_offsets(50, 3, "stratified", 1.0, torch.Generator().manual_seed(1))
    cells = torch.floor((offsets + 1.0) / 2.0 * 3).clamp(0, 2)
    codes = (cells[..., 0] * 9 + cells[..., 1] * 3 + cells[..., 2]).long()
    for row in codes:
        assert sorted(row.tolist()) == list(range(27))


@pytest.mark.parametrize("layout", ["stratified", "uniform"])
def test_training_layouts_are_uniform_over_the_cube(layout):
    offsets = cube_offsets(4000, 3, layout, 1.0, torch.Generator().manual_seed(2)).reshape(-1, 3).numpy()
    # Each axis: 10 equal bins, counts within 5σ of the uniform expectation.
    for axis in range(3):
        counts, _ = np.histogram(offsets[:, axis], bins=10, range=(-1, 1))
        expected = offsets.shape[0] / 10
        assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected))
    np.testing.assert_allclose(offsets.mean(0), 0.0, atol=0.01)


def test_official_training_sampler_leans_to_the_low_corner():
    offsets = cube_offsets(4000, 4, "official-train", 1.0, torch.Generator().manual_seed(3))
    assert (offsets.reshape(-1, 3).mean(0) < -0.3).all()


def test_uniform_directions_cover_the_sphere_evenly():
    directions = sphere_directions((20000,), "uniform", torch.Generator().manual_seed(4))
    np.testing.assert_allclose(torch.linalg.vector_norm(directions, dim=-1).numpy(), 1.0, rtol=1e-6)
    z = directions[:, 2].numpy()
    assert abs(z.mean()) < 0.02 and abs((z**2).mean() - 1 / 3) < 0.01  # area-uniform: E[z²] = 1/3
    official = sphere_directions((20000,), "official", torch.Generator().manual_seed(4))[:, 2].numpy()
    assert abs((official**2).mean() - 0.5) < 0.01  # θ ~ U(0, π) crowds the poles: E[z²] = 1/2


def test_fibonacci_directions_are_deterministic_unit_vectors():
    a = sphere_directions((5, 64), "fibonacci")
    assert torch.equal(a[0], a[4])
    np.testing.assert_allclose(torch.linalg.vector_norm(a, dim=-1).numpy(), 1.0, rtol=1e-6)
    np.testing.assert_allclose(a[0].mean(0).numpy(), 0.0, atol=0.02)


def test_radii_follow_the_weights():
    edges = torch.tensor([[0.0, 0.2, 0.4, 0.6, 0.8]])
    weights = torch.tensor([[0.0, 0.0, 1.0, 0.0]])
    radii = sample_radii_from_weights(edges, weights, 500, False, torch.Generator().manual_seed(5))
    inside = ((radii >= 0.4) & (radii <= 0.6)).float().mean()
    assert inside > 0.99
    fixed = sample_radii_from_weights(edges, weights, 16, True)
    assert torch.all(fixed[0, 1:] >= fixed[0, :-1])


@settings(max_examples=50, deadline=None)
@given(
    bins=st.integers(1, 40),
    zeros=st.booleans(),
    scale=st.sampled_from([0.0, 1e-30, 1e-6, 1.0, 1e30]),
    deterministic=st.booleans(),
    seed=st.integers(0, 1000),
)
def test_radii_stay_within_the_edges_for_any_weights(bins, zeros, scale, deterministic, seed):
    generator = torch.Generator().manual_seed(seed)
    edges = torch.sort(torch.rand(2, bins + 1, generator=generator), dim=1).values
    edges[:, 1] = edges[:, 0]  # a zero-width bin
    weights = torch.zeros(2, bins) if zeros else torch.rand(2, bins, generator=generator) * scale
    radii = sample_radii_from_weights(edges, weights, 33, deterministic, generator)
    assert torch.isfinite(radii).all()
    assert (radii >= edges[:, :1] - 1e-6).all() and (radii <= edges[:, -1:] + 1e-6).all()
