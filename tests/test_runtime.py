"""How a stage runs: the heap setting that spares training its page faults, and --threads bounding
every thread pool, so that a stage's bits follow --threads alone."""

from __future__ import annotations

import hashlib
import resource
import sys

import numpy as np
import pytest
from cli_helpers import invoke
from threadpoolctl import threadpool_info, threadpool_limits

from cubecloud_cli.core.runtime import Runtime, keep_freed_memory
from cubecloud_cli.sample_data import sample_ct_path


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


def test_threads_bound_the_blas_pools_too():
    with threadpool_limits(limits=2):
        Runtime(threads=1).bound_cpu_threads()
        assert {pool["num_threads"] for pool in threadpool_info()} == {1}
        Runtime().bound_cpu_threads()  # no --threads: the pools stay as they are
        assert {pool["num_threads"] for pool in threadpool_info()} == {1}


def test_a_stage_gives_the_bits_of_its_threads_whatever_blas_was_set_to_before(tmp_path):
    """The resampling is a BLAS product whose last bits follow its thread count: a cohort's job
    on a cluster (OMP_NUM_THREADS=1 from Snakemake) and the same job here once differed by one
    ulp in 1,358 of 32,768 voxels."""
    digests = []
    for blas_threads in (1, 2):
        with threadpool_limits(limits=blas_threads):  # what the environment had set
            work = tmp_path / f"blas{blas_threads}"
            result = invoke(
                "run", sample_ct_path(), "-o", work, "--size", "32", "--threads", "1", "--stage", "preprocess", "-q"
            )
            assert result.exit_code == 0, result.output
            digests.append(hashlib.sha256((work / "preprocess" / "volume.npy").read_bytes()).hexdigest())
    assert digests[0] == digests[1]
