"""The plain PyTorch rasterizer (the oracle of the fast kernels): projection, compositing rules
against a literal per-pixel loop, gradients by finite differences, and the extremes."""

import math

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st

from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
from cubecloud_cli.raster import composite, covariances, project
from cubecloud_cli.raster.backends import NUMBA, TORCH
from cubecloud_cli.raster.cpu.autograd import composite_cpu
from cubecloud_cli.raster.cpu.binning import stable_depth_order
from cubecloud_cli.raster.pairs import MAX_ALPHA, MIN_ALPHA, TRANSMITTANCE_STOP

COMPOSITORS = {"torch": composite, "numba": composite_cpu}

W, H = 24, 20


def camera(view=0, dtype=torch.float64):
    cameras = orbit_cameras(OrbitSpec(views=4, resolution=W, elevation=10.0))
    rotation = torch.tensor(cameras.rotations[view], dtype=dtype)
    translation = torch.tensor(cameras.translations[view], dtype=dtype)
    return cameras, rotation, translation


def scene(count=30, seed=0, dtype=torch.float64):
    """Random Gaussians with the extremes mixed in."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(count, 3, generator=g, dtype=dtype) * 1.6 - 0.8
    log_scales = torch.log(torch.rand(count, 3, generator=g, dtype=dtype) * 0.08 + 0.01)
    quaternions = torch.randn(count, 4, generator=g, dtype=dtype)
    opacities = torch.rand(count, generator=g, dtype=dtype)
    colours = torch.rand(count, 2, generator=g, dtype=dtype)
    log_scales[0] = math.log(1e-6)  # tiny: a dilated point
    log_scales[1] = math.log(3.0)  # huge: covers the image
    opacities[2], opacities[3] = 1e-4, 0.9999  # near 0 and near 1
    means[5] = means[4]  # identical, overlapping
    log_scales[5], quaternions[5], opacities[5], colours[5] = log_scales[4], quaternions[4], opacities[4], colours[4]
    means[6] = torch.tensor([9.0, 0.0, 0.0], dtype=dtype)  # off screen
    return means, log_scales, quaternions, opacities, colours


def render_and_differentiate(backend, tensors, weights, background, antialias, device="cpu"):
    """Render (means, log-scales, quaternions, opacities, colours) through ``backend`` from camera 0
    on ``device`` and backpropagate Σ weights · image: the image, the screen-space gradient and the
    five inputs' gradients."""
    cameras, rotation, translation = camera(0, tensors[0].dtype)
    inputs = [t.to(device).clone().requires_grad_(True) for t in tensors]
    rendered = backend.render(
        inputs[0],
        torch.exp(inputs[1]),
        *inputs[2:],
        rotation.to(device),
        translation.to(device),
        float(cameras.focal),
        W,
        H,
        background=background.to(device),
        retain_screen_grad=True,
        antialias=antialias,
    )
    (rendered.image * weights.to(device)).sum().backward()
    return rendered.image.detach(), rendered.screen_gradient(), [t.grad for t in inputs]


def render(means, log_scales, quaternions, opacities, colours, view=0, background=None, compositor=composite):
    cameras, rotation, translation = camera(view, means.dtype)
    projected = project(means, torch.exp(log_scales), quaternions, rotation, translation, float(cameras.focal), W, H)
    return compositor(projected, colours, opacities, W, H, background), projected


def literal_loop(projected, colours, opacities, background):
    """The reference algorithm, pixel by pixel, Gaussian by Gaussian (docs/references.md §1.9)."""
    image = np.zeros((H, W, colours.shape[1]))
    order = torch.argsort(projected.depths, stable=True).tolist()
    m, conic, radii = projected.means2d.detach().numpy(), projected.conics.detach().numpy(), projected.radii.numpy()
    for v in range(H):
        for u in range(W):
            transmittance, colour = 1.0, np.zeros(colours.shape[1])
            for i in order:
                if radii[i] == 0 or abs(u + 0.5 - m[i, 0]) > radii[i] or abs(v + 0.5 - m[i, 1]) > radii[i]:
                    continue
                dx, dy = u + 0.5 - m[i, 0], v + 0.5 - m[i, 1]
                power = 0.5 * (conic[i, 0] * dx * dx + conic[i, 2] * dy * dy) + conic[i, 1] * dx * dy
                alpha = min(MAX_ALPHA, float(opacities[i]) * math.exp(-power))
                if alpha < MIN_ALPHA:
                    continue
                if transmittance * (1 - alpha) < TRANSMITTANCE_STOP:
                    break
                colour += transmittance * alpha * colours[i].detach().numpy()
                transmittance *= 1 - alpha
            image[v, u] = colour + transmittance * background
    return image


@pytest.mark.parametrize("backend", COMPOSITORS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compositing_follows_the_reference_rules(seed, backend):
    means, log_scales, quaternions, opacities, colours = scene(seed=seed)
    background = torch.tensor([0.2, 0.0], dtype=torch.float64)
    (image, coverage), projected = render(
        means, log_scales, quaternions, opacities, colours, background=background, compositor=COMPOSITORS[backend]
    )
    expected = literal_loop(projected, colours, opacities, background.numpy())
    np.testing.assert_allclose(image.detach().numpy(), expected, atol=1e-10)
    assert coverage.min() >= 0 and coverage.max() <= 1


@pytest.mark.parametrize("backend", COMPOSITORS)
def test_an_opaque_stack_stops_early(backend):
    # 20 identical, nearly opaque Gaussians: only the first few are blended at each pixel.
    means = torch.zeros(20, 3, dtype=torch.float64)
    log_scales = torch.full((20, 3), math.log(0.3), dtype=torch.float64)
    quaternions = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).repeat(20, 1)
    opacities = torch.full((20,), 0.99, dtype=torch.float64)
    colours = torch.rand(20, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    (image, coverage), projected = render(
        means,
        log_scales,
        quaternions,
        opacities,
        colours,
        background=torch.ones(1, dtype=torch.float64),
        compositor=COMPOSITORS[backend],
    )
    expected = literal_loop(projected, colours, opacities, np.ones(1))
    np.testing.assert_allclose(image.detach().numpy(), expected, atol=1e-10)
    assert 0.9998 < coverage[H // 2, W // 2] <= 1 - TRANSMITTANCE_STOP  # two blended; a third would pass T 1e-4


def test_projection_matches_the_cameras():
    cameras, rotation, translation = camera(2)
    means = torch.tensor([[0.3, -0.2, 0.5], [0.0, 0.0, 0.0]], dtype=torch.float64)
    scale = 0.05
    identity = torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=torch.float64)
    projected = project(
        means,
        torch.full((2, 3), scale, dtype=torch.float64),
        identity,
        rotation,
        translation,
        float(cameras.focal),
        W,
        H,
    )
    pixels, depth = cameras.project(2, means.numpy())
    # Width and height differ here only through cx, cy; the orbit's cameras are square.
    pixels[:, 1] += (H - W) / 2
    np.testing.assert_allclose(projected.means2d.numpy(), pixels, atol=1e-9)
    np.testing.assert_allclose(projected.depths.numpy(), depth, atol=1e-12)
    # An isotropic Gaussian at the origin (on the optical axis) projects to a circle of
    # variance (f·s/z)², plus the 0.3 px² dilation.
    variance = (cameras.focal * scale / depth[1]) ** 2 + 0.3
    np.testing.assert_allclose(projected.covariances2d[1].numpy(), [variance, 0.0, variance], atol=1e-9)
    assert projected.radii[1] == math.ceil(3 * math.sqrt(variance))


def test_projected_covariance_is_the_ewa_matrix_product():
    """J W Σ Wᵀ Jᵀ + 0.3 I with matrices, against the element-wise form, clamps included."""
    means, log_scales, quaternions, _, _ = scene(count=40, seed=5)
    means[:5] *= 4.0  # some far off to the sides, where the Jacobian's x/z, y/z are clamped
    cameras, rotation, translation = camera(3)
    projected = project(means, torch.exp(log_scales), quaternions, rotation, translation, float(cameras.focal), W, H)
    camera_points = means @ rotation.T + translation
    z = camera_points[:, 2]
    limit_x, limit_y = 1.3 * (W / 2) / cameras.focal, 1.3 * (H / 2) / cameras.focal
    tx = (camera_points[:, 0] / z).clamp(-limit_x, limit_x) * z
    ty = (camera_points[:, 1] / z).clamp(-limit_y, limit_y) * z
    f = cameras.focal
    jacobian = torch.zeros(40, 2, 3, dtype=torch.float64)
    jacobian[:, 0, 0], jacobian[:, 0, 2] = f / z, -f * tx / z**2
    jacobian[:, 1, 1], jacobian[:, 1, 2] = f / z, -f * ty / z**2
    transform = jacobian @ rotation
    cov2d = transform @ covariances(torch.exp(log_scales), quaternions) @ transform.transpose(1, 2)
    expected = torch.stack((cov2d[:, 0, 0] + 0.3, cov2d[:, 0, 1], cov2d[:, 1, 1] + 0.3), dim=1)
    visible = z > 0.2
    torch.testing.assert_close(projected.covariances2d[visible], expected[visible], rtol=1e-10, atol=1e-12)


def test_culling_near_plane_and_off_screen():
    cameras, rotation, translation = camera(0)
    centre = torch.tensor(cameras.centres()[0], dtype=torch.float64)
    forward = rotation[2]
    means = torch.stack(
        [
            centre + 0.1 * forward,
            centre - forward,
            centre + 3 * forward,
            torch.tensor([0.0, 0.0, 50.0], dtype=torch.float64),
        ]
    )
    identity = torch.tensor([[1.0, 0, 0, 0]] * 4, dtype=torch.float64)
    projected = project(
        means,
        torch.full((4, 3), 0.01, dtype=torch.float64),
        identity,
        rotation,
        translation,
        float(cameras.focal),
        W,
        H,
    )
    assert projected.radii.tolist()[:2] == [0, 0] and projected.radii[2] > 0 and projected.radii[3] == 0
    assert torch.isfinite(projected.means2d).all() and torch.isfinite(projected.conics).all()
    image, coverage = composite(
        projected, torch.ones(4, 1, dtype=torch.float64), torch.ones(4, dtype=torch.float64), W, H
    )
    assert torch.isfinite(image).all()


def test_a_gaussian_is_drawn_where_its_mean_projects():
    cameras, rotation, translation = camera(1)
    point = torch.tensor([[0.35, -0.4, 0.25]], dtype=torch.float64)
    identity = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64)
    projected = project(
        point,
        torch.full((1, 3), 0.02, dtype=torch.float64),
        identity,
        rotation,
        translation,
        float(cameras.focal),
        W,
        H,
    )
    image, _ = composite(
        projected, torch.ones(1, 1, dtype=torch.float64), torch.full((1,), 0.9, dtype=torch.float64), W, H
    )
    row, column = np.unravel_index(int(torch.argmax(image[..., 0])), (H, W))
    assert (column, row) == tuple(int(c) for c in torch.floor(projected.means2d[0]).tolist())


def test_empty_views_render_the_background():
    cameras, rotation, translation = camera(0)
    empty = torch.zeros(0, 3, dtype=torch.float64)
    projected = project(
        empty,
        torch.zeros(0, 3, dtype=torch.float64),
        torch.zeros(0, 4, dtype=torch.float64),
        rotation,
        translation,
        float(cameras.focal),
        W,
        H,
    )
    image, coverage = composite(
        projected,
        torch.zeros(0, 1, dtype=torch.float64),
        torch.zeros(0, dtype=torch.float64),
        W,
        H,
        torch.tensor([0.25], dtype=torch.float64),
    )
    assert torch.all(image == 0.25) and not coverage.any()


def test_gradients_match_finite_differences():
    means, log_scales, quaternions, opacities, colours = scene(count=8, seed=4)
    opacity_logits = torch.logit(opacities.clamp(1e-3, 1 - 1e-3))
    inputs = [t.clone().requires_grad_(True) for t in (means, log_scales, quaternions, opacity_logits, colours)]
    weights = torch.rand(H, W, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(9))

    def loss(m, s, q, o, c):
        (image, _), _ = render(m, s, q, torch.sigmoid(o), c)
        return (image * weights).sum()

    assert torch.autograd.gradcheck(loss, inputs, eps=1e-7, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("antialias", [False, True])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("seed", [0, 3, 7])
def test_the_numba_kernels_match_the_oracle_and_its_gradients(seed, dtype, antialias):
    """The whole numba path (projection and compositing) against the PyTorch path: forward and
    every gradient within 1e-4 relative, on scenes with the extremes: tiny and huge scales,
    opacity near 0 and 1, identical Gaussians, one off screen, one at the near plane, one behind
    the camera and a zero quaternion; plain and through the 2D Mip filter."""
    means, log_scales, quaternions, opacities, colours = (t.to(dtype) for t in scene(count=60, seed=seed))
    cameras = camera(0, dtype)[0]
    forward = torch.tensor(cameras.rotations[0][2], dtype=dtype)
    centre = torch.tensor(cameras.centres()[0], dtype=dtype)
    means[7] = centre + 0.21 * forward  # just past the near plane
    means[8] = centre - 0.5 * forward  # behind the camera
    quaternions[9] = 0.0  # degenerate rotation
    weights = torch.rand(H, W, 2, dtype=dtype, generator=torch.Generator().manual_seed(seed))
    tensors, background = (means, log_scales, quaternions, opacities, colours), torch.tensor([0.1, 0.3], dtype=dtype)
    results = {b.name: render_and_differentiate(b, tensors, weights, background, antialias) for b in (TORCH, NUMBA)}
    tolerance = 1e-4 if dtype == torch.float64 else 2e-3
    (image_t, screen_t, grads_t), (image_n, screen_n, grads_n) = results["torch"], results["numba"]
    torch.testing.assert_close(image_n, image_t, rtol=0, atol=1e-6 if dtype == torch.float64 else 1e-5)
    for oracle, fast in zip([screen_t, *grads_t], [screen_n, *grads_n]):
        assert torch.isfinite(fast).all()
        scale = oracle.abs().max().clamp_min(1e-12)
        assert float((fast - oracle).abs().max() / scale) < tolerance


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_numba_compositor_reports_coverage_like_the_oracle(dtype):
    means, log_scales, quaternions, opacities, colours = (t.to(dtype) for t in scene(count=60, seed=5))
    coverages = [
        render(means, log_scales, quaternions, opacities, colours, compositor=c)[0][1] for c in COMPOSITORS.values()
    ]
    torch.testing.assert_close(coverages[1], coverages[0], rtol=0, atol=1e-6 if dtype == torch.float64 else 1e-5)


@settings(max_examples=40, deadline=None)
@example([0.0, -0.0, 2.0, -0.0, 2.0])
@given(
    st.lists(
        st.sampled_from([0.0, -0.0, 1e-300, -1.5, 2.0, 2.0, 3.25, 1e300, -1e300, 7.0]) | st.floats(-1e6, 1e6),
        min_size=0,
        max_size=300,
    )
)
def test_radix_depth_order_is_a_stable_sort(depths):
    depths = np.asarray(depths, dtype=np.float64)
    candidates = np.arange(depths.size, dtype=np.int64)
    np.testing.assert_array_equal(stable_depth_order(candidates, depths), np.argsort(depths, kind="stable"))


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.floats(2.0, 2.0099999904632568, width=32, allow_subnormal=False) | st.sampled_from([2.0, 2.005]),
        min_size=0,
        max_size=300,
    )
)
def test_radix_depth_order_of_nearby_float32_depths_is_a_stable_sort(depths):
    """Training's case: float32 depths in a narrow range, where most 11-bit digits of the keys are
    the same in every key and only those that differ take a pass."""
    depths = np.asarray(depths, dtype=np.float32)
    candidates = np.arange(depths.size, dtype=np.int64)
    np.testing.assert_array_equal(stable_depth_order(candidates, depths), np.argsort(depths, kind="stable"))


def test_the_mip_filter_replaces_the_dilation_and_plain_3dgs_is_untouched():
    """Off, the projection is the reference's (0.3 px² added, no opacity factor); on, 0.1 px² is
    added and the opacity factor is √(det Σ₂ / det(Σ₂ + 0.1 I)) of the undilated footprint."""
    means, log_scales, quaternions, opacities, colours = scene(count=30, seed=2)
    cameras, rotation, translation = camera(0)
    args = (means, torch.exp(log_scales), quaternions, rotation, translation, float(cameras.focal), W, H)
    plain, mip = project(*args), project(*args, antialias=True)
    assert plain.compensations is None and torch.equal(plain.effective_opacities(opacities), opacities)
    footprint = plain.covariances2d - torch.tensor([0.3, 0.0, 0.3], dtype=torch.float64)
    torch.testing.assert_close(mip.covariances2d, footprint + torch.tensor([0.1, 0.0, 0.1], dtype=torch.float64))
    a, b, c = footprint.unbind(1)
    expected = torch.sqrt(((a * c - b * b) / ((a + 0.1) * (c + 0.1) - b * b)).clamp_min(0.005**2))
    torch.testing.assert_close(mip.compensations, expected, rtol=1e-9, atol=1e-12)
    assert bool(((mip.compensations > 0) & (mip.compensations <= 1)).all())
    # A splat of a hundred pixels keeps its opacity; one far below a pixel fades to the floor.
    assert float(mip.compensations[1]) > 0.999 and float(mip.compensations[0]) == pytest.approx(0.005)


@settings(max_examples=60, deadline=None)
@given(st.floats(-12, 3), st.floats(1e-3, 1e3), st.floats(0.0, 1.0))
def test_the_mip_filter_conserves_a_splats_mass_and_never_brightens(log_scale, anisotropy, opacity):
    """ρ·√det(Σ₂ + vI) = √det Σ₂ (the filter spreads a splat, it adds no mass) until ρ reaches its
    floor, and the opacity never grows: a zoomed-out splat cannot outshine what it was."""
    scales = torch.tensor([[10.0**log_scale, 10.0**log_scale * anisotropy, 10.0**log_scale]], dtype=torch.float64)
    cameras, rotation, translation = camera(1)
    projected = project(
        torch.zeros(1, 3, dtype=torch.float64),
        scales,
        torch.tensor([[1.0, 0.2, -0.3, 0.1]], dtype=torch.float64),
        rotation,
        translation,
        float(cameras.focal),
        W,
        H,
        antialias=True,
    )
    rho = float(projected.compensations[0])
    a, b, c = (float(v) for v in projected.covariances2d[0])
    raw = (a - 0.1) * (c - 0.1) - b * b
    assert math.isfinite(rho) and 0.005 <= rho <= 1.0
    if rho > 0.005 * (1 + 1e-9):
        assert rho * math.sqrt(a * c - b * b) == pytest.approx(math.sqrt(max(raw, 0.0)), rel=1e-6, abs=1e-12)
    effective = float(projected.effective_opacities(torch.tensor([opacity], dtype=torch.float64))[0])
    assert 0.0 <= effective <= opacity
