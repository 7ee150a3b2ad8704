import warnings
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from conftest import body_phantom, shared_scan, write_nifti

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.volume.readers import read_scan


def test_nifti_round_trip(phantom_nifti):
    scan = read_scan(phantom_nifti)
    assert scan.data.dtype == np.float32 and scan.data.shape == (24, 20, 16)
    assert np.allclose(scan.spacing_mm, [1.5, 1.5, 3.0])
    assert np.array_equal(scan.data, body_phantom().astype(np.float32))


def test_nifti_scaling_is_applied_without_int16_overflow(tmp_path):
    raw = np.full((4, 4, 4), 32767, dtype=np.int16)
    raw[0] = -32768
    image = nib.Nifti1Image(raw, np.eye(4))
    image.header.set_slope_inter(2.0, -1024.0)
    nib.save(image, str(tmp_path / "scaled.nii.gz"))
    scan = read_scan(tmp_path / "scaled.nii.gz")
    assert scan.data.max() == pytest.approx(32767 * 2 - 1024)
    assert scan.data.min() == pytest.approx(-32768 * 2 - 1024)


def test_nifti_in_metres_is_converted_to_mm(tmp_path):
    image = nib.Nifti1Image(np.zeros((3, 3, 3), np.float32), np.diag([0.001, 0.001, 0.002, 1]))
    image.header.set_xyzt_units("meter")
    nib.save(image, str(tmp_path / "m.nii"))
    assert np.allclose(read_scan(tmp_path / "m.nii").spacing_mm, [1, 1, 2])


def test_4d_needs_a_volume_index(tmp_path):
    path = write_nifti(
        tmp_path / "t.nii.gz", np.stack([np.zeros((3, 3, 3)), np.ones((3, 3, 3))], -1).astype(np.float32)
    )
    with pytest.raises(CubecloudError, match="--volume-index 0..1"):
        read_scan(path)
    assert np.all(read_scan(path, volume_index=1).data == 1)
    with pytest.raises(CubecloudError, match="out of range: .* has volumes 0..1$"):
        read_scan(path, volume_index=5)


def test_trailing_singleton_axis_is_dropped(tmp_path):
    path = write_nifti(tmp_path / "s.nii.gz", np.zeros((3, 4, 5, 1), np.float32))
    assert read_scan(path).data.shape == (3, 4, 5)


@pytest.mark.parametrize("shape", [(8, 8), (8, 8, 1), (1, 8, 8)])
def test_2d_images_are_refused(tmp_path, shape):
    path = write_nifti(tmp_path / "flat.nii.gz", np.zeros(shape, np.float32))
    with pytest.raises(CubecloudError, match="2D image|3D volume"):
        read_scan(path)


def test_truncated_gzip_is_reported(tmp_path, phantom_nifti):
    blob = phantom_nifti.read_bytes()
    (tmp_path / "cut.nii.gz").write_bytes(blob[: len(blob) // 2])
    with pytest.raises(CubecloudError, match="truncated or corrupt"):
        read_scan(tmp_path / "cut.nii.gz")


def test_garbage_file_is_reported(tmp_path):
    (tmp_path / "junk.nii").write_bytes(b"not a nifti" * 10)
    with pytest.raises(CubecloudError, match="cannot read"):
        read_scan(tmp_path / "junk.nii")


@pytest.mark.parametrize(
    "spacing, message",
    [((0.0, 1.0, 1.0), "zero, negative"), ((-1.0, 1.0, 1.0), "zero, negative"), ((1.0, 1.0, 1e6), "outside")],
)
def test_bad_spacing_is_refused(tmp_path, spacing, message):
    path = tmp_path / "a.npy"
    np.save(path, np.zeros((3, 3, 3), np.float32))
    with pytest.raises(CubecloudError, match=message):
        read_scan(path, spacing_mm=spacing)


def test_header_with_absurd_spacing_is_refused_and_override_fixes_it(tmp_path):
    path = write_nifti(tmp_path / "huge.nii.gz", np.zeros((3, 3, 3), np.float32), np.diag([1.0, 1.0, 5000.0, 1.0]))
    with pytest.raises(CubecloudError, match="--spacing"):
        read_scan(path)
    assert np.allclose(read_scan(path, spacing_mm=(1, 1, 5)).spacing_mm, [1, 1, 5])


def test_singular_affine_is_refused(tmp_path):
    affine = np.array([[1, 1, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], float)
    path = write_nifti(tmp_path / "sing.nii.gz", np.zeros((3, 3, 3), np.float32), affine)
    with pytest.raises(CubecloudError):
        read_scan(path)


def test_npy_requires_spacing_and_is_ras(tmp_path):
    path = tmp_path / "v.npy"
    np.save(path, np.arange(27, dtype=np.int16).reshape(3, 3, 3))
    with pytest.raises(CubecloudError, match="--spacing"):
        read_scan(path)
    scan = read_scan(path, spacing_mm=(0.5, 0.5, 2.0))
    assert np.allclose(scan.affine, np.diag([0.5, 0.5, 2.0, 1.0]))


def test_npy_float16_is_read(tmp_path):
    np.save(tmp_path / "h.npy", np.ones((3, 3, 3), np.float16))
    assert read_scan(tmp_path / "h.npy", spacing_mm=(1, 1, 1)).data.dtype == np.float32


def test_missing_path_and_unknown_suffix(tmp_path):
    with pytest.raises(CubecloudError, match="does not exist"):
        read_scan(tmp_path / "nope.nii.gz")
    (tmp_path / "scan.mp4").write_bytes(b"x")
    with pytest.raises(CubecloudError, match="unknown file type"):
        read_scan(tmp_path / "scan.mp4")


def test_nrrd_lps_becomes_ras(tmp_path):
    import nrrd

    data = body_phantom((6, 5, 4))
    header = {
        "space": "left-posterior-superior",
        "space directions": np.diag([0.7, 0.7, 2.5]),
        "space origin": np.array([10.0, 20.0, 30.0]),
    }
    nrrd.write(str(tmp_path / "v.nrrd"), data, header)
    scan = read_scan(tmp_path / "v.nrrd")
    assert np.array_equal(scan.data, data.astype(np.float32))
    assert np.allclose(scan.affine[:3, :3], np.diag([-0.7, -0.7, 2.5]))
    assert np.allclose(scan.affine[:3, 3], [-10, -20, 30])


# --- DICOM -----------------------------------------------------------------------------------


def _write_dicom_series(folder: Path, volume_hu: np.ndarray, spacing=(0.8, 0.8, 2.0), shuffle=True):
    """A minimal CT series in LPS, uint16 stored with intercept -1024, no file extensions."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    folder.mkdir()
    columns, rows, count = volume_hu.shape
    order = np.random.default_rng(1).permutation(count) if shuffle else range(count)
    for file_number, k in enumerate(order):
        meta = FileMetaDataset()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.2"
        meta.MediaStorageSOPInstanceUID = generate_uid()
        ds = Dataset()
        ds.file_meta = meta
        ds.Modality = "CT"
        ds.SeriesInstanceUID = ""
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.ImagePositionPatient = [-100.0, -120.0, 50.0 + spacing[2] * k]
        ds.PixelSpacing = [spacing[1], spacing[0]]
        ds.Rows, ds.Columns = rows, columns
        ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, 16, 15
        ds.PixelRepresentation = 0
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.InstanceNumber = int(file_number) + 1  # deliberately unrelated to position
        ds.PixelData = (volume_hu[:, :, k].T + 1024).astype(np.uint16).tobytes()
        ds.save_as(folder / f"IMG{file_number:04d}", enforce_file_format=True)
    return folder


def test_dicom_series_sorted_by_position_and_rescaled(tmp_path):
    volume = body_phantom((12, 10, 6)).astype(np.float32)
    folder = _write_dicom_series(tmp_path / "series", volume)
    (folder / "notes.txt").write_text("not dicom")
    scan = read_scan(folder)
    assert scan.modality == "ct"
    assert np.array_equal(scan.data, volume)
    lps_to_ras = np.diag([-1, -1, 1, 1])
    expected = lps_to_ras @ np.array([[0.8, 0, 0, -100], [0, 0.8, 0, -120], [0, 0, 2, 50], [0, 0, 0, 1]])
    assert np.allclose(scan.affine, expected)


def test_single_dicom_file_reads_its_folder(tmp_path):
    folder = _write_dicom_series(tmp_path / "series", body_phantom((8, 8, 3)).astype(np.float32))
    scan = read_scan(folder / "IMG0000")
    assert scan.data.shape == (8, 8, 3)


def test_folder_without_dicom(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "readme.txt").write_text("hello")
    with pytest.raises(CubecloudError, match="no DICOM"):
        read_scan(tmp_path / "empty")


def test_many_slices_at_taken_positions_are_two_series_mixed_and_refused(tmp_path):
    folder = _write_dicom_series(tmp_path / "series", body_phantom((8, 8, 3)).astype(np.float32))
    import shutil

    shutil.copy(folder / "IMG0000", folder / "COPY")
    with pytest.raises(CubecloudError, match="1 slices at positions already taken: it mixes series or repeats files"):
        read_scan(folder)


def test_real_jpeg2000_series_matches_nibabel_nicom():
    folder = shared_scan("dicom/ct_upper_abdomen_totalseg")
    from nibabel.nicom import dicomwrappers

    scan = read_scan(folder)
    assert scan.data.shape == (512, 512, 20) and scan.modality == "ct"
    assert scan.data.min() == -1024 and scan.data.max() == 1839
    lps_to_ras = np.diag([-1, -1, 1, 1])
    for path in sorted(folder.iterdir())[::7]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            wrapper = dicomwrappers.wrapper_from_file(str(path))
            pixels = wrapper.get_data()  # rows × columns, rescaled, decoded independently of us
        position = np.asarray(wrapper.image_position, float)
        k = int(round(np.linalg.solve(scan.affine[:3, :3], lps_to_ras[:3, :3] @ position - scan.affine[:3, 3])[2]))
        assert np.array_equal(scan.data[:, :, k], pixels.T.astype(np.float32))
        # nicom's affine maps (row, column) to LPS; ours maps (column, row) to RAS.
        for row, column in [(0, 0), (100, 300), (511, 17)]:
            ours = scan.affine @ [column, row, k, 1]
            theirs = lps_to_ras @ wrapper.affine @ [row, column, 0, 1]
            assert np.allclose(ours, theirs, atol=1e-4)


def test_read_only_reader_output_is_made_writable(tmp_path, monkeypatch, phantom_nifti):
    import cubecloud_cli.volume.readers as readers

    original = readers.read_nifti

    def read_only(path, volume_index):
        scan = original(path, volume_index)
        scan.data.flags.writeable = False
        return scan

    monkeypatch.setattr(readers, "read_nifti", read_only)
    assert read_scan(phantom_nifti).data.flags.writeable


def test_undecodable_compressed_pixels_name_the_fix(tmp_path):
    from pydicom.encaps import encapsulate
    from pydicom.uid import JPEGLosslessSV1

    folder = _write_dicom_series(tmp_path / "series", body_phantom((8, 8, 2)).astype(np.float32), shuffle=False)
    import pydicom

    for path in folder.iterdir():
        ds = pydicom.dcmread(path)
        ds.file_meta.TransferSyntaxUID = JPEGLosslessSV1
        ds.PixelData = encapsulate([b"\xff\xd8 not really a jpeg \xff\xd9"])
        ds["PixelData"].VR = "OB"
        ds.save_as(path, enforce_file_format=True)
    with pytest.raises(CubecloudError, match=r"cannot decode the pixels .*1\.2\.840\.10008\.1\.2\.4\.70.*python-gdcm"):
        read_scan(folder)
