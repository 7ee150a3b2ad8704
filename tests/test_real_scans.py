"""The preprocess stage on every real scan: orientation, extent, range, placement in the scanner.

The placement check is independent of our reader and reorientation code: with nearest-neighbour
resampling each output voxel must hold the value of the input voxel whose centre lies within
half a voxel of the output voxel's scanner position, found through nibabel's affines alone.
"""

import json

import nibabel as nib
import numpy as np
import pytest
from conftest import shared_scan

from cubecloud_cli.preprocess import PreprocessSettings, preprocess_scan
from cubecloud_cli.sample_data import sample_ct_path
from cubecloud_cli.volume.readers import read_scan

SCANS = {
    "bundled": None,
    "abdomen": "ct_abdomen_pelvis_3mm_totalseg.nii.gz",
    "cardiac": "ct_cardiac_cta_1p5mm_totalseg.nii.gz",
    "chest": "ct_chest_5mm_pyradiomics_lung1.nii.gz",
    "mr": "mr_abdomen_3mm_totalseg.nii.gz",
    "dicom": "dicom/ct_upper_abdomen_totalseg",
}


def _scan_path(key):
    return sample_ct_path() if SCANS[key] is None else shared_scan(SCANS[key])


def _source_array_and_affine(path):
    """The input as stored (not reoriented): nibabel for NIfTI, our DICOM reader otherwise
    (that reader is checked against nibabel.nicom in test_readers)."""
    if path.is_dir():
        scan = read_scan(path)
        return scan.data, scan.affine
    image = nib.load(str(path))
    return np.asarray(image.dataobj, dtype=np.float32), image.affine


def assert_nearest_voxels_over_source(volume, affine, source, source_affine, intensity, samples=4000):
    """Each sampled output voxel equals the windowed input voxel nearest its scanner position."""
    low, high = intensity["low"], intensity["high"]
    rng = np.random.default_rng(0)
    voxels = rng.integers(0, volume.shape[0], size=(samples, 3))
    continuous = (np.linalg.inv(source_affine) @ affine @ np.c_[voxels, np.ones(len(voxels))].T)[:3].T
    nearest = np.floor(continuous + 0.5).astype(int)
    inside = np.all((continuous > -0.5) & (continuous < np.array(source.shape) - 0.5), axis=1)
    # Skip positions halfway between two input centres, where "nearest" is a tie.
    not_a_tie = np.all(np.abs(continuous - np.floor(continuous) - 0.5) > 1e-3, axis=1)
    check = inside & not_a_tie
    assert check.sum() > 200
    expected = np.clip((source[tuple(nearest[check].T)] - low) / (high - low), 0, 1)
    assert np.allclose(volume[tuple(voxels[check].T)], expected, atol=1e-6)
    # Padding is air; a centre exactly on the scan's outer face may go either way.
    outside = np.any((continuous < -0.5 - 1e-3) | (continuous > np.array(source.shape) - 0.5 + 1e-3), axis=1)
    assert np.all(volume[tuple(voxels[outside].T)] == 0)


@pytest.mark.parametrize("key", list(SCANS))
def test_nearest_output_voxels_sit_over_their_input_voxels(tmp_path, key):
    path = _scan_path(key)
    manifest = preprocess_scan(
        path, tmp_path, PreprocessSettings(size=40, window="full", interpolation="nearest", modality="ct")
    )
    output = nib.load(str(tmp_path / "preprocess" / "volume.nii.gz"))
    assert "".join(nib.aff2axcodes(output.affine)) == "RAS"
    volume = np.asarray(output.dataobj)
    assert np.array_equal(volume, np.load(tmp_path / "preprocess" / "volume.npy"))

    source, source_affine = _source_array_and_affine(path)
    assert_nearest_voxels_over_source(volume, output.affine, source, source_affine, manifest["intensity"])


@pytest.mark.parametrize("key", list(SCANS))
def test_default_settings_on_real_scans(tmp_path, key):
    path = _scan_path(key)
    manifest = preprocess_scan(path, tmp_path, PreprocessSettings(size=48))
    volume = np.load(tmp_path / "preprocess" / "volume.npy", mmap_mode="r")
    assert volume.shape == (48, 48, 48) and volume.dtype == np.float32
    assert float(volume.min()) >= 0 and float(volume.max()) <= 1 and float(volume.max()) > 0.5
    expected_modality = "mr" if key == "mr" else "ct"
    assert manifest["intensity"]["modality"] == expected_modality

    # --fit pad keeps the physical extent: the cube side equals the longest scan extent and
    # the scan's bounding box lies inside the cube in scanner coordinates.
    geometry = manifest["geometry"]
    source = manifest["source"]
    extent = np.array(source["shape"]) * np.array(source["spacing_mm"])
    assert np.allclose(np.array(geometry["voxel_size_mm"]) * 48, extent.max(), rtol=1e-6)
    assert np.allclose(geometry["mm_per_world_unit"], extent.max() / 2, rtol=1e-6)
    source_affine = np.array(source["affine"])
    corners = np.array(
        [
            [i, j, k, 1]
            for i in (-0.5, source["shape"][0] - 0.5)
            for j in (-0.5, source["shape"][1] - 0.5)
            for k in (-0.5, source["shape"][2] - 0.5)
        ]
    )
    world = (np.linalg.inv(np.array(geometry["world_to_scanner"])) @ (source_affine @ corners.T))[:3]
    assert np.all(np.abs(world) <= 1 + 1e-6)
    assert np.isclose(np.abs(world).max(), 1.0, atol=1e-6)  # the longest axis touches the faces


@pytest.mark.parametrize("key", ["cardiac", "chest"])
def test_lps_scans_match_nibabel_canonical(tmp_path, key):
    path = _scan_path(key)
    assert "".join(nib.aff2axcodes(nib.load(str(path)).affine)) == "LPS"
    canonical = nib.as_closest_canonical(nib.load(str(path)))
    manifest = preprocess_scan(path, tmp_path, PreprocessSettings(size=32, fit="stretch"))
    # With stretch, cube voxel (0,0,0)'s outer corner is the canonical array's (-0.5,-0.5,-0.5).
    corner = np.array(manifest["geometry"]["voxel_to_scanner"]) @ [-0.5, -0.5, -0.5, 1]
    assert np.allclose(corner, canonical.affine @ [-0.5, -0.5, -0.5, 1], atol=1e-6)
    assert json.loads((tmp_path / "preprocess" / "manifest.json").read_text())["source"]["axcodes"] == "LPS"


def test_oblique_scan_lies_over_the_original(tmp_path):
    from conftest import body_phantom, write_nifti

    angle = np.deg2rad(25)
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    affine = np.eye(4)
    affine[:3, :3] = rotation @ np.diag([-1.2, 0.9, 2.5])  # oblique, and x flipped
    affine[:3, 3] = (40, -60, 100)
    data = body_phantom((30, 26, 14), seed=3)
    path = write_nifti(tmp_path / "oblique.nii.gz", data, affine)
    manifest = preprocess_scan(
        path, tmp_path / "w", PreprocessSettings(size=36, window="full", interpolation="nearest")
    )
    output = nib.load(str(tmp_path / "w" / "preprocess" / "volume.nii.gz"))
    image = nib.load(str(path))
    assert_nearest_voxels_over_source(
        np.asarray(output.dataobj),
        output.affine,
        np.asarray(image.dataobj, np.float32),
        image.affine,
        manifest["intensity"],
    )


@pytest.mark.parametrize("key", ["chest", "mr"])
def test_cunerf_on_real_scans_lies_over_the_scan(tmp_path, key):
    """A short cunerf run on other real scans (lung window, MR percentiles): finite, in range,
    the reconstruction on the preprocessed volume's grid and better than a constant guess."""
    from cubecloud_cli.cunerf import CunerfSettings, train_cunerf

    work = tmp_path / "w"
    preprocess_scan(_scan_path(key), work, PreprocessSettings(size=32, window="lung" if key == "chest" else "abdomen"))
    settings = CunerfSettings(iterations=150, batch_size=2048, holdout=2, val_every=75)
    manifest = train_cunerf(work, settings)
    recon = nib.load(work / "cunerf" / "recon.nii.gz")
    volume = nib.load(work / "preprocess" / "volume.nii.gz")
    np.testing.assert_allclose(recon.affine, volume.affine, atol=1e-5)
    data = np.asarray(recon.dataobj)
    assert np.isfinite(data).all() and 0 <= data.min() and data.max() <= 1
    reference = np.asarray(volume.dataobj)
    constant_mse = float(((reference - reference.mean()) ** 2).mean())
    assert manifest["metrics"]["mse_3d"] < 0.2 * constant_mse
