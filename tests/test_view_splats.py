"""The viewer's Gaussians: what the browser draws must be what the rasterizer renders."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.raster.projection import dilation, project
from cubecloud_cli.splat.gaussian_ply import read_gaussians_ply, write_gaussians_ply
from cubecloud_cli.splat.gaussians import Gaussians
from cubecloud_cli.view.splats import (
    FLOAT16_MAX,
    ViewSplats,
    axis_normal,
    by_importance,
    clip_mask,
    detail_count,
    detail_percent,
    importance_order,
    view_scale,
    view_splats,
)


def random_gaussians(count: int, seed: int = 0, channels: int = 1, smoothing: bool = False) -> Gaussians:
    generator = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.rand(count, 3, generator=generator) * 1.6 - 0.8,
        log_scales=torch.log(torch.rand(count, 3, generator=generator) * 0.05 + 0.002),
        quaternions=torch.randn(count, 4, generator=generator),
        opacity_logits=torch.randn(count, generator=generator),
        sh_dc=torch.randn(count, 1, channels, generator=generator),
        sh_rest=torch.zeros(count, 0, channels),
        smoothing=torch.full((count,), 1e-5) if smoothing else None,
    )


def test_the_ply_the_viewer_reads_projects_to_the_rasterizers_own_2d_covariances(tmp_path):
    gaussians = random_gaussians(200, smoothing=True)
    write_gaussians_ply(tmp_path / "point_cloud.ply", gaussians.baked())
    splats = view_splats(read_gaussians_ply(tmp_path / "point_cloud.ply"))

    rotation, translation, focal, size = torch.eye(3), torch.tensor([0.0, 0.0, 4.0]), 100.0, 64
    expected = project(
        gaussians.means, gaussians.scales(), gaussians.quaternions, rotation, translation, focal, size, size
    )
    # The 2D covariance is J Σ Jᵀ, plus the rasterizer's low-pass filter on the diagonal.
    camera = gaussians.means.double() + translation.double()
    x, y, z = camera.unbind(1)
    jacobian = torch.zeros(len(gaussians), 2, 3, dtype=torch.float64)
    jacobian[:, 0, 0] = jacobian[:, 1, 1] = focal / z
    jacobian[:, 0, 2], jacobian[:, 1, 2] = -focal * x / z**2, -focal * y / z**2
    projected = jacobian @ torch.from_numpy(splats.covariances).double() @ jacobian.transpose(1, 2)
    a, b, c = projected[:, 0, 0] + dilation(False), projected[:, 0, 1], projected[:, 1, 1] + dilation(False)
    assert torch.allclose(torch.stack((a, b, c), 1).float(), expected.covariances2d, rtol=2e-3, atol=1e-4)
    assert np.allclose(splats.centers, gaussians.means.numpy(), atol=1e-6)
    assert np.allclose(splats.opacities[:, 0], gaussians.opacities().detach().numpy(), atol=1e-3)


def test_colours_are_the_sh_dc_term_as_rendered_and_grey_fills_three_channels():
    grey = random_gaussians(50, channels=1)
    splats = view_splats(grey)
    expected = np.clip(grey.colours(degree=0).detach().numpy(), 0.0, 1.0)
    assert splats.rgbs.shape == (50, 3) and np.allclose(splats.rgbs, np.repeat(expected, 3, axis=1))
    colour = random_gaussians(50, channels=3)
    assert np.allclose(view_splats(colour).rgbs, np.clip(colour.colours(degree=0).detach().numpy(), 0.0, 1.0))


def test_the_view_scale_keeps_small_gaussians_precise_through_float16():
    gaussians = random_gaussians(500)
    # Fine detail of a 512³ volume (voxels of 0.004 world units): σ of an eighth to half a voxel.
    gaussians.log_scales = torch.log(torch.rand(500, 3, generator=torch.Generator().manual_seed(1)) * 0.0015 + 0.0005)
    splats = view_splats(gaussians)
    scale = view_scale(splats.covariances)
    assert math.log2(scale) == round(math.log2(scale))  # a power of two scales exactly

    def worst_error(sent: np.ndarray) -> float:
        exact = splats.covariances.astype(np.float64)
        return float((np.linalg.norm(sent - exact, axis=(1, 2)) / np.linalg.norm(exact, axis=(1, 2))).max())

    scaled = splats.scaled(scale).covariances.astype(np.float16).astype(np.float64) / scale**2
    assert worst_error(scaled) < 2e-3
    assert worst_error(splats.covariances.astype(np.float16).astype(np.float64)) > 2e-2  # why the scale exists


@settings(max_examples=60, deadline=None)
@given(sigma=st.floats(1e-6, 10.0), spread=st.floats(1.0, 1e3))
def test_the_view_scale_is_finite_and_never_overflows_float16(sigma, spread):
    sigmas = np.geomspace(sigma, sigma * spread, 7)
    covariances = np.stack([np.eye(3) * s**2 for s in sigmas])
    scale = view_scale(covariances)
    assert math.isfinite(scale) and scale > 0
    assert np.isfinite((covariances * scale**2).astype(np.float16)).all() or scale == 2.0**-10
    assert float((covariances * scale**2).max()) <= FLOAT16_MAX or scale == 2.0**-10


def test_the_view_scale_of_nothing_or_of_degenerate_gaussians_is_one():
    assert view_scale(np.zeros((0, 3, 3))) == 1.0
    assert view_scale(np.zeros((4, 3, 3))) == 1.0
    assert view_scale(np.full((2, 3, 3), np.nan)) == 1.0


def test_the_clipping_plane_hides_what_lies_beyond_it():
    centers = np.array([[-0.5, 0.0, -0.9], [0.0, 0.2, 0.0], [0.3, -0.4, 0.8]])
    assert clip_mask(centers, axis_normal("axial"), 0.0).tolist() == [True, True, False]
    assert clip_mask(centers, axis_normal("axial"), 0.0, keep="above").tolist() == [False, True, True]
    assert clip_mask(centers, axis_normal("sagittal"), -1.0).tolist() == [False, False, False]
    assert clip_mask(centers, axis_normal("coronal"), 1.0).tolist() == [True, True, True]
    # Any direction (the view's): its length does not matter; a zero one clips nothing.
    assert clip_mask(centers, np.array([0.0, 0.0, 5.0]), 0.0).tolist() == [True, True, False]
    assert clip_mask(centers, np.zeros(3), 0.0).all()
    assert clip_mask(centers, np.array([np.nan, 0, 0]), 0.0).all()


@pytest.mark.parametrize("axis", ["sagittal", "coronal", "axial"])
def test_a_plane_through_the_middle_hides_about_half_of_an_even_cloud(axis):
    centers = np.random.default_rng(0).uniform(-1, 1, (4000, 3))
    kept = clip_mask(centers, axis_normal(axis), 0.0)
    assert 0.45 < kept.mean() < 0.55


def test_the_most_important_gaussians_come_first_and_broken_ones_last():
    splats = view_splats(random_gaussians(300, seed=3))
    covariances, opacities = splats.covariances.copy(), splats.opacities.copy()
    covariances[7] = np.nan
    opacities[11] = np.inf
    broken = ViewSplats(splats.centers, covariances, splats.rgbs, opacities)
    order = importance_order(broken)
    assert sorted(order.tolist()) == list(range(300))
    assert set(order[-2:].tolist()) == {7, 11}
    weight = broken.opacities[order[:-2], 0] * np.trace(broken.covariances[order[:-2]], axis1=1, axis2=2)
    assert np.all(np.diff(weight) <= 1e-12)
    assert np.array_equal(by_importance(broken).centers, broken.centers[order])
    ties = ViewSplats(np.zeros((4, 3)), np.tile(np.eye(3), (4, 1, 1)), np.zeros((4, 3)), np.ones((4, 1)))
    assert importance_order(ties).tolist() == [0, 1, 2, 3]


@settings(max_examples=80, deadline=None)
@given(total=st.integers(0, 10**7), percent=st.floats(allow_nan=True, allow_infinity=True))
def test_a_detail_draws_at_least_one_and_at_most_every_gaussian(total, percent):
    count = detail_count(total, percent)
    assert (count == 0) if total == 0 else (1 <= count <= total)
    assert 1.0 <= detail_percent(percent) <= 100.0
    if total and (math.isnan(percent) or percent >= 100):
        assert count == total


def test_detail_counts_round_up():
    assert detail_count(88759, 10) == 8876 and detail_count(10, 1) == 1 and detail_count(3, 50) == 2
