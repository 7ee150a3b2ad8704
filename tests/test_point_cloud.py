"""The cube-sampled point cloud: tiling (Eq. 1), uniform draws (Eq. 2), air, and the budget."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.export.point_cloud import (
    build_point_cloud,
    cube_boxes,
    gradient_magnitude,
    sample_in_cubes,
    structure_weights,
    weighted_choice,
)


@pytest.mark.parametrize("size, cube", [(32, 16), (32, 8), (30, 16), (7, 7)])
def test_cubes_tile_the_volume(size, cube):
    low, high = cube_boxes(size, cube)
    count = -(-size // cube)
    assert low.shape == (count**3, 3)
    assert torch.all(low >= -1) and torch.all(high <= 1 + 1e-6) and torch.all(high > low)
    volumes = torch.prod(high - low, dim=1)
    assert float(volumes.sum()) == pytest.approx(8.0, rel=1e-5)  # no gap, no overlap
    # Cube edges sit on voxel faces: cube voxels wide, except the last one cut at the face.
    widths = sorted({round(float(w) * size / 2, 4) for w in (high - low)[:, 0]})
    assert widths[-1] == cube and (size % cube == 0 or widths[0] == size % cube)


def test_points_are_uniform_inside_their_cube():
    low, high = cube_boxes(32, 16)
    points = sample_in_cubes(low, high, 4000, torch.Generator().manual_seed(0))
    assert torch.all(points >= low[:, None]) and torch.all(points <= high[:, None])
    # Uniform: each octant of a cube holds about an eighth of its points.
    centre = (low + high)[:, None] / 2
    octant = ((points > centre).long() * torch.tensor([4, 2, 1])).sum(-1)
    shares = torch.stack([(octant == k).float().mean(1) for k in range(8)])
    assert torch.allclose(shares, torch.full_like(shares, 0.125), atol=0.03)


def half_body(points: torch.Tensor) -> torch.Tensor:
    """Air for x < 0; for x ≥ 0 a bright flat slab (y ≥ 0) and dim stripes (y < 0)."""
    stripes = 0.3 + 0.2 * torch.sin(points[:, 2] * 20.0)
    values = torch.where(points[:, 1] >= 0, torch.full_like(stripes, 0.95), stripes)
    return torch.where(points[:, 0] >= 0, values, torch.zeros_like(values))


def test_air_cubes_and_points_are_dropped():
    cloud = build_point_cloud(half_body, lambda p: torch.ones(p.shape[0]), half_body, 32, 8, 64, None, 0.02)
    assert (cloud.xyz[:, 0] >= 0).all()
    assert cloud.stats["cubes"] == 64 and cloud.stats["air_cubes"] == 32
    assert cloud.stats["points"] == cloud.stats["sampled"] - cloud.stats["air_points_dropped"] == 32 * 64
    np.testing.assert_allclose(cloud.intensity, half_body(torch.from_numpy(cloud.xyz)).numpy(), atol=1e-6)
    assert (cloud.rgb[:, 0] == cloud.rgb[:, 2]).all()  # grey


def test_budget_keeps_structure_not_brightness():
    cloud = build_point_cloud(half_body, lambda p: p[:, 0], half_body, 32, 8, 256, 1000, 0.02, seed=4)
    assert cloud.stats["points"] == 1000 and cloud.stats["budget_dropped"] == 32 * 256 - 1000
    striped = (cloud.xyz[:, 1] < 0).mean()
    # The striped half has the volume of the bright flat half but all the edges: it gets most
    # points, where weights following brightness would give it a quarter (0.3 vs 0.95).
    assert striped > 0.62
    assert (cloud.xyz[:, 1] >= 0).mean() > 0.1  # flat tissue keeps an even, sparser cover
    again = build_point_cloud(half_body, lambda p: p[:, 0], half_body, 32, 8, 256, 1000, 0.02, seed=4)
    np.testing.assert_array_equal(cloud.xyz, again.xyz)
    np.testing.assert_allclose(cloud.density, cloud.xyz[:, 0], atol=1e-6)


def test_all_air_gives_an_empty_cloud():
    def air(points):
        return torch.zeros(points.shape[0])

    cloud = build_point_cloud(air, air, air, 16, 8, 8, 100, 0.02)
    assert cloud.xyz.shape == (0, 3) and cloud.stats["air_cubes"] == 8 and cloud.rgb.shape == (0, 3)


def test_gradient_of_a_linear_field():
    points = torch.rand(50, 3) * 1.6 - 0.8
    gradient = gradient_magnitude(lambda p: 2.0 * p[:, 0] - 1.0 * p[:, 2], points, 1 / 16)
    assert torch.allclose(gradient, torch.full_like(gradient, 5.0**0.5), atol=1e-4)


def test_structure_weights_of_a_flat_field_are_uniform():
    assert torch.equal(structure_weights(torch.zeros(5)), torch.ones(5))
    assert torch.equal(structure_weights(torch.full((3,), float("nan"))), torch.ones(3))
    weights = structure_weights(torch.tensor([0.0, 1.0, 3.0]))
    assert torch.allclose(weights, torch.tensor([0.25, 1.0, 2.5]))


@settings(max_examples=50, deadline=None)
@given(
    weights=st.lists(st.floats(1e-30, 1e30), min_size=1, max_size=200),
    count=st.integers(0, 250),
    seed=st.integers(0, 1000),
)
def test_weighted_choice_is_distinct_sorted_and_finite_at_extreme_weights(weights, count, seed):
    chosen = weighted_choice(
        torch.tensor(weights, dtype=torch.float32).clamp_min(1e-30), count, torch.Generator().manual_seed(seed)
    )
    assert chosen.numel() == min(count, len(weights))
    assert torch.equal(chosen, torch.unique(chosen))


def test_weighted_choice_follows_the_weights():
    weights = torch.cat([torch.full((1000,), 9.0), torch.ones(1000)])
    chosen = weighted_choice(weights, 200, torch.Generator().manual_seed(1))
    assert (chosen < 1000).float().mean() > 0.8
