from __future__ import annotations

import os
import signal
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

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


def pytest_collection_modifyitems(config, items):
    """Tests marked ``cuda`` need a GPU that torch can see; everywhere else they skip."""
    import torch

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
