"""The numba settings every parallel CPU kernel compiles with.

``PRANGE_ONLY`` parallelises the loops written as ``prange`` and nothing else. With plain
``parallel=True`` numba also turns every ``np.zeros``, ``np.ones``, ``np.full``, slice
assignment and array expression of a kernel into a parallel loop of its own, each compiled as a
separate function: that made up most of the 19 s a new user waited for the rasterizer's first
compilation, for allocations that take microseconds. The ``prange`` loops, and so the kernels'
arithmetic and results, are the same either way.
"""

from numba.core.cpu import ParallelOptions

# A ParallelOptions, not a dict: numba pops the keys of a dict it is given as it reads them.
PRANGE_ONLY = ParallelOptions(
    {
        "prange": True,
        "numpy": False,
        "setitem": False,
        "reduction": False,
        "inplace_binop": False,
        "comprehension": False,
        "stencil": False,
        "fusion": False,
    }
)
