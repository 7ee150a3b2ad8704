"""How a stage runs, as opposed to what it computes: device, threads, and the memory it took.

Kept out of the parameters that identify a stage's result, so the same settings on another
device count as the same stage.
"""

from __future__ import annotations

import ctypes
import resource
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING

from cubecloud_cli.core.errors import CubecloudError

if TYPE_CHECKING:  # torch is imported where a stage runs, not where the command line is read
    import torch

DEVICES = ("auto", "cpu", "cuda")


@dataclass(frozen=True)
class Runtime:
    device: str = "auto"
    """auto (CUDA when available), cpu or cuda."""
    threads: int | None = None
    """CPU threads for torch, the BLAS libraries and splat's numba kernels (default: all cores,
    and `run` trains its two splat runs side by side, on half of them each)."""

    def apply(self) -> torch.device:
        """Bound the CPU threads and return the device to run on."""
        self.bound_cpu_threads()
        keep_freed_memory()
        return resolve_device(self.device)

    def bound_cpu_threads(self) -> None:
        """Hold torch's pool and every BLAS library's (numpy's and torch's OpenBLAS, MKL) to
        ``threads``. A BLAS product splits its sums by thread, so its last bits follow the thread
        count: the same ``threads`` gives the same bits on any machine, and a 1-thread cluster job
        does not run a BLAS thread per core of its node."""
        if self.threads is None:
            return
        if self.threads < 1:
            raise CubecloudError(f"--threads {self.threads} must be at least 1")
        import torch
        from threadpoolctl import threadpool_limits

        torch.set_num_threads(self.threads)
        threadpool_limits(limits=self.threads)  # process-wide, until the next bound


# glibc's mallopt parameters: the size from which an allocation gets pages of its own, and how
# much free memory the heap's top may hold before it is handed back to the system.
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
KEPT_FREE_BYTES = 512 * 2**20


def keep_freed_memory() -> bool:
    """Let glibc's heap keep up to 512 MiB of freed memory for the next allocation instead of
    handing it back to the system. A training step allocates and frees the same few MB of
    arrays each time (the kernels' outputs, torch's gradients); by default glibc maps such
    blocks afresh and unmaps them on free, so each step touched ~2,200 new pages, zeroed by
    the kernel at a page fault each: ~10 % of a 50k-Gaussian frame on a 2-core VM
    (docs/history/rasterizer-speed.md). What an earlier stage of the same process freed is handed back first
    (``malloc_trim``), so that a stage's recorded peak memory is its own.
    Returns whether the setting took (not on other C libraries, where it is skipped)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        mallopt, malloc_trim = libc.mallopt, libc.malloc_trim
    except (OSError, AttributeError):  # musl and other C libraries have no mallopt
        return False
    malloc_trim.argtypes, malloc_trim.restype = (ctypes.c_size_t,), ctypes.c_int
    malloc_trim(0)
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, KEPT_FREE_BYTES) and mallopt(M_TRIM_THRESHOLD, KEPT_FREE_BYTES))


def resolve_device(device: str) -> torch.device:
    import torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise CubecloudError("--device cuda was asked for but torch sees no CUDA GPU: use --device cpu or auto")
    if device not in DEVICES:
        raise CubecloudError(f"--device {device!r} must be auto, cpu or cuda")
    return torch.device(device)


def reset_peak_memory(device: torch.device) -> None:
    """Start measuring peak memory afresh, so a stage run after another (in `cubecloud run`)
    reports its own peak. Linux resets the resident-set high-water mark on request; elsewhere
    the peak stays the process's."""
    try:
        with open("/proc/self/clear_refs", "w") as handle:
            handle.write("5")
    except OSError:
        pass
    if device.type == "cuda":
        import torch

        torch.cuda.reset_peak_memory_stats(device)


def _resident_high_water_kb() -> float | None:
    try:
        with open("/proc/self/status") as handle:
            for line in handle:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def peak_memory_mb(device: torch.device) -> dict[str, float]:
    """Peak resident memory since the last :func:`reset_peak_memory` where the system can tell
    (Linux), else of the whole process; and peak GPU memory on CUDA; in MB."""
    high_water = _resident_high_water_kb()
    if high_water is None:
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        high_water = rss / (1 if sys.platform != "darwin" else 1024)
    peak = {"peak_rss_mb": round(high_water / 1024, 1)}
    if device.type == "cuda":
        import torch

        peak["peak_gpu_mb"] = round(torch.cuda.max_memory_allocated(device) / 2**20, 1)
    return peak
