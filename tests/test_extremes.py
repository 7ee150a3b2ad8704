"""preprocess on legal but extreme scans: each completes with finite values in [0, 1]."""

import numpy as np
import pytest
from conftest import write_nifti

from cubecloud_cli.preprocess import PreprocessSettings, preprocess_scan


def _two_slices():
    return np.random.default_rng(0).integers(-1000, 1000, (20, 20, 2)).astype(np.int16), np.diag([1.0, 1.0, 3.0, 1.0])


def _anisotropic():
    return np.random.default_rng(1).integers(-1000, 1000, (40, 40, 4)).astype(np.int16), np.diag([0.3, 0.3, 10.0, 1.0])


def _one_bright_voxel():
    data = np.full((16, 16, 16), -1000, np.int16)
    data[8, 8, 8] = 1000
    return data, np.eye(4)


def _tiny_cube():
    return np.array([[[-1000, 0], [100, 200]], [[300, 400], [500, 1000]]], np.int16), np.eye(4) * 5 + np.diag(
        [0, 0, 0, -4]
    )


def _float16():
    return np.random.default_rng(2).uniform(-1000, 1000, (10, 12, 14)).astype(np.float16), np.eye(4)


@pytest.mark.parametrize("make", [_two_slices, _anisotropic, _one_bright_voxel, _tiny_cube, _float16])
@pytest.mark.parametrize("fit", ["pad", "stretch"])
def test_extreme_scans_give_finite_unit_volumes(tmp_path, make, fit):
    data, affine = make()
    if data.dtype == np.float16:
        path = tmp_path / "scan.npy"
        np.save(path, data)
        spacing = (1.0, 1.0, 1.0)
    else:
        path = write_nifti(tmp_path / "scan.nii.gz", data, affine)
        spacing = None
    manifest = preprocess_scan(
        path, tmp_path / "w", PreprocessSettings(size=64, fit=fit, window="full", spacing=spacing)
    )
    volume = np.load(tmp_path / "w" / "preprocess" / "volume.npy")
    assert volume.shape == (64, 64, 64)
    assert np.all(np.isfinite(volume)) and volume.min() >= 0 and volume.max() <= 1
    assert volume.max() > 0  # the anatomy (or the single bright voxel) survives resampling
    assert np.all(np.isfinite(np.array(manifest["geometry"]["world_to_scanner"])))
