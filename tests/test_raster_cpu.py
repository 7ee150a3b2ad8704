"""The pieces of the fast CPU rasterizer, each against a plain reference: the projection kernels
against autograd through ``project``, the tile binning against brute force, the inline exp
against numpy, and the backend choice (with gsplat's adapter run against a stand-in)."""

import importlib.abc
import importlib.machinery
import logging
import math
import sys
import types

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st
from numba import njit

from cubecloud_cli.cameras import OrbitSpec, orbit_cameras
from cubecloud_cli.numerics.jit import FASTMATH
from cubecloud_cli.raster import project
from cubecloud_cli.raster.backends import GSPLAT, NUMBA, TORCH, gsplat_available, gsplat_inputs, rasterizer_for
from cubecloud_cli.raster.constants import TILE
from cubecloud_cli.raster.cpu.autograd import composite_cpu, project_cpu
from cubecloud_cli.raster.cpu.binning import alpha_level, bin_tiles, natural_log, splat_boxes, sum_per_gaussian
from cubecloud_cli.raster.cpu.compositing import (
    NARROW,
    blend_row,
    exp_negative,
    narrow_row_masks,
    narrow_window,
    number_gradient_rows,
    polynomial_falloff,
    row_masks,
)
from cubecloud_cli.raster.pairs import pixel_bounds

W, H = 40, 28
CAMERAS = orbit_cameras(OrbitSpec(views=3, resolution=W, elevation=20.0))


def pose(view=1, dtype=torch.float64):
    return (torch.tensor(CAMERAS.rotations[view], dtype=dtype), torch.tensor(CAMERAS.translations[view], dtype=dtype))


def gaussians(count, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(count, 3, generator=g, dtype=dtype) * 4 - 2  # some behind the camera, some off screen
    scales = torch.exp(torch.randn(count, 3, generator=g, dtype=dtype) * 2 - 3)
    quaternions = torch.randn(count, 4, generator=g, dtype=dtype)
    quaternions[0] = 0.0
    quaternions[1] = 1e-14
    return means, scales, quaternions


def compare_projection(means, scales, quaternions, view=1, antialias=False):
    """Forward fields equal; gradients through means2d, conics (and, anti-aliased, the Mip
    filter's opacity factors) equal to autograd's."""
    rotation, translation = pose(view)
    outputs, grads = [], []
    grad_means2d = torch.randn(means.shape[0], 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    grad_conics = torch.randn(means.shape[0], 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    grad_compensations = torch.randn(means.shape[0], dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    for projector in (project, project_cpu):
        inputs = [t.clone().requires_grad_(True) for t in (means, scales, quaternions)]
        projected = projector(*inputs, rotation, translation, float(CAMERAS.focal), W, H, antialias=antialias)
        loss = (projected.means2d * grad_means2d).sum() + (projected.conics * grad_conics).sum()
        if antialias:
            loss = loss + (projected.compensations * grad_compensations).sum()
        else:
            assert projected.compensations is None
        loss.backward()
        outputs.append(projected)
        grads.append([t.grad for t in inputs])
    reference, fast = outputs
    drawn = reference.radii > 0
    assert torch.equal(fast.radii > 0, drawn)
    # ceil(3·sqrt(λ)) with λ from mid² − det: huge splats round differently by a few pixels
    assert bool(((fast.radii - reference.radii).abs() <= 1 + 1e-6 * reference.radii).all())
    torch.testing.assert_close(fast.depths, reference.depths.detach())
    for name in ("means2d", "conics", "covariances2d") + (("compensations",) if antialias else ()):
        torch.testing.assert_close(
            getattr(fast, name)[drawn].detach(), getattr(reference, name)[drawn].detach(), rtol=1e-9, atol=1e-9
        )
    tolerance = 1e-7
    # A gradient that is zero in exact arithmetic (a round Gaussian's rotation) comes out as
    # rounding noise of the terms that cancel, terms of the size of the Gaussian's other
    # gradients: each row is compared at the scale of at least a millionth of its largest.
    largest = torch.stack([g.abs().nan_to_num(0.0, 0.0, 0.0).amax(dim=1) for g in grads[0]]).amax(dim=0)
    for oracle, kernel in zip(*grads):
        rows = drawn & torch.isfinite(oracle).all(dim=1)
        scale = torch.maximum(oracle[rows].abs().amax(dim=1), 1e-6 * largest[rows]).clamp_min(1e-12)[:, None]
        if rows.any():
            assert float(((kernel[rows] - oracle[rows]).abs() / scale).max()) < tolerance
        assert torch.isfinite(kernel).all()


@pytest.mark.parametrize("antialias", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projection_kernels_match_autograd(seed, antialias):
    compare_projection(*gaussians(400, seed), antialias=antialias)


@settings(max_examples=60, deadline=None)
@given(
    st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(-3, 3)),
    st.floats(-14, 4),  # log10 of the scales: from a point to far larger than the scene
    st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)),
    st.floats(1e-3, 1e3),
    st.booleans(),
)
@example((0.0, 0.0, 0.0), 0.0, (0.0, 0.0, 0.0, 1.0), 1.0, False)  # round: rotation gradient 0 ± rounding
def test_projection_kernels_at_the_extremes(mean, log_scale, quaternion, anisotropy, antialias):
    """One Gaussian anywhere (behind the camera, at the near plane, off screen), of any size and
    shape, with any quaternion including zero, with or without the Mip filter (a point-sized
    splat sits at the compensation's floor): the kernels agree with autograd and stay finite."""
    means = torch.tensor([mean], dtype=torch.float64)
    scales = torch.tensor([[10.0**log_scale, 10.0**log_scale * anisotropy, 10.0**log_scale]], dtype=torch.float64)
    compare_projection(means, scales, torch.tensor([quaternion], dtype=torch.float64), antialias=antialias)


def test_the_inline_exp_is_accurate_wherever_a_pair_is_kept():
    powers = np.concatenate([np.linspace(0.0, 6.0, 200_001), [1e-300, math.log(255.0), 6.0]])
    approx = np.array([exp_negative(p) for p in powers])
    assert np.max(np.abs(approx - np.exp(-powers)) / np.exp(-powers)) < 1e-11
    singles = powers.astype(np.float32)
    approx = np.array([exp_negative(p) for p in singles])
    exact = np.exp(-singles.astype(np.float64))
    assert np.max(np.abs(approx - exact) / exact) < 5e-6  # float32 kernels composite in float32


@njit
def _natural_logs(values):
    out = np.empty_like(values)
    for i in range(values.size):
        out[i] = natural_log(values[i])
    return out


@njit
def _alpha_levels(opacities):
    out = np.empty(opacities.size)
    for i in range(opacities.size):
        out[i] = alpha_level(opacities[i])
    return out


@settings(deadline=None, max_examples=300)
@given(st.lists(st.floats(1e-30, 1.7976931348623157e308), min_size=1, max_size=64))
@example([1.0, 2.0, math.sqrt(2.0), math.nextafter(math.sqrt(2.0), 2.0), 255.0, 1e-30, 2.2250738585072014e-308])
@example([1.7976931348623157e308, math.nextafter(1.0, 0.0), math.nextafter(1.0, 2.0), 0.5, 3.0])
def test_the_inline_log_is_within_an_ulp_of_libms(values):
    """The splat boxes' levels come from natural_log, which a SIMD loop can run: within an ulp of
    libm's log from 1e-30 (the floor its caller clamps to) to the largest float64."""
    values = np.array(values)
    ours, exact = _natural_logs(values), np.log(values)
    assert np.all(np.abs(ours - exact) <= np.spacing(np.abs(exact)))


def test_the_inline_log_passes_infinity_and_nan_through_and_levels_floor_at_zero():
    ours = _natural_logs(np.array([math.inf, math.nan]))
    assert ours[0] == math.inf and math.isnan(ours[1])
    levels = _alpha_levels(np.array([0.0, 1e-300, 1.0 / 255.0, 1.0, 3.0, math.inf], dtype=np.float32))
    np.testing.assert_array_equal(levels[:2], 0.0)
    assert 0.0 <= levels[2] < 1e-7  # float32(1/255) × 255 rounds to within an ulp of 1
    np.testing.assert_allclose(levels[3:5], np.log(255.0 * np.array([1.0, 3.0])), rtol=1e-15)
    assert levels[5] == math.inf  # splat_boxes culls it


@settings(deadline=None)
@given(st.integers(1, (1 << TILE) - 1))
@example(0b1)
@example(1 << (TILE - 1))
@example(0b11111111 << (TILE - NARROW))
@example(0b100000001)
def test_a_narrow_window_covers_every_live_column_or_is_refused(columns):
    window = narrow_window(columns)
    assert narrow_window(np.int32(columns)) == narrow_window(np.uint16(columns)) == window  # the backward's masks
    live = [i for i in range(TILE) if columns >> i & 1]
    if live[-1] - live[0] < NARROW:
        assert 0 <= window <= TILE - NARROW and window <= live[0] and live[-1] < window + NARROW
    else:
        assert window == -1


@njit(fastmath=FASTMATH)
def _blend_one_row(transmittance, colour, weights, window, narrow, live, low, high, dx0, dy, a, b, c, cut, opacity, colour_0):  # fmt: skip
    if narrow:
        blend_row(
            transmittance, colour, weights, 0, window, NARROW, low, high, dx0, dy, a, b, c, cut, opacity, colour_0, polynomial_falloff
        )  # fmt: skip
        return narrow_row_masks(transmittance, weights, 0, window, live)
    blend_row(
        transmittance, colour, weights, 0, 0, TILE, low, high, dx0, dy, a, b, c, cut, opacity, colour_0, polynomial_falloff
    )  # fmt: skip
    return row_masks(transmittance, weights, 0, live)


@pytest.mark.parametrize("real", [np.float32, np.float64])
@settings(max_examples=60, deadline=None)
@given(
    first=st.integers(0, TILE - 1), width=st.integers(1, NARROW), u=st.floats(-4.0, 20.0), dy=st.floats(-3.0, 3.0),
    conic=st.tuples(st.floats(0.05, 3.0), st.floats(-0.5, 0.5), st.floats(0.05, 3.0)), opacity=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**16),
)  # fmt: skip
# Where a float counter of columns gave the 8-pixel loop dx = (dx0 + window) + lane, two roundings:
# column 6's weight came out 34 ulp off (compositing.COLUMNS_32).
@example(first=1, width=6, u=0.06264178507645202, dy=0.5, conic=(0.25, -0.5, 1.0), opacity=1.0, seed=0)
def test_a_narrow_row_blends_the_bits_of_a_whole_row(real, first, width, u, dy, conic, opacity, seed):
    """The 8-pixel loop gives each pixel the bits the 16-pixel loop gives it, for every input: dx
    is one rounding of dx0 + column in both, whatever the window, the column read from a table. The bit masks read from the row after either (the
    columns that stopped and that blended, which the backward undoes) are exactly the pixels whose
    T went from positive to negative, and from positive to a smaller positive value."""
    final = min(first + width - 1, TILE - 1)
    window = min(first, TILE - NARROW)
    rng = np.random.default_rng(seed)
    start = rng.uniform(1e-4, 1.0, TILE).astype(real)
    start[rng.random(TILE) < 0.2] *= -1  # stopped pixels
    start[rng.random(TILE) < 0.1] = 0  # beyond the image's edge
    dx0 = real(0.5 - u)
    level = max(np.log(255.0 * opacity), 0.0) if opacity > 0 else 0.0
    scalars = (
        dx0 + real(first - 0.5), dx0 + real(final + 0.5), dx0, real(dy), real(conic[0]), real(conic[1] * 0.9 * min(conic[0], conic[2]) ** 0.5 * 2),
        real(conic[2]), real(level + 1e-9), real(opacity), real(0.7),
    )  # fmt: skip
    rows = []
    for narrow in (True, False):
        transmittance = np.zeros((TILE, TILE), real)
        transmittance[0] = start
        colour, weights = np.zeros((TILE, TILE), real), np.zeros((TILE, TILE), real)
        live = sum(1 << i for i in range(first, final + 1) if start[i] > 0)  # under the splat, not stopped
        stopped, blended = _blend_one_row(transmittance, colour, weights, window, narrow, live, *scalars)
        after = transmittance[0]
        assert stopped == sum(1 << i for i in range(TILE) if start[i] > 0 > after[i])
        assert blended == sum(1 << i for i in range(TILE) if start[i] > after[i] > 0)
        counts = stopped, blended
        rows.append(
            (transmittance[0].tobytes(), colour[0].tobytes(), weights[0, window : window + NARROW].tobytes(), counts)
        )
    assert rows[0] == rows[1]


@pytest.mark.parametrize("channels", [1, 3])
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**16), count=st.integers(2, 300), spread=st.floats(0.1, 1.0))
@example(seed=4, count=300, spread=0.2)  # dense: most pixels stop
def test_the_backward_undoes_exactly_the_pairs_the_forward_blended(channels, seed, count, spread):
    """Under a unit gradient on every pixel of an image over a black background, a Gaussian's
    colour gradient is the sum of T·α over the pixels it blended, and summed over Gaussians it is
    the image's coverage Σ(1 − T). A pair undone by the backward that the forward did not blend,
    or the other way round, moves that sum by at least 1e-4 · 1/255 ≈ 4e-7; float64 rounding
    moves it by far less. Opacities at the α threshold, at the 0.99 cap and beyond the [0, 1]
    contract (libm's exp) take every row path of both kernels."""
    means, scales, quaternions = gaussians(count, seed)
    generator = torch.Generator().manual_seed(seed)
    opacities = torch.rand(count, dtype=torch.float64, generator=generator)
    kinds = torch.randint(0, 4, (count,), generator=generator)
    opacities[kinds == 1] = 1.0 / 255.0
    opacities[kinds == 2] = 1.0
    opacities[(kinds == 3) & (torch.rand(count, generator=generator) < 0.1)] = 3.0
    colours = torch.ones(count, channels, dtype=torch.float64, requires_grad=True)
    rotation, translation = pose()
    projected = project_cpu(means * spread, scales, quaternions, rotation, translation, float(CAMERAS.focal), W, H)
    image, coverage = composite_cpu(projected, colours, projected.effective_opacities(opacities), W, H)
    image.sum().backward()
    for channel in range(channels):
        assert abs(colours.grad[:, channel].sum().item() - coverage.sum().item()) < 1e-10


def projected_scene(count=300, seed=3):
    means, scales, quaternions = gaussians(count, seed)
    opacities = torch.rand(count, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))
    opacities[:5] = torch.tensor([0.0, 1e-6, 1.0 / 255.0, 0.5, 1.0], dtype=torch.float64)
    rotation, translation = pose()
    return project(means, scales, quaternions, rotation, translation, float(CAMERAS.focal), W, H), opacities


def test_splat_boxes_are_the_oracles_pixel_bounds():
    projected, opacities = projected_scene()
    bounds, levels = splat_boxes(
        projected.means2d.detach().numpy(),
        projected.covariances2d.detach().numpy(),
        projected.radii.numpy(),
        opacities.numpy(),
        W,
        H,
    )
    np.testing.assert_array_equal(bounds, pixel_bounds(projected, W, H, opacities).numpy())
    np.testing.assert_allclose(levels, np.log(np.maximum(255 * opacities.numpy(), 1e-30)).clip(min=0))


def brute_force_tile_lists(bounds, depths, tiles_x, tiles_y):
    """Each tile's Gaussians in stable depth order, by testing every box against every tile."""
    by_depth = np.argsort(depths, kind="stable")
    lists = []
    for tile in range(tiles_x * tiles_y):
        left, top = (tile % tiles_x) * TILE, (tile // tiles_x) * TILE
        lists.append(
            [
                g
                for g in by_depth
                if bounds[g, 1] >= max(bounds[g, 0], left)
                and bounds[g, 0] <= left + TILE - 1
                and bounds[g, 3] >= max(bounds[g, 2], top)
                and bounds[g, 2] <= top + TILE - 1
            ]
        )
    return lists


def test_tile_lists_are_the_brute_force_lists_and_gradients_sum_per_gaussian():
    projected, opacities = projected_scene(count=500, seed=4)
    bounds = pixel_bounds(projected, W, H, opacities).numpy()
    depths = projected.depths.detach().numpy().copy()
    depths[10:20] = depths[10]  # ties keep index order
    tiles_x, tiles_y = -(-W // TILE), -(-H // TILE)
    offsets, entries = bin_tiles(bounds, depths, tiles_x, tiles_y)
    lists = brute_force_tile_lists(bounds, depths, tiles_x, tiles_y)
    assert [entries[offsets[t] : offsets[t + 1]].tolist() for t in range(tiles_x * tiles_y)] == lists
    # a forward's record of the entries that blended: per tile, some of its entries, front to back,
    # from the tile's offset on (the slots after them hold whatever was there)
    blended = np.random.default_rng(1).random(entries.size) < 0.3
    blended_entries = np.full(entries.size, -1, dtype=np.int32)
    blended_counts = np.zeros(tiles_x * tiles_y, dtype=np.int64)
    for t in range(tiles_x * tiles_y):
        listed = np.flatnonzero(blended[offsets[t] : offsets[t + 1]]) + offsets[t]
        blended_entries[offsets[t] : offsets[t] + listed.size] = listed
        blended_counts[t] = listed.size
    gaussian_rows, entry_rows = number_gradient_rows(offsets, entries, blended_entries, blended_counts, 500)
    # each Gaussian's rows are its blended entries', one stretch, in the order of its tiles
    for g in range(500):
        mine = np.flatnonzero(blended & (entries == g))  # entry order is tile order
        assert entry_rows[mine].tolist() == list(range(gaussian_rows[g], gaussian_rows[g + 1]))
    values = np.random.default_rng(0).normal(size=(entries.size, 6 + 2))  # two colour channels
    expected = np.zeros((500, 8))
    np.add.at(expected, entries[blended], values[blended])
    row_grads = np.empty((gaussian_rows[-1], 8))
    row_grads[entry_rows[blended]] = values[blended]
    grads = (np.full((500, 2), np.nan), np.full((500, 3), np.nan), np.full(500, np.nan), np.full((500, 2), np.nan))
    sum_per_gaussian(row_grads, gaussian_rows, *grads)  # every Gaussian's row written, 0 where it has none
    sums = np.concatenate([grads[0], grads[1], grads[2][:, None], grads[3]], axis=1)
    np.testing.assert_allclose(sums, expected, atol=1e-12)


@st.composite
def boxes_in_an_image(draw):
    """Boxes as splat_boxes makes them: inside a width × height image, or empty in either of its
    two ways (culled: (0, −1, 0, −1); clamped off an edge: x0 = width or x1 = −1)."""
    width, height = draw(st.integers(1, 70)), draw(st.integers(1, 70))
    count = draw(st.integers(0, 40))
    bounds = np.empty((count, 4), dtype=np.int64)
    for g in range(count):
        kind = draw(st.sampled_from(["box", "box", "box", "whole", "culled", "off the right", "off the top"]))
        x0, x1 = sorted(draw(st.integers(0, width - 1)) for _ in range(2))
        y0, y1 = sorted(draw(st.integers(0, height - 1)) for _ in range(2))
        bounds[g] = {
            "box": (x0, x1, y0, y1),
            "whole": (0, width - 1, 0, height - 1),
            "culled": (0, -1, 0, -1),
            "off the right": (width, width - 1, y0, y1),
            "off the top": (x0, x1, 0, -1),
        }[kind]
    depths = np.array([draw(st.sampled_from([0.5, 1.0, 1.0, 2.0, 7.25])) for _ in range(count)])
    return bounds, depths, width, height


@settings(max_examples=60, deadline=None)
@given(boxes_in_an_image())
@example((np.array([[0, 69, 0, 69], [0, -1, 0, -1], [70, 69, 3, 5]]), np.array([1.0, 1.0, 0.5]), 70, 70))
def test_tile_lists_of_any_boxes_are_the_brute_force_lists(scene):
    """Boxes over every tile, on the last row and column of an image that is not a whole number
    of tiles, empty ones and ties in depth: each tile's list, in order, and its CSR offsets."""
    bounds, depths, width, height = scene
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    offsets, entries = bin_tiles(bounds, depths, tiles_x, tiles_y)
    lists = brute_force_tile_lists(bounds, depths, tiles_x, tiles_y)
    assert offsets.tolist() == np.cumsum([0] + [len(tile_list) for tile_list in lists]).tolist()
    assert [entries[offsets[t] : offsets[t + 1]].tolist() for t in range(tiles_x * tiles_y)] == lists


def test_the_backend_follows_the_device(monkeypatch):
    assert rasterizer_for(torch.device("cpu")) is NUMBA
    monkeypatch.setattr("cubecloud_cli.raster.backends.gsplat_available", lambda: False)
    assert rasterizer_for(torch.device("cuda")) is TORCH
    monkeypatch.setattr("cubecloud_cli.raster.backends.gsplat_available", lambda: True)
    assert rasterizer_for(torch.device("cuda")) is GSPLAT
    assert rasterizer_for(torch.device("mps")) is TORCH


@pytest.mark.parametrize(
    "backend, expected",
    [("built", True), ("no toolkit", False), ("failed build", False), ("missing dependency", False), ("moved", True)],
)
def test_gsplat_counts_only_when_its_kernels_load(monkeypatch, backend, expected):
    """gsplat builds its CUDA kernels at first import; where that fails or finds no CUDA toolkit,
    the PyTorch path draws instead, with a warning that says why."""
    package = types.ModuleType("gsplat")
    package.__spec__ = importlib.machinery.ModuleSpec("gsplat", None, is_package=True)
    cuda = types.ModuleType("gsplat.cuda")
    package.__path__, cuda.__path__ = [], []  # packages, so that the finder below is asked for _backend
    monkeypatch.setitem(sys.modules, "gsplat", package)
    monkeypatch.setitem(sys.modules, "gsplat.cuda", cuda)

    class Loader(importlib.abc.Loader):
        def create_module(self, spec):
            return None

        def exec_module(self, module):
            if backend == "failed build":
                raise RuntimeError("Error building extension 'gsplat_cuda'")
            if backend == "missing dependency":
                raise ModuleNotFoundError("No module named 'jaxtyping'", name="jaxtyping")
            if backend == "moved":
                raise ModuleNotFoundError("No module named 'gsplat.cuda._backend'", name="gsplat.cuda._backend")
            module._C = object() if backend == "built" else None

    class Finder(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            return importlib.machinery.ModuleSpec(name, Loader()) if name == "gsplat.cuda._backend" else None

    class Collect(logging.Handler):
        messages: list[str] = []

        def emit(self, record):
            self.messages.append(record.getMessage())

    # The CLI's own handler on this logger (which does not propagate) may hold a closed stream
    # from an earlier test's runner: collect the warnings here instead.
    monkeypatch.setattr(logging.getLogger("cubecloud"), "handlers", [Collect()])
    monkeypatch.setattr(sys, "meta_path", [Finder(), *sys.meta_path])
    monkeypatch.delitem(sys.modules, "gsplat.cuda._backend", raising=False)
    gsplat_available.cache_clear()
    try:
        assert gsplat_available() is expected
    finally:
        gsplat_available.cache_clear()
    warned = [message for message in Collect.messages if "using plain PyTorch" in message]
    assert len(warned) == (0 if expected else 1)


@pytest.mark.parametrize("antialias", [False, True])
def test_the_gsplat_adapter_passes_our_camera_conventions(monkeypatch, antialias):
    """A stand-in for gsplat.rasterization decodes its viewmats and Ks back into our pose and
    renders with our PyTorch path, reading eps2d and the antialiased mode as gsplat documents
    them (eps2d added to the 2D covariance; antialiased: opacity × √(det Σ / det(Σ + eps2d·I))):
    if the adapter got a convention wrong, the images differ."""
    calls = {}

    def rasterization(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        near_plane,
        eps2d,
        packed,
        rasterize_mode,
        backgrounds,
    ):
        calls.update(near_plane=near_plane, eps2d=eps2d, mode=rasterize_mode, viewmats=viewmats.shape, Ks=Ks.shape)
        rotation, translation = viewmats[0, :3, :3], viewmats[0, :3, 3]
        focal, cx, cy = float(Ks[0, 0, 0]), float(Ks[0, 0, 2]), float(Ks[0, 1, 2])
        assert (cx, cy) == (width / 2, height / 2) and float(Ks[0, 1, 1]) == focal
        plain = project(means, scales, quats, rotation, translation, focal, width, height)
        covariance = plain.covariances2d - 0.3  # the reference dilation taken off the diagonal...
        covariance[:, 1] += 0.3
        a, b, c = covariance[:, 0] + eps2d, covariance[:, 1], covariance[:, 2] + eps2d  # ... and eps2d put on
        determinant = a * c - b * b
        conics = torch.stack((c / determinant, -b / determinant, a / determinant), dim=-1)
        projected = type(plain)(plain.means2d, conics, plain.depths, plain.radii, torch.stack((a, b, c), dim=-1))
        if rasterize_mode == "antialiased":
            raw = covariance[:, 0] * covariance[:, 2] - b * b
            opacities = opacities * torch.sqrt((raw / determinant).clamp_min(0.005**2))
        from cubecloud_cli.raster.pairs import composite

        image, alpha = composite(
            projected, colors, opacities, width, height, None if backgrounds is None else backgrounds[0]
        )
        return (
            image[None],
            alpha[None, ..., None],
            {"means2d": projected.means2d[None], "radii": torch.stack([projected.radii] * 2, dim=-1)[None]},
        )

    monkeypatch.setitem(sys.modules, "gsplat", types.SimpleNamespace(rasterization=rasterization))
    means, scales, quaternions = gaussians(50, 5)
    colours = torch.rand(50, 1, dtype=torch.float64)
    opacities = torch.full((50,), 0.6, dtype=torch.float64)
    rotation, translation = pose(2)
    args = (means, scales, quaternions, opacities, colours, rotation, translation, float(CAMERAS.focal), W, H)
    ours = TORCH.render(*args, antialias=antialias)
    theirs = GSPLAT.render(*args, antialias=antialias)
    torch.testing.assert_close(theirs.image, ours.image)
    drawn = ours.radii > 0  # radii from the stand-in's plain projection: the same splats are drawn
    assert torch.equal(theirs.radii > 0, drawn)
    assert calls == {
        "near_plane": 0.2,
        "eps2d": 0.1 if antialias else 0.3,
        "mode": "antialiased" if antialias else "classic",
        "viewmats": (1, 4, 4),
        "Ks": (1, 3, 3),
    }
    viewmats, _ = gsplat_inputs(rotation, translation, float(CAMERAS.focal), W, H)
    assert torch.equal(viewmats[0, 3], torch.tensor([0, 0, 0, 1.0], dtype=torch.float64))


def test_opacities_outside_the_contract_match_the_oracle_or_are_culled():
    """Above e⁶/255 pairs reach powers beyond the exp table (the kernels fall back to libm); a
    NaN or infinite opacity culls its Gaussian instead of drawing it opaque."""
    means, scales, quaternions = gaussians(40, 9)
    means = means * 0.3
    colours = torch.rand(40, 1, dtype=torch.float64)
    rotation, translation = pose()
    args = (rotation, translation, float(CAMERAS.focal), W, H)
    # One Gaussian at a time: stacks of α clamped to exactly 0.99 land T on 1e-4 exactly, a tie
    # that products and the oracle's log sums may break either way.
    for opacity in (3.0, 50.0):
        for i in range(0, 40, 4):
            one = slice(i, i + 1)
            opacities = torch.full((1,), opacity, dtype=torch.float64)
            ours = NUMBA.render(means[one], scales[one], quaternions[one], opacities, colours[one], *args).image
            oracle = TORCH.render(means[one], scales[one], quaternions[one], opacities, colours[one], *args).image
            torch.testing.assert_close(ours, oracle, rtol=0, atol=1e-9)
    opacities = torch.full((40,), 0.5, dtype=torch.float64)
    opacities[3], opacities[4] = float("nan"), float("inf")
    projected = project(means, scales, quaternions, *args)
    bounds, _ = splat_boxes(
        projected.means2d.detach().numpy(),
        projected.covariances2d.detach().numpy(),
        projected.radii.numpy(),
        opacities.numpy(),
        W,
        H,
    )
    assert (bounds[3] == [0, -1, 0, -1]).all() and (bounds[4] == [0, -1, 0, -1]).all()
    assert torch.isfinite(NUMBA.render(means, scales, quaternions, opacities, colours, *args).image).all()


def test_a_radius_too_large_for_an_integer_is_culled():
    means = torch.tensor([[0.0, 0.0, 0.0]], dtype=torch.float64)
    quaternions = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    rotation, translation = pose()
    for scale, drawn in ((1e3, True), (1e20, False), (float("inf"), False)):
        projected = project_cpu(
            means,
            torch.full((1, 3), scale, dtype=torch.float64),
            quaternions,
            rotation,
            translation,
            float(CAMERAS.focal),
            W,
            H,
        )
        assert bool(projected.radii[0] > 0) == drawn
