"""The rasterizer's first compilation on both cores. numba compiles on one core, and a new user's
first splat waited ~15 s for it while the other core sat idle. So the trainer starts a helper
process that compiles the backward side (``python -m cubecloud_cli.raster.cpu.backward_compile``: the
composite backward, the projection backward and the per-Gaussian sums) into numba's cache, while
the trainer itself compiles the forward side through its first render; the first backward then
loads from the cache what the helper compiled.

The helper calls the kernels with empty arrays of the training dtypes (float32 tensors; the
float64, int64 and int32 arrays the binning makes). Where training passes other types, the trainer
compiles them itself as before: the helper can only save time, never change a result. With a warm
cache the helper is stopped as soon as the forward side is seen to have come from the cache.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from cubecloud_cli.raster.cpu import binning, compositing, projection_kernels

HELPER_SECONDS = 300.0  # longer than any first compilation; then the trainer compiles itself


def compile_backward_side() -> None:
    """Compile (or load) the backward kernels for the training dtypes, on empty inputs."""

    def empty(*shape, dtype=np.float32):
        return np.zeros(shape, dtype)

    index, wide = np.int64, np.float64
    compositing.backward(
        np.zeros(1, index), empty(0, dtype=np.int32), empty(0, 4, dtype=index),
        empty(0, 2), empty(0, 3), empty(0, 1), empty(0), empty(0, dtype=wide), empty(1),
        16, 16, 1, empty(0), empty(0, dtype=np.int32), empty(0, dtype=index), empty(0, dtype=np.int32),
        empty(0, 16, dtype=np.uint16),
        empty(0, 1),
    )  # fmt: skip
    projection_kernels.project_backward(
        empty(0, 3), empty(0, 3), empty(0, 4), empty(3, 3), empty(3), 1.0, 16, 16, 0.01, 0.3, False,
        empty(0, 2), empty(0, 3), empty(0),
    )  # fmt: skip
    binning.sum_per_gaussian(
        empty(0, 7, dtype=wide), np.zeros(1, index), empty(0, 2), empty(0, 3), empty(0), empty(0, 1),
    )  # fmt: skip


class BackwardCompile:
    """The helper process, from the trainer's first render to its first backward."""

    def __init__(self, process: subprocess.Popen):
        self.process = process

    @classmethod
    def start(cls) -> "BackwardCompile | None":
        """A helper, unless this process has compiled the backward already (a second run in it)."""
        if compositing.backward.signatures:
            return None
        process = subprocess.Popen(
            [sys.executable, "-m", "cubecloud_cli.raster.cpu.backward_compile"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        return cls(process)

    def before_backward(self) -> None:
        """Wait for the helper if the forward side had to be compiled (the cache was cold, so the
        helper is compiling too); stop it if the forward side came from the cache."""
        if compositing.forward.stats.cache_misses:
            try:
                self.process.wait(timeout=HELPER_SECONDS)
                return
            except subprocess.TimeoutExpired:
                pass
        self.process.kill()
        self.process.wait()


if __name__ == "__main__":
    compile_backward_side()
