"""The CPU rasterizer: numba kernels for projection (``projection_kernels``, ``projection_blocks``),
binning (``binning``) and compositing (``compositing``), wrapped as torch autograd functions
(``autograd``); ``backward_compile`` compiles the backward kernels in a helper process."""

from cubecloud_cli.core.lazy import lazy_exports

_EXPORTS = {
    "composite_cpu": "autograd",
    "kernel_inputs": "autograd",
    "project_cpu": "autograd",
}
__getattr__ = lazy_exports(__name__, _EXPORTS)

__all__ = ["composite_cpu", "kernel_inputs", "project_cpu"]
