"""The Gaussian model: initial scales, spherical harmonics and the reference PLY layout."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from plyfile import PlyData

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.splat import gaussians_from_points, random_points, read_gaussians_ply, write_gaussians_ply
from cubecloud_cli.splat.gaussian_ply import attribute_names
from cubecloud_cli.splat.gaussians import neighbour_log_scales
from cubecloud_cli.splat.spherical_harmonics import SH_C0, SH_C1, rgb_to_sh, sh_to_colour


def test_initial_scales_are_the_neighbour_distance():
    spacing = 0.05
    grid = np.stack(np.meshgrid(*[np.arange(6) * spacing] * 3, indexing="ij"), -1).reshape(-1, 3)
    scales = np.exp(neighbour_log_scales(grid))
    np.testing.assert_allclose(scales, spacing, rtol=1e-9)  # 3 nearest all at one spacing


def test_duplicated_and_lonely_points_stay_finite():
    points = np.zeros((5, 3))
    assert np.allclose(neighbour_log_scales(points), 0.5 * math.log(1e-7))
    assert neighbour_log_scales(np.zeros((1, 3))).shape == (1,)
    assert neighbour_log_scales(np.array([[0, 0, 0], [1e9, 0, 0.0]])).max() < 25


@pytest.mark.parametrize("channels", [1, 3])
@pytest.mark.parametrize("degree", [0, 3])
def test_points_become_gaussians_with_their_colour(channels, degree):
    xyz, grey = random_points(200, seed=1)
    gaussians = gaussians_from_points(xyz, grey, channels=channels, sh_degree=degree)
    assert len(gaussians) == 200 and gaussians.channels == channels and gaussians.sh_degree == degree
    assert torch.allclose(gaussians.opacities(), torch.tensor(0.1))
    assert torch.allclose(gaussians.quaternions[:, 0], torch.tensor(1.0))
    colours = gaussians.colours(torch.tensor([0.0, 4.0, 0.0]))
    expected = torch.from_numpy(grey).float().expand(-1, channels)
    assert torch.allclose(colours, expected, atol=1e-6)  # higher SH bands start at zero


def test_random_points_fill_the_cube():
    xyz, grey = random_points(5000, seed=0)
    assert xyz.min() >= -1 and xyz.max() <= 1 and abs(xyz.mean()) < 0.05
    assert grey.shape == (5000, 1) and 0 <= grey.min() and grey.max() <= 1


def test_spherical_harmonics_degree_one_and_constant():
    dc = rgb_to_sh(torch.tensor([[0.7]]))
    assert float(SH_C0 * dc + 0.5) == pytest.approx(0.7)
    coefficients = torch.zeros(2, 4, 1)
    coefficients[:, 3, 0] = 1.0  # the x band, −C1·x in the 3DGS convention
    directions = torch.tensor([[1.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    colours = sh_to_colour(coefficients, directions, 1)
    assert torch.allclose(colours[:, 0], torch.tensor([0.5 - SH_C1, 0.5 + SH_C1]))
    coefficients[:, 3, 0] = 10.0
    assert sh_to_colour(coefficients, directions, 1)[0, 0] == 0.0  # clamped at 0, as the reference does


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 3), st.integers(0, 2**16))
def test_spherical_harmonics_are_finite_for_any_direction(degree, seed):
    g = torch.Generator().manual_seed(seed)
    coefficients = torch.randn(50, 16, 3, generator=g) * 10
    directions = torch.randn(50, 3, generator=g) * torch.tensor([1e-30, 1.0, 1e30])
    directions[0] = 0.0  # a camera at the mean itself
    colours = sh_to_colour(coefficients, directions, degree)
    assert torch.isfinite(colours).all() and (colours >= 0).all()


@pytest.mark.parametrize("channels, degree", [(1, 0), (3, 0), (1, 3), (3, 2)])
def test_ply_round_trip_in_the_reference_layout(tmp_path, channels, degree):
    xyz, grey = random_points(64, seed=2)
    gaussians = gaussians_from_points(xyz, grey, channels=channels, sh_degree=degree)
    generator = torch.Generator().manual_seed(0)
    gaussians.sh_dc = torch.randn(gaussians.sh_dc.shape, generator=generator)
    gaussians.sh_rest = torch.randn(gaussians.sh_rest.shape, generator=generator)
    gaussians.quaternions = torch.randn(64, 4, generator=generator)
    path = tmp_path / "point_cloud.ply"
    write_gaussians_ply(path, gaussians)

    vertex = PlyData.read(str(path))["vertex"]
    assert [p.name for p in vertex.properties] == attribute_names(degree)
    assert all(p.val_dtype in ("f4", "float32") for p in vertex.properties)
    assert len(attribute_names(3)) == 62  # the reference's 248 bytes per Gaussian at degree 3
    # What the reference loader does: f_rest sorted by number, channel-major, pre-activation.
    rest = sorted(
        (p.name for p in vertex.properties if p.name.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1])
    )
    assert len(rest) == 3 * (degree + 1) ** 2 - 3
    if rest:
        features = np.stack([vertex[n] for n in rest], 1).reshape(64, 3, -1)
        np.testing.assert_allclose(features[:, 0, :], gaussians.sh[:, 1:, 0].numpy(), atol=1e-7)
    np.testing.assert_allclose(vertex["opacity"], gaussians.opacity_logits.numpy(), atol=1e-7)

    back = read_gaussians_ply(path)
    assert back.channels == channels and back.sh_degree == degree
    for name, value in gaussians.parameters().items():
        torch.testing.assert_close(back.parameters()[name], value.float(), rtol=0, atol=1e-6)


def test_reading_a_bad_ply_is_a_one_line_error(tmp_path):
    with pytest.raises(CubecloudError, match="does not exist"):
        read_gaussians_ply(tmp_path / "missing.ply")
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(CubecloudError, match="not a readable PLY"):
        read_gaussians_ply(tmp_path / "bad.ply")


@pytest.mark.parametrize("smoothing", [False, True])
def test_gaussians_move_between_devices_whole(smoothing):
    """`eval --device cuda` moves each run's Gaussians with ``to``: every tensor, the 3D filter's
    variances too, go along, and nothing else changes (CPU to CPU here; tests/test_cuda.py runs
    eval on a GPU)."""
    points, colours = random_points(50, seed=3)
    gaussians = gaussians_from_points(points, colours)
    if smoothing:
        gaussians.smoothing = torch.full((50,), 1e-4)
    moved = gaussians.to("cpu")
    for name, tensor in gaussians.parameters().items():
        assert torch.equal(moved.parameters()[name], tensor)
    assert (moved.smoothing is None) == (not smoothing)
    if smoothing:
        assert torch.equal(moved.smoothing, gaussians.smoothing)
    torch.testing.assert_close(moved.scales(), gaussians.scales())
    torch.testing.assert_close(moved.opacities(), gaussians.opacities())
