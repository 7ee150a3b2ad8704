"""Every parallel CPU kernel parallelises its prange loops only (cubecloud_cli/numerics/jit.py)."""

import os
import platform
import re
import subprocess
import sys

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit
from numba.core.registry import CPUDispatcher
from test_raster import H, W, camera, scene

from cubecloud_cli.cunerf import grid_kernels
from cubecloud_cli.numerics import blur_kernel, ssim_kernel
from cubecloud_cli.numerics.jit import (
    EXACT_FASTMATH,
    FASTMATH,
    PRANGE_ONLY,
    negative_lanes_8,
    negative_lanes_16,
    positive_lanes_8,
    positive_lanes_16,
    prefetch,
)
from cubecloud_cli.raster.constants import TILE
from cubecloud_cli.raster.cpu import binning, compositing, projection_kernels
from cubecloud_cli.raster.cpu.autograd import _numpy, project_cpu
from cubecloud_cli.splat import smoothing

pytestmark = pytest.mark.slow  # runs first: pytest-xdist's workers then end together


def test_parallel_kernels_convert_no_numpy_call_into_a_loop_of_its_own():
    parallel = {}
    for module in (binning, compositing, projection_kernels, grid_kernels, smoothing, ssim_kernel, blur_kernel):
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.targetoptions.get("parallel"):
                parallel[f"{module.__name__}.{name}"] = value.targetoptions["parallel"]
    assert len(parallel) == 13
    assert all(options is PRANGE_ONLY for options in parallel.values()), parallel
    assert PRANGE_ONLY.prange and not (PRANGE_ONLY.numpy or PRANGE_ONLY.setitem or PRANGE_ONLY.fusion)


def test_as_real_keeps_a_kernels_arithmetic_in_its_inputs_precision():
    from numba import njit

    from cubecloud_cli.numerics.jit import as_real

    @njit
    def scaled(values):
        return values[0] * as_real(0.99, values), as_real(1.0 / 3.0, values[0])

    for dtype in (np.float32, np.float64):
        values = np.ones(1, dtype=dtype)
        product, third = scaled(values)
        assert product == dtype(0.99) and third == dtype(1.0 / 3.0)
        assert scaled.nopython_signatures[-1].return_type.types[0].bitwidth == np.dtype(dtype).itemsize * 8
    assert as_real(0.99, np.ones(1, np.float32)).dtype == np.float32


@pytest.mark.parametrize("dtype, step", [(np.float64, 2.0**-30), (np.float32, 2.0**-13)])
def test_fused_multiply_add_rounds_once(dtype, step):
    """(1 + s)² − 1 = 2s + s²: the product alone rounds s² away, the fused operation keeps it."""
    from cubecloud_cli.numerics.jit import fused_multiply_add

    @njit
    def fused(a, b, c):
        return fused_multiply_add(a, b, c)

    a, minus_one = dtype(1.0 + step), dtype(-1.0)
    result = fused(a, a, minus_one)
    assert result == dtype(2 * step + step * step) and a * a + minus_one == dtype(2 * step)
    assert fused.nopython_signatures[-1].return_type.bitwidth == np.dtype(dtype).itemsize * 8


@njit
def _lane_masks(tile, row, start):
    return (
        negative_lanes_8(tile, row, start),
        positive_lanes_8(tile, row, start),
        negative_lanes_16(tile, row, 0),
        positive_lanes_16(tile, row, 0),
    )


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**16), row=st.integers(0, TILE - 1), start=st.integers(0, TILE - 8))
def test_lane_masks_read_the_signs_of_a_row(dtype, seed, row, start):
    """The compositing kernels' row masks come from a vector compare of the row: bit i set where
    the value's sign bit is (−0 included: a stopped pixel's T is −T ≤ −0) or where it is > 0."""
    rng = np.random.default_rng(seed)
    tile = rng.choice(np.array([-1.0, -1e-30, -0.0, 0.0, 1e-30, 0.5, 1e30], dtype=dtype), size=(TILE, TILE))
    tile[rng.random((TILE, TILE)) < 0.3] = rng.normal(size=1)[0]

    def bits(values):
        return sum(1 << i for i, set_ in enumerate(values) if set_)

    window, whole = tile[row, start : start + 8], tile[row]
    expected = (bits(np.signbit(window)), bits(window > 0), bits(np.signbit(whole)), bits(whole > 0))
    assert _lane_masks(tile, row, start) == expected


@njit
def _gathered_after_prefetching(values, rows, ahead):
    total = 0.0
    for k in range(rows.size):
        prefetch(values, rows[k] + ahead)
        total += values[rows[k], 0]
    return total


def test_prefetch_is_a_hint_that_changes_nothing_and_never_faults():
    """The compositing kernels prefetch the Gaussians of entries ahead; past the end of a tile's
    list, or with any row at all, the hint must neither fault nor change a value."""
    values = np.arange(300.0).reshape(100, 3)
    rows = np.random.default_rng(0).integers(0, 100, 500)
    for ahead in (0, 4, 100, 10**6, -(10**6)):
        assert _gathered_after_prefetching(values, rows, ahead) == values[rows, 0].sum()
    if platform.machine() in ("x86_64", "AMD64"):
        assembly = _gathered_after_prefetching.inspect_asm(_gathered_after_prefetching.signatures[0])
        assert "prefetcht0" in assembly


def test_no_kernel_lets_llvm_fuse_multiply_and_add():
    """``contract`` (FMA) rounded the copy of a prange loop that a kernel compiled in the process
    runs otherwise than the copy a kernel loaded from the cache runs (cubecloud_cli/numerics/jit.py)."""
    flags = {}
    for module in (binning, compositing, projection_kernels, grid_kernels, smoothing, ssim_kernel, blur_kernel):
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.targetoptions.get("fastmath"):
                flags[f"{module.__name__}.{name}"] = value.targetoptions["fastmath"]
    assert flags and all(isinstance(f, set) and not f & {"fast", "contract"} for f in flags.values()), flags
    assert {name for name, f in flags.items() if f == EXACT_FASTMATH} == {
        "cubecloud_cli.cunerf.grid_kernels.mlp_forward",
        "cubecloud_cli.cunerf.grid_kernels.mlp_backward",
        "cubecloud_cli.numerics.ssim_kernel._blur_rows",
        "cubecloud_cli.numerics.ssim_kernel.slice_ssim_sums",
        "cubecloud_cli.numerics.blur_kernel.blur_same_into",
    }


FRESH_OR_CACHED = """
import hashlib, sys
import numpy as np
from cubecloud_cli.cunerf import grid_kernels
from cubecloud_cli.numerics import blur_kernel, ssim_kernel
from cubecloud_cli.raster.cpu import compositing
inputs = np.load(sys.argv[1])
forward = [inputs[f"forward_{i}"] for i in range(9)]
grey = forward[:5] + [np.ascontiguousarray(forward[5][:, :1])] + forward[6:]  # narrow rows: grey only
mlp = grid_kernels.mlp_forward(*[inputs[f"mlp_{i}"] for i in range(5)])
for colours in (forward, grey):
    image, transmittance, listed, counts, rows, pixels = compositing.forward(*colours, *inputs["sizes"])
    recorded = np.where((rows[:, None] >> np.arange(16)) & 1 == 1, pixels, 0)  # the rest is never written
    offsets = colours[0]
    walked = np.concatenate([listed[start : start + n] for start, n in zip(offsets[:-1], counts)])
    for array in (image, transmittance, walked, rows, recorded):
        print(hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest())
print(hashlib.sha256(mlp.tobytes()).hexdigest())
"""


def _binned_scene():
    """A float32 scene of 400 Gaussians projected and binned as training does: the tile lists
    and the forward kernel's per-Gaussian arrays (RGB colours; grey is their first channel)."""
    means, log_scales, quaternions, opacities, colours = (t.float() for t in scene(count=400, seed=5))
    cameras, rotation, translation = camera(0, torch.float32)
    projected = project_cpu(
        means * 0.5, torch.exp(log_scales), quaternions, rotation, translation, float(cameras.focal), W, H, True
    )
    effective = _numpy(projected.effective_opacities(opacities))
    means2d, tiles_x = _numpy(projected.means2d), -(-W // TILE)
    bounds, levels = binning.splat_boxes(means2d, _numpy(projected.covariances2d), projected.radii.numpy(), effective, W, H)  # fmt: skip
    offsets, entries = binning.bin_tiles(bounds, _numpy(projected.depths), tiles_x, -(-H // TILE))
    per_gaussian = (bounds, means2d, _numpy(projected.conics), _numpy(colours), effective, levels)
    return offsets, entries, per_gaussian, tiles_x


def _fresh_then_cached(script, arrays, tmp_path):
    """``script``'s output in a process that compiles the kernels into an empty numba cache, then
    in one that loads them from it; ``arrays`` reach it as the .npz file its argument names."""
    np.savez(tmp_path / "inputs.npz", **arrays)
    environment = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    return [
        subprocess.run(
            [sys.executable, "-c", script, str(tmp_path / "inputs.npz")],
            env=environment,
            capture_output=True,
            text=True,
            check=True,
        ).stdout  # fmt: skip
        for _ in ("compiled in the process", "loaded from the cache")
    ]


BACKWARD_FRESH_OR_CACHED = """
backward_head, backward_tail = [inputs[f"head_{i}"] for i in range(9)], [inputs[f"tail_{i}"] for i in range(6)]
row_grads, gaussian_rows = compositing.backward(*backward_head, *inputs["sizes"], *backward_tail)
print(hashlib.sha256(np.ascontiguousarray(row_grads).tobytes() + gaussian_rows.tobytes()).hexdigest())
"""


def test_kernels_compiled_in_the_process_give_the_bits_of_ones_loaded_from_the_cache(tmp_path):
    """The compositing forward and backward and the grid field's MLP (the kernels whose bits
    differed) run on one input in a process that compiles them into an empty cache, then in one
    that loads them from it: the same bits. A render where they differed by one float32 ulp in 92
    of 960 pixels. The forward on RGB rows and on grey ones (training's, narrow rows included);
    the backward on one frame's grey gradients, whose conic terms, as products of three factors,
    were grouped one way in each copy (compositing.pair_geometry_gradients). The projection's
    kernels take no fast-math freedom. One pair of processes for all three: each fresh process
    compiles for tens of seconds."""
    offsets, entries, per_gaussian, tiles_x = _binned_scene()
    forward = (offsets, entries, *per_gaussian)
    rng = np.random.default_rng(0)
    mlp = [rng.normal(size=shape).astype(np.float32) for shape in ((3000, 6), (6, 32), (32,), (2, 32), (2,))]
    arrays = {f"forward_{i}": a for i, a in enumerate((*forward, np.zeros(2, np.float32)))}
    arrays.update({f"mlp_{i}": a for i, a in enumerate(mlp)}, sizes=np.array([W, H, tiles_x]))

    bounds, means2d, conics, colours, effective, levels = per_gaussian
    grey = np.ascontiguousarray(colours[:, :1])  # training's case (CT), whose rows take the vector loops
    grey_arrays = (bounds, means2d, conics, grey, effective, levels, np.zeros(1, np.float32))
    _, transmittance, *blended = compositing.forward(offsets, entries, *grey_arrays, W, H, tiles_x)
    grad = np.random.default_rng(0).standard_normal((W * H, 1)).astype(np.float32)
    arrays.update({f"head_{i}": a for i, a in enumerate((offsets, entries, *grey_arrays))})
    arrays.update({f"tail_{i}": a for i, a in enumerate((transmittance, *blended, grad))})

    runs = _fresh_then_cached(FRESH_OR_CACHED + BACKWARD_FRESH_OR_CACHED, arrays, tmp_path)
    assert len(runs[0].split()) == 12 and runs[0] == runs[1]


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="reads x86 assembly")
def test_a_loop_writing_many_arrays_still_vectorizes():
    # The projection kernels' loop reads and writes many arrays; LLVM's default limit on the
    # run-time overlap checks that takes (128) leaves such a loop scalar. jit.py raises it.
    reads, writes = 6, 14
    names = [f"r{j}" for j in range(reads)] + [f"w{j}" for j in range(writes)]
    body = "\n".join(f"        w{j}[i] = t * {j + 2}.0 + r{j % reads}[i]" for j in range(writes))
    source = f"def many_columns({', '.join(names)}):\n    for i in range(r0.size):\n        t = r0[i] * r1[i]\n{body}\n"
    namespace = {}
    exec(source, namespace)
    many_columns = njit(error_model="numpy")(namespace["many_columns"])
    many_columns(*(np.ones(64) for _ in names))
    assembly = many_columns.inspect_asm(many_columns.signatures[0])
    assert re.search(r"\bv?mulpd\b", assembly), "the loop stayed scalar (mulsd only)"


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="reads x86 assembly")
def test_a_narrow_row_of_the_compositing_kernels_vectorizes():
    # A narrow row is a loop of 8 float32 pixels; LLVM's default leaves loops of under 16
    # iterations scalar, and jit.py lowers that limit to 8.
    real = np.float32

    @njit(fastmath=FASTMATH)
    def narrow_row(transmittance, colour, weights, window):
        return compositing.blend_row(
            transmittance, colour, weights, 0, window, compositing.NARROW, real(-8.0), real(8.0), real(-4.5),
            real(0.3), real(0.2), real(0.01), real(0.2), real(5.0), real(0.5), real(1.0), compositing.polynomial_falloff,
        )  # fmt: skip

    narrow_row(np.ones((TILE, TILE), real), np.zeros((TILE, TILE), real), np.zeros((TILE, TILE), real), 3)
    assembly = narrow_row.inspect_asm(narrow_row.signatures[0])
    assert re.search(r"\bv?mulps\b", assembly), "the narrow row stayed scalar (mulss only)"
