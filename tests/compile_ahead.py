"""numba's first compilation of the kernels the suite calls, before the tests start, as two jobs
on the two cores (tests/conftest.py starts them when the cache is cold).

In a fresh clone the suite compiled for about 4 minutes in the pytest process alone, on one core:
the rasterizer's forward, backward and projection kernels in float32 and float64 (about 20 s each
on the 2-core VM), the SSIM kernel, the bake, the march. Under pytest-xdist both workers would
compile the same kernels at once. Here one job runs a tiny pipeline through the CLI (every
float32 kernel a stage calls, with the stages' own dtypes and layouts) and the grid bake, the
other the float64 rasterizer (the oracle tests) and both dtypes of the SSIM kernel. numba writes
each to its cache, and the tests load them from it. A kernel called here with other types than a test
uses only costs that test its own compilation, as before: nothing here changes a result.

    python tests/compile_ahead.py float32|float64
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path


def float32_stages() -> None:
    """A tiny work directory through every stage, as the CLI tests make them, the grid bake
    (which the stages take from 256³ on) and a scalar splat's own kernels."""
    import numpy as np
    from cli_helpers import invoke, tiny_work
    from test_grid_bake import model_with_structure

    from cubecloud_cli.cunerf import grid_bake
    from cubecloud_cli.splat.on_cpu import compile_scalar_kernels

    grid_bake.bake_lattice(model_with_structure(), 8, None, np.empty((8, 8, 8), dtype=np.float32))
    compile_scalar_kernels()
    with tempfile.TemporaryDirectory(prefix="cubecloud-compile-ahead-") as scratch:
        work = Path(scratch) / "work"
        splat = ["--iterations", "2", "--device", "cpu"]
        tiny_work(work, cunerf_iterations=20, views=4, max_points=300, novel_directions=2, splat=splat)
        result = invoke("eval", work, "-q")
        if result.exit_code != 0:
            raise SystemExit(f"compile ahead: eval failed: {result.output[-2000:]}")


def float64_and_large() -> None:
    """The float64 rasterizer with its gradients, the SSIM kernel in both dtypes, the training
    SSIM's window and the scalar appearance (its oracle and finite-difference tests) in float64 (the
    two jobs take about as long: 2 minutes each on the 2-core VM)."""
    import numpy as np
    import torch
    from test_raster import H, W, render_and_differentiate, scene

    from cubecloud_cli.numerics.blur_kernel import blur_same
    from cubecloud_cli.numerics.metrics import K1, K2, gaussian_window
    from cubecloud_cli.numerics.ssim_kernel import stack_ssim_sums
    from cubecloud_cli.raster.backends import NUMBA
    from cubecloud_cli.splat.on_cpu import compile_scalar_appearance

    weights = torch.rand(H, W, 2, dtype=torch.float64)
    render_and_differentiate(NUMBA, scene(count=20), weights, torch.zeros(2, dtype=torch.float64), False)
    window = gaussian_window().numpy()
    for dtype in (np.float32, np.float64):
        stack = np.random.default_rng(0).random((2, 16, 16)).astype(dtype)
        stack_ssim_sums(stack, stack, stack > 0.5, window, K1**2, K2**2)
    blur_same(np.zeros((1, 4, 4)), window)
    compile_scalar_appearance(torch.float64)


JOBS = {"float32": float32_stages, "float64": float64_and_large}

if __name__ == "__main__":
    JOBS[sys.argv[1]]()
