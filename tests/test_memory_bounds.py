"""Memory that holds as the cube grows: export and eval on a 256³ volume, each in a process of its
own, stay within a bound over what the process holds once its modules are imported.

The bound is about what two copies of the volume and the model would add (64 MB and 136 MB at
256³). Export before the volume was memory-mapped and the model's weights taken from the file as
they are added 658 MB here; it adds about 430 MB now. No time is measured.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from cli_helpers import invoke

pytestmark = pytest.mark.slow  # runs first: pytest-xdist's workers then end together

SIZE = 256
# Over the imports' own peak: a 64 MB volume, a 136 MB CuNeRF table and the work of a few views.
EXPORT_BOUND_MB = 560
EVAL_BOUND_MB = 560

_MEASURED = """
import atexit, sys
def peak():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM"):
            print("PEAK_KB", line.split()[1], file=sys.stderr)
atexit.register(peak)
{body}
"""
_IMPORTS = "import cubecloud_cli.export.stage, cubecloud_cli.eval.stage, cubecloud_cli.render.grid_march"


def _peak_mb(body: str) -> float:
    code = _MEASURED.format(body=body)
    finished = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert finished.returncode == 0, finished.stderr[-2000:]
    line = next(line for line in finished.stderr.splitlines() if line.startswith("PEAK_KB"))
    return int(line.split()[1]) / 1024


def _command(*args: str) -> str:
    return f"import sys; sys.argv = ['cubecloud', *{list(map(str, args))!r}]\nfrom cubecloud_cli.cli import main\ntry:\n    main()\nexcept SystemExit as exit:\n    assert not exit.code, exit.code"


@pytest.fixture(scope="module")
def work_at_256(tmp_path_factory) -> Path:
    """A 256³ work directory of a small body in a large field of view (so CuNeRF's bake skips
    most of the cube), finished with tiny views and splat runs."""
    root = tmp_path_factory.mktemp("memory")
    grids = np.meshgrid(*[np.linspace(-1, 1, 64)] * 3, indexing="ij")
    radius = sum(g**2 for g in grids)
    hu = np.where(radius < 0.08, 40.0, -1000.0)
    hu[radius < 0.02] = 700.0
    scan = root / "blob.nii.gz"
    nib.save(nib.Nifti1Image(hu.astype(np.int16), np.eye(4)), str(scan))
    work = root / "w"
    result = invoke("run", scan, "-o", work, "--size", SIZE, "--views", 4, "--resolution", 32, "--splat-iterations", 3)
    assert result.exit_code == 0, result.output
    assert json.loads((work / "preprocess" / "manifest.json").read_text())["volume"]["shape"] == [SIZE] * 3
    return work


def test_export_and_eval_at_256_cubed_stay_within_a_memory_bound(work_at_256):
    imports = _peak_mb(_IMPORTS)
    evaluated = _peak_mb(_command("eval", work_at_256, "--force", "-q")) - imports
    exported = _peak_mb(_command("export", work_at_256, "--views", 4, "--resolution", 32, "--force", "-q")) - imports
    assert exported < EXPORT_BOUND_MB, f"export held {exported:.0f} MB over its imports at {SIZE}³"
    assert evaluated < EVAL_BOUND_MB, f"eval held {evaluated:.0f} MB over its imports at {SIZE}³"
