import nibabel as nib
import numpy as np
import pytest

from cubecloud_cli.volume.nifti import write_nifti


@pytest.mark.parametrize("name", ["v.nii", "v.nii.gz"])
def test_round_trip_through_nibabel(tmp_path, name):
    rng = np.random.default_rng(0)
    volume = rng.random((7, 5, 9), dtype=np.float32)
    affine = np.array([[0.0, -0.8, 0.1, 10], [0.9, 0.0, 0.0, -5], [0.0, 0.05, 2.0, 30], [0, 0, 0, 1]])
    fractions = []
    write_nifti(volume, affine, tmp_path / name, "test", on_progress=fractions.append, slab_bytes=7 * 5 * 4 * 2)
    image = nib.load(str(tmp_path / name))
    assert np.array_equal(np.asarray(image.dataobj), volume)
    assert np.allclose(image.affine, affine, atol=1e-5)
    assert int(image.header["sform_code"]) == 1 and int(image.header["qform_code"]) == 1
    assert image.header.get_xyzt_units()[0] == "mm"
    assert fractions == sorted(fractions) and fractions[-1] == 1.0 and len(fractions) == 5
