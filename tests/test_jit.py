"""Every parallel CPU kernel parallelises its prange loops only (cubecloud_cli/jit.py)."""

import numpy as np
from numba.core.registry import CPUDispatcher

from cubecloud_cli.cunerf import grid_kernels
from cubecloud_cli.jit import PRANGE_ONLY
from cubecloud_cli.raster import cpu_binning, cpu_kernels, cpu_projection
from cubecloud_cli.splat import smoothing


def test_parallel_kernels_convert_no_numpy_call_into_a_loop_of_its_own():
    parallel = {}
    for module in (cpu_binning, cpu_kernels, cpu_projection, grid_kernels, smoothing):
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.targetoptions.get("parallel"):
                parallel[f"{module.__name__}.{name}"] = value.targetoptions["parallel"]
    assert len(parallel) == 12
    assert all(options is PRANGE_ONLY for options in parallel.values()), parallel
    assert PRANGE_ONLY.prange and not (PRANGE_ONLY.numpy or PRANGE_ONLY.setitem or PRANGE_ONLY.fusion)


def test_as_real_keeps_a_kernels_arithmetic_in_its_inputs_precision():
    from numba import njit

    from cubecloud_cli.jit import as_real

    @njit
    def scaled(values):
        return values[0] * as_real(0.99, values), as_real(1.0 / 3.0, values[0])

    for dtype in (np.float32, np.float64):
        values = np.ones(1, dtype=dtype)
        product, third = scaled(values)
        assert product == dtype(0.99) and third == dtype(1.0 / 3.0)
        assert scaled.nopython_signatures[-1].return_type.types[0].bitwidth == np.dtype(dtype).itemsize * 8
    assert as_real(0.99, np.ones(1, np.float32)).dtype == np.float32
