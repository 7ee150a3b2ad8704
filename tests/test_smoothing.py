"""Mip-Splatting's 3D smoothing filter: the sampling rate of the training views, the filtered
scales and opacities at the extremes, and the PLY that carries the filter baked in."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cubecloud_cli.cameras import OrbitSpec, PinholeCameras, orbit_cameras, sphere_cameras
from cubecloud_cli.raster.backends import NUMBA, TORCH
from cubecloud_cli.splat.gaussian_ply import read_gaussians_ply, write_gaussians_ply
from cubecloud_cli.splat.gaussians import Gaussians
from cubecloud_cli.splat.smoothing import (
    FILTER_SCALE,
    filter_variances,
    sampling_intervals,
    smoothed_scales,
    smoothing_attenuation,
)
from cubecloud_cli.splat.trainer import render_camera


def two_cameras_on_z(near: float, far: float, focal: float = 100.0) -> PinholeCameras:
    """Cameras on +z at distances ``near`` and ``far`` from the origin, both looking at it."""
    rotation = np.diag([1.0, -1.0, -1.0])  # looking down −z, a proper rotation
    rotations = np.stack([rotation, rotation])
    translations = np.stack([-rotation @ np.array([0, 0, near]), -rotation @ np.array([0, 0, far])])
    return PinholeCameras(rotations, translations, 64, 64, focal)


def test_the_interval_is_that_of_the_nearest_camera_that_sees_the_point():
    cameras = two_cameras_on_z(4.0, 8.0)
    means = torch.tensor(
        [
            [0.0, 0.0, 0.0],  # seen by both: the nearer one samples it more finely
            [0.0, 0.0, 1.0],  # depth 3 and 7
            [3.0, 0.0, 0.0],  # outside the near camera's view (x/z·f = 75 > 1.15·32), inside the far one's
            [0.0, 0.0, 20.0],
        ],
        dtype=torch.float64,
    )  # behind both: seen by none
    intervals = sampling_intervals(means, cameras)
    torch.testing.assert_close(intervals[:3], torch.tensor([4.0, 3.0, 8.0], dtype=torch.float64) / 100.0)
    assert float(intervals[3]) == pytest.approx(8.0 / 100.0)  # the largest interval of those seen
    torch.testing.assert_close(filter_variances(means, cameras), FILTER_SCALE * intervals**2)
    torch.testing.assert_close(filter_variances(means, cameras, 0.01), 0.01 * intervals**2)
    assert (filter_variances(means, cameras, 0.0) == 0).all()  # no filter: the scales as trained


@pytest.mark.parametrize("scale", [-0.1, float("nan"), float("inf"), 11.0])
def test_a_filter_scale_outside_its_range_is_refused_in_one_line(scale):
    from cubecloud_cli.core.errors import CubecloudError
    from cubecloud_cli.splat.settings import SplatSettings

    with pytest.raises(CubecloudError, match="--filter-scale .* must be within"):
        SplatSettings(filter_scale=scale).validate()


def test_a_sphere_of_cameras_sees_every_point_of_the_cube_at_about_its_distance():
    cameras = sphere_cameras(OrbitSpec(views=40, radius=4.0, resolution=64))
    points = torch.rand(500, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 2 - 1
    depth = sampling_intervals(points, cameras) * cameras.focal
    # The nearest camera is at most 4 − (distance of the point towards it) away, at least 4 − √3.
    assert bool((depth >= 4.0 - math.sqrt(3.0) - 1e-9).all()) and bool((depth <= 4.0 + 1e-9).all())


def test_no_cameras_in_view_falls_back_to_their_distance():
    cameras = two_cameras_on_z(4.0, 8.0)
    intervals = sampling_intervals(torch.tensor([[0.0, 0.0, 50.0]]), cameras)
    assert float(intervals[0]) == pytest.approx(6.0 / 100.0)


def test_the_compiled_pass_matches_the_definition_in_tensors():
    """Every mean against every camera, written out in torch: the nearest depth of those that see it."""
    cameras = orbit_cameras(OrbitSpec(views=24, radius=3.0, resolution=48))  # a ring in the z = 0 plane
    means = torch.rand(300, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 6 - 3
    means[::10, 2] *= 10  # far above and below the ring: seen by none
    rotations, translations = torch.as_tensor(cameras.rotations), torch.as_tensor(cameras.translations)
    camera = torch.einsum("cij,nj->cni", rotations, means) + translations[:, None]
    depth = camera[..., 2]
    limit = 1.3 * cameras.width / 2
    with torch.no_grad():
        projected = cameras.focal * camera[..., :2] / depth.clamp_min(1e-9)[..., None]
    seen = (depth > 0.2) & (projected.abs() <= limit).all(dim=-1)
    nearest = torch.where(seen, depth, torch.inf).min(dim=0).values
    expected = torch.where(seen.any(dim=0), nearest, nearest[seen.any(dim=0)].max()) / cameras.focal
    assert bool((~seen.any(dim=0)).any()) and bool(seen.any(dim=0).any())  # both kinds are in the sample
    torch.testing.assert_close(sampling_intervals(means, cameras), expected, rtol=1e-12, atol=0)


def test_means_at_the_extremes_are_seen_by_no_camera_and_keep_a_finite_interval():
    cameras = two_cameras_on_z(4.0, 8.0)
    means = torch.tensor(
        [[0.0, 0.0, 0.0], [math.nan, 0.0, 0.0], [math.inf, 0.0, 0.0], [0.0, 0.0, -math.inf], [1e300, 1e300, -1e300]],
        dtype=torch.float64,
    )
    intervals = sampling_intervals(means, cameras)
    torch.testing.assert_close(intervals, torch.full((5,), 4.0 / 100.0, dtype=torch.float64))
    alone = sampling_intervals(means[1:], cameras)  # none seen: the cameras' mean distance
    torch.testing.assert_close(alone, torch.full((4,), 6.0 / 100.0, dtype=torch.float64))


@settings(max_examples=80, deadline=None)
@given(st.lists(st.floats(-10, 10), min_size=3, max_size=3), st.floats(1e-12, 1e4))
def test_the_filter_spreads_mass_and_stays_finite_at_the_extremes(log_scales, variance):
    """Σ + vI with opacity × √(det Σ / det(Σ + vI)): opacity · √det is conserved, scales only
    grow, the attenuation stays in (0, 1], everything finite, from e⁻¹⁰ to e¹⁰ world units."""
    log_scales = torch.tensor([log_scales], dtype=torch.float64)
    variances = torch.tensor([variance], dtype=torch.float64)
    scales = smoothed_scales(log_scales, variances)
    attenuation = smoothing_attenuation(log_scales, variances)
    assert bool(torch.isfinite(scales).all()) and bool(torch.isfinite(attenuation).all())
    assert bool((scales >= torch.exp(log_scales) * (1 - 1e-12)).all())
    assert 0.0 < float(attenuation) <= 1.0
    conserved = float(torch.log(attenuation) + torch.log(scales).sum())
    assert conserved == pytest.approx(float(log_scales.sum()), abs=1e-9 * max(1.0, abs(float(log_scales.sum()))))


def test_gradients_through_the_filter_are_finite_for_tiny_and_huge_gaussians():
    log_scales = torch.tensor([[-10.0, -10.0, -10.0], [10.0, 10.0, 10.0], [-10.0, 0.0, 10.0]], requires_grad=True)
    variances = torch.tensor([1e-6, 1e-6, 1e-6])
    (smoothed_scales(log_scales, variances).sum() + smoothing_attenuation(log_scales, variances).sum()).backward()
    assert bool(torch.isfinite(log_scales.grad).all())


def random_gaussians(count=40, seed=0, smoothing=True) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(count, 3, generator=g) * 1.6 - 0.8
    log_scales = torch.log(torch.rand(count, 3, generator=g) * 0.05 + 1e-4)
    quaternions = torch.randn(count, 4, generator=g)
    logits = torch.randn(count, generator=g) * 2
    sh_dc = torch.rand(count, 1, 1, generator=g)
    gaussians = Gaussians(means, log_scales, quaternions, logits, sh_dc, torch.zeros(count, 0, 1))
    if smoothing:
        gaussians.smoothing = filter_variances(means, orbit_cameras(OrbitSpec(views=8, resolution=32)))
    return gaussians


def test_without_the_filter_the_gaussians_are_plain_3dgs():
    gaussians = random_gaussians(smoothing=False)
    torch.testing.assert_close(gaussians.scales(), torch.exp(gaussians.log_scales))
    torch.testing.assert_close(gaussians.opacities(), torch.sigmoid(gaussians.opacity_logits))
    assert gaussians.baked() is gaussians


@pytest.mark.parametrize("backend", [TORCH, NUMBA])
def test_the_baked_ply_renders_what_the_filtered_model_renders(tmp_path, backend):
    """What a viewer opens (the filter folded into scales and opacities, written and read back)
    is what training and eval render."""
    gaussians = random_gaussians()
    assert bool((gaussians.scales() > torch.exp(gaussians.log_scales)).all())
    assert bool((gaussians.opacities() < torch.sigmoid(gaussians.opacity_logits)).all())
    write_gaussians_ply(tmp_path / "g.ply", gaussians.baked())
    baked = read_gaussians_ply(tmp_path / "g.ply")
    assert baked.smoothing is None
    cameras = orbit_cameras(OrbitSpec(views=3, resolution=32, elevation=15.0))
    for view in range(3):
        ours = render_camera(gaussians, cameras, view, 0, backend, antialias=True).image
        theirs = render_camera(baked, cameras, view, 0, backend, antialias=True).image
        torch.testing.assert_close(theirs, ours, rtol=0, atol=2e-5)
