"""Every parallel CPU kernel parallelises its prange loops only (cubecloud_cli/jit.py)."""

from numba.core.registry import CPUDispatcher

from cubecloud_cli.cunerf import grid_kernels
from cubecloud_cli.jit import PRANGE_ONLY
from cubecloud_cli.raster import cpu_binning, cpu_kernels, cpu_projection


def test_parallel_kernels_convert_no_numpy_call_into_a_loop_of_its_own():
    parallel = {}
    for module in (cpu_binning, cpu_kernels, cpu_projection, grid_kernels):
        for name, value in vars(module).items():
            if isinstance(value, CPUDispatcher) and value.targetoptions.get("parallel"):
                parallel[f"{module.__name__}.{name}"] = value.targetoptions["parallel"]
    assert len(parallel) == 11
    assert all(options is PRANGE_ONLY for options in parallel.values()), parallel
    assert PRANGE_ONLY.prange and not (PRANGE_ONLY.numpy or PRANGE_ONLY.setitem or PRANGE_ONLY.fusion)
