"""The helper that compiles the rasterizer's backward side on the other core must compile exactly
what training calls. numba keys its cache by the argument types, so the helper is right when it
passes each backward kernel the same types (dtype, dimensions and layout) as a splat run does."""

import subprocess
import sys

import numba
from cli_helpers import invoke

from cubecloud_cli.raster.cpu import binning, compositing, projection_kernels
from cubecloud_cli.raster.cpu.backward_compile import BackwardCompile, compile_backward_side

BACKWARD_KERNELS = {
    (compositing, "backward"): "composite backward",
    (projection_kernels, "project_backward"): "projection backward",
    (binning, "sum_per_gaussian"): "per-Gaussian sums",
}


def record_argument_types(monkeypatch) -> dict[str, set]:
    """Wrap each backward kernel so that its calls are recorded as numba types, then run it."""
    calls: dict[str, set] = {name: set() for name in BACKWARD_KERNELS.values()}
    for (module, attribute), name in BACKWARD_KERNELS.items():
        kernel = getattr(module, attribute)

        def recorded(*args, kernel=kernel, name=name):
            calls[name].add(tuple(numba.typeof(a) for a in args))
            return kernel(*args)

        monkeypatch.setattr(module, attribute, recorded)
    return calls


def test_the_helper_compiles_the_backward_signatures_that_training_calls(tmp_path, monkeypatch):
    work = tmp_path / "work"
    for args in (
        ["preprocess", "-o", work, "--size", "32"],
        ["cunerf", work, "--iterations", "20", "--batch-size", "1024", "--holdout", "2"],
        ["export", work, "--resolution", "32", "--views", "4", "--max-points", "300", "--novel-directions", "2"],
    ):
        assert invoke(*args, "-q").exit_code == 0
    monkeypatch.setattr(BackwardCompile, "start", classmethod(lambda cls: None))
    calls = record_argument_types(monkeypatch)
    compile_backward_side()
    helper = {name: set(types) for name, types in calls.items()}
    for types in calls.values():
        types.clear()
    assert invoke("splat", work, "--iterations", "2", "--device", "cpu", "-q").exit_code == 0  # the kernels
    assert all(len(types) == 1 for types in helper.values()), helper
    assert calls == helper  # a strided slice where training passes a contiguous array would differ here


def test_the_helper_runs_as_its_own_process():
    helper = subprocess.run([sys.executable, "-m", "cubecloud_cli.raster.cpu.backward_compile"], timeout=600)
    assert helper.returncode == 0


def test_no_helper_once_this_process_has_the_backward_compiled():
    compile_backward_side()  # as a first splat run in this process would have
    assert compositing.backward.signatures
    assert BackwardCompile.start() is None
