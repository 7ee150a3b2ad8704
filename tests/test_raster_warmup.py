"""The helper that compiles the rasterizer's backward side on the other core must compile exactly
what training calls: after it has filled an empty numba cache, a splat run loads the backward
kernels from there and compiles none of them itself."""

import json
import os
import subprocess
import sys

from cli_helpers import invoke

from cubecloud_cli.raster import cpu_kernels
from cubecloud_cli.raster.cpu_warmup import BackwardCompile, compile_backward_side

# Runs `cubecloud splat` with the trainer's own helper switched off, then reports per backward
# kernel whether this process compiled it (a cache miss) or loaded it (a hit).
SPLAT_THEN_REPORT = """
import json, sys
import cubecloud_cli.raster.cpu_warmup as warmup
warmup.BackwardCompile.start = classmethod(lambda cls: None)
from cubecloud_cli.cli import main
from cubecloud_cli.raster import cpu_binning, cpu_kernels, cpu_projection
sys.argv = ["cubecloud", "splat", sys.argv[1], "--iterations", "2", "-q"]
try:
    main()
except SystemExit as exit:
    assert not exit.code, exit.code
kernels = {"composite backward": cpu_kernels.backward, "projection backward": cpu_projection.project_backward,
           "per-Gaussian sums": cpu_binning.sum_per_gaussian}
print(json.dumps({name: [len(k.stats.cache_hits), len(k.stats.cache_misses)] for name, k in kernels.items()}))
"""


def test_the_helper_compiles_the_backward_kernels_that_training_loads(tmp_path):
    work = tmp_path / "work"
    for args in (
        ["preprocess", "-o", work, "--size", "32"],
        ["cunerf", work, "--iterations", "20", "--batch-size", "1024", "--holdout", "2"],
        ["export", work, "--resolution", "32", "--views", "4", "--max-points", "300", "--novel-directions", "2"],
    ):
        assert invoke(*args, "-q").exit_code == 0
    environment = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}
    helper = subprocess.run([sys.executable, "-m", "cubecloud_cli.raster.cpu_warmup"], env=environment, timeout=600)
    assert helper.returncode == 0
    splat = subprocess.run([sys.executable, "-c", SPLAT_THEN_REPORT, str(work)],
                           env=environment, capture_output=True, text=True, timeout=600)  # fmt: skip
    assert splat.returncode == 0, splat.stderr
    loaded = json.loads(splat.stdout.strip().splitlines()[-1])
    assert loaded == {name: [1, 0] for name in loaded}, loaded  # one signature each, from the cache


def test_no_helper_once_this_process_has_the_backward_compiled():
    compile_backward_side()  # as a first splat run in this process would have
    assert cpu_kernels.backward.signatures
    assert BackwardCompile.start() is None
