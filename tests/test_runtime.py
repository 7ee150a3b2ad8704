"""How a stage runs: the heap setting that spares training its page faults."""

from __future__ import annotations

import resource
import sys

import numpy as np
import pytest

from cubecloud_cli.core.runtime import Runtime, keep_freed_memory


def _faults_over_steps(steps: int) -> int:
    """Minor page faults while a step-like pattern runs ``steps`` times: five 4 MB arrays alive
    together, filled, then all freed (as a training step's kernel outputs and gradients are)."""
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(steps):
        arrays = [np.ones(4 * 2**20, dtype=np.uint8) for _ in range(5)]
        del arrays
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a glibc heap setting")
def test_applying_the_runtime_lets_freed_arrays_be_reused_without_page_faults():
    if not keep_freed_memory():
        pytest.skip("this C library has no mallopt")
    Runtime(device="cpu").apply()
    _faults_over_steps(1)  # the first step grows the heap: its pages fault once
    # By default glibc hands the 20 MB back after each step and the next one faults on every
    # page again (~20,000 faults over ten steps here); kept, they are reused.
    assert _faults_over_steps(10) < 4 * 2**20 // resource.getpagesize()


def _resident_mb() -> float:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * resource.getpagesize() / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a glibc heap setting")
def test_the_next_stage_starts_by_handing_back_what_the_last_one_freed():
    if not keep_freed_memory():
        pytest.skip("this C library has no mallopt")
    block = np.ones(64 * 2**20, dtype=np.uint8)  # under the kept size: from the heap
    del block
    kept = _resident_mb()
    Runtime(device="cpu").apply()  # as each stage of `cubecloud run` does when it starts
    # so the stage's recorded peak is its own, not the earlier stage's leftovers
    assert _resident_mb() < kept - 48
