from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

MACHINE_CORES: set[int] | None = None  # the cores before this worker was pinned to its share


def _pin_this_worker() -> None:
    """Under pytest-xdist each worker keeps to its own share of the cores, and so do the processes
    its tests start (the CLI sizes its threads by the cores it may use). Otherwise two workers'
    torch and numba threads, two each on a 2-core host, wait on each other: the suite ran 1.5×
    slower than with one thread each. numba's pool keeps its full size, so a test may still widen
    the kernels (on the worker's cores)."""
    worker, count = os.environ.get("PYTEST_XDIST_WORKER"), int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if not worker or count < 2 or not hasattr(os, "sched_setaffinity"):
        return
    global MACHINE_CORES
    MACHINE_CORES = os.sched_getaffinity(0)
    cores = sorted(MACHINE_CORES)
    os.environ.setdefault("NUMBA_NUM_THREADS", str(len(cores)))
    index = int(worker.removeprefix("gw"))
    os.sched_setaffinity(0, cores[index % len(cores) :: count] or cores)


_pin_this_worker()  # before numpy, torch or numba start their threads

import nibabel as nib  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("CUBECLOUD_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(autouse=True, scope="session")
def ctrl_c_is_delivered():
    """The interrupt tests send themselves a real SIGINT. A shell that starts pytest in the
    background (`&`, nohup, some CI runners) leaves SIGINT ignored, and cubecloud rightly keeps it
    ignored, so the tests' Ctrl-C would vanish; give the session Python's own handler instead."""
    previous = signal.getsignal(signal.SIGINT)
    if previous == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def _numba_cache_is_cold() -> bool:
    """Whether the rasterizer's backward kernel was never compiled into numba's cache here."""
    root = Path(os.environ.get("NUMBA_CACHE_DIR") or REPO / "cubecloud_cli" / "raster" / "cpu" / "__pycache__")
    return not any(root.rglob("compositing.backward-*.nbi")) if root.exists() else True


def pytest_sessionstart(session):
    """On a cold numba cache (a fresh clone, CI), compile the kernels before any test runs, in two
    processes at once (tests/compile_ahead.py). Only the first process does this: pytest-xdist's
    workers start after it."""
    if os.environ.get("PYTEST_XDIST_WORKER") or not _numba_cache_is_cold():
        return
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    start = time.perf_counter()
    jobs = {
        job: subprocess.Popen(
            [sys.executable, str(Path(__file__).with_name("compile_ahead.py")), job],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )  # fmt: skip
        for job in ("float32", "float64")
    }
    for job, process in jobs.items():
        output, _ = process.communicate()
        if process.returncode != 0 and reporter is not None:  # the tests then compile for themselves
            reporter.write_line(f"compile ahead ({job}) failed:\n{output[-3000:]}", red=True)
    if reporter is not None:
        reporter.write_line(f"numba's kernels compiled ahead in {time.perf_counter() - start:.0f} s (a cold cache)")


@pytest.fixture
def every_core():
    """The machine's cores for this test, as outside pytest-xdist (tests of how runs share them)."""
    if MACHINE_CORES is None:
        yield
        return
    own = os.sched_getaffinity(0)
    os.sched_setaffinity(0, MACHINE_CORES)
    yield
    os.sched_setaffinity(0, own)


def pytest_collection_modifyitems(config, items):
    """Tests marked ``slow`` (whole files of them) run first, so that pytest-xdist's workers end
    together rather than one waiting on another's last long test. Tests marked ``cuda`` need a
    GPU that torch can see; everywhere else they skip."""
    import torch

    items.sort(key=lambda item: item.get_closest_marker("slow") is None)  # stable: files stay in order

    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA GPU (torch sees none)")
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)


def shared_scan(name: str) -> Path:
    """A real scan from ../shared/data, or a clean skip when that folder is absent."""
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"{path} is not available (../shared/data absent)")
    return path


def write_nifti(path: Path, data: np.ndarray, affine: np.ndarray | None = None, **header) -> Path:
    image = nib.Nifti1Image(data, np.eye(4) if affine is None else affine)
    for key, value in header.items():
        image.header[key] = value
    nib.save(image, str(path))
    return path


def body_phantom(shape=(24, 20, 16), seed=0) -> np.ndarray:
    """An int16 CT-like phantom in HU: air around an ellipsoid of soft tissue with a bright core."""
    rng = np.random.default_rng(seed)
    grids = np.meshgrid(*[np.linspace(-1, 1, n) for n in shape], indexing="ij")
    radius = sum((g / 0.8) ** 2 for g in grids)
    hu = np.where(radius < 1, 40.0, -1000.0)
    hu[radius < 0.2] = 700.0
    hu += rng.normal(0, 5, shape)
    return hu.astype(np.int16)


@pytest.fixture
def phantom_nifti(tmp_path) -> Path:
    affine = np.diag([1.5, 1.5, 3.0, 1.0])
    return write_nifti(tmp_path / "phantom.nii.gz", body_phantom(), affine)


VIEWABLE_SPLAT = ["--iterations", "200", "--eval-every", "100", "--checkpoint-every", "100", "-q"]


@pytest.fixture(scope="session")
def viewable_work(tmp_path_factory):
    """A finished 32³ work directory with a baked run (`splat`) and a scalar one (`splat-scalar`),
    for the tests of `cubecloud view` and `cubecloud share`: made once per pytest worker. Tests
    that damage it work on a copy."""
    from cli_helpers import invoke, tiny_work

    work = tiny_work(tmp_path_factory.mktemp("viewable") / "work", cunerf_iterations=200, views=16, max_points=3000,
                     novel_directions=0, splat=VIEWABLE_SPLAT)  # fmt: skip
    assert invoke("splat", work, *VIEWABLE_SPLAT, "--scalar", "--name", "scalar").exit_code == 0
    return work
