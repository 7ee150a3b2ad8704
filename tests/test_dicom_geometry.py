"""DICOM series as scanners write them: every output voxel holds the phantom's value at its own
scanner position, whatever the slice steps, gaps, overlaps or gantry tilt."""

import numpy as np
import pytest
from dicom_phantoms import (
    AIR_HU,
    MARK,
    MARK_HU,
    correlation_with_phantom,
    phantom_hu,
    write_enhanced,
    write_series,
)
from pydicom.uid import generate_uid

from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.volume.dicom import LPS_TO_RAS
from cubecloud_cli.volume.readers import read_scan


def voxel_near(scan, lps_point) -> tuple[float, np.ndarray]:
    """The value of the scan's voxel nearest a scanner (LPS) position, and that voxel's centre (LPS)."""
    ras = LPS_TO_RAS @ np.append(lps_point, 1.0)
    index = np.round(np.linalg.solve(scan.affine, ras)[:3]).astype(int)
    assert np.all(index >= 0) and np.all(index < scan.data.shape), "the position lies outside the volume"
    centre = (LPS_TO_RAS @ scan.affine @ np.append(index, 1.0))[:3]
    return float(scan.data[tuple(index)]), centre


EVEN = list(np.arange(0.0, 62.6, 2.5))
CASES = {
    "even": dict(table_positions=EVEN),
    "thin and thick slabs": dict(table_positions=[*np.arange(0.0, 24.0, 1.0), *np.arange(24.0, 63.0, 7.0)]),
    "a missing slice": dict(table_positions=[z for z in EVEN if z != 30.0]),
    "overlapping slabs": dict(table_positions=[*np.arange(0.0, 40.0, 2.5), *np.arange(33.75, 62.0, 2.5)]),
    "gantry tilt +20°": dict(table_positions=EVEN, tilt_deg=20.0),
    "gantry tilt −20°": dict(table_positions=EVEN, tilt_deg=-20.0),
}


@pytest.mark.parametrize("case", CASES)
def test_the_voxel_at_a_marked_scanner_position_holds_the_marked_value(case, tmp_path):
    scan = read_scan(write_series(tmp_path / "series", **CASES[case]))
    assert voxel_near(scan, MARK)[0] == pytest.approx(MARK_HU, abs=1.0)
    assert voxel_near(scan, [66.0, 45.0, 30.0])[0] == pytest.approx(AIR_HU, abs=1.0)
    # In the body the phantom is linear along the table, which interpolation reproduces: a voxel
    # holds the value at its own centre to the HU's rounding, wherever the slices were.
    for point in ([-20.0, 10.0, 5.0], [-40.0, -20.0, 30.0], [25.0, -15.0, 55.0]):
        value, centre = voxel_near(scan, point)
        assert value == pytest.approx(float(phantom_hu(centre)), abs=1.0)
    assert correlation_with_phantom(scan) > 0.999


def test_what_was_found_is_recorded_and_said_in_one_line(tmp_path):
    scan = read_scan(write_series(tmp_path / "series", [z for z in EVEN if z != 30.0], tilt_deg=20.0))
    found = scan.acquisition
    assert found["tilt_deg"] == pytest.approx(20.0, abs=0.01) and found["gantry_detector_tilt_deg"] == -20.0
    assert found["gaps_mm"] and found["resampled"] and found["slices"] == len(EVEN) - 1
    [notice] = [note for note in scan.notes if "resampled" in note]
    assert "gantry tilt 20.0°" in notice and "gap" in notice and "\n" not in notice


def test_an_even_series_is_read_as_it_is(tmp_path):
    scan = read_scan(write_series(tmp_path / "series", EVEN))
    assert scan.data.shape == (56, 48, len(EVEN)) and not scan.acquisition["resampled"]
    assert not [note for note in scan.notes if "resampled" in note]
    assert np.allclose(scan.spacing_mm, [3.0, 3.0, 2.5])


def assert_holds_the_phantom(scan):
    assert voxel_near(scan, MARK)[0] == pytest.approx(MARK_HU, abs=1.0)
    assert voxel_near(scan, [66.0, 45.0, 30.0])[0] == pytest.approx(AIR_HU, abs=1.0)
    for point in ([-20.0, 10.0, 5.0], [-40.0, -20.0, 30.0], [25.0, -15.0, 55.0]):
        value, centre = voxel_near(scan, point)
        assert value == pytest.approx(float(phantom_hu(centre)), abs=1.0)


@pytest.mark.parametrize("tilt", [0.0, 20.0])
def test_an_enhanced_multiframe_file_is_read_with_its_per_frame_geometry_and_rescale(tilt, tmp_path):
    path = write_enhanced(tmp_path / "enhanced.dcm", [z for z in EVEN if z != 30.0], tilt_deg=tilt)
    for source in (path, path.parent):  # the file itself, or its folder
        scan = read_scan(source)
        assert_holds_the_phantom(scan)
        assert scan.acquisition["enhanced_multiframe"] and scan.source_format.startswith("DICOM enhanced")
        assert scan.acquisition["tilt_deg"] == pytest.approx(tilt, abs=0.01)


def test_an_enhanced_file_with_several_stacks_is_refused_naming_them(tmp_path):
    path = write_enhanced(tmp_path / "enhanced.dcm", EVEN, extra_stack="coronal")
    with pytest.raises(CubecloudError, match=r"holds 2 stacks .*: axial \(26 frames\), coronal \(3 frames\)"):
        read_scan(path)


def test_a_folder_with_a_localizer_and_two_series_reads_the_largest_axial_one_and_says_so(tmp_path):
    folder = tmp_path / "study"
    main_uid, short_uid = generate_uid(), generate_uid()
    write_series(folder, EVEN, series_uid=main_uid, description="abdomen")
    write_series(folder, [20.0, 25.0, 30.0], series_uid=short_uid, description="short", rows=40, columns=40)
    write_localizer(folder)
    scan = read_scan(folder)
    assert scan.data.shape[2] == len(EVEN) and scan.acquisition["series_uid"] == main_uid
    [note] = [note for note in scan.notes if "stacks" in note]
    assert f"reading {main_uid} (26 images, axial, 'abdomen')" in note and "localizer" in note and "--series" in note

    short = read_scan(folder, series_uid=short_uid)
    assert short.data.shape[2] == 3 and short.acquisition["series_uid"] == short_uid
    with pytest.raises(CubecloudError, match=r"--series 1\.2\.3 is not in .* which holds .*abdomen"):
        read_scan(folder, series_uid="1.2.3")
    (tmp_path / "scan.nii.gz").touch()
    with pytest.raises(CubecloudError, match="--series picks a DICOM series"):
        read_scan(tmp_path / "scan.nii.gz", series_uid=main_uid)


def write_localizer(folder):
    """Two coronal scout images, marked LOCALIZER as scanners mark them."""
    from dicom_phantoms import CT_IMAGE_STORAGE, _base_dataset

    uid = generate_uid()
    for number, y in enumerate((0.0, 5.0)):
        ds = _base_dataset(CT_IMAGE_STORAGE, uid, generate_uid())
        ds.ImageType = ["ORIGINAL", "PRIMARY", "LOCALIZER"]
        ds.ImagePositionPatient = [-100.0, y, 100.0]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 0, -1]
        ds.PixelSpacing = [2.0, 2.0]
        ds.Rows = ds.Columns = 64
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.PixelData = np.zeros((64, 64), np.int16).tobytes()
        ds.save_as(folder / f"SCOUT{number}", enforce_file_format=True)


def test_the_command_line_takes_series_and_names_a_wrong_one_in_one_line(tmp_path):
    from cli_helpers import assert_one_line_error, invoke

    uid = generate_uid()
    folder = write_series(tmp_path / "series", EVEN, series_uid=uid)
    result = invoke("preprocess", folder, "-o", tmp_path / "work", "--size", "32", "--series", uid, "-q")
    assert result.exit_code == 0, result.output
    error = assert_one_line_error(invoke("preprocess", folder, "-o", tmp_path / "other", "--series", "9.9"),
                                  r"--series 9\.9 is not in .*, which holds")  # fmt: skip
    assert uid in error and not (tmp_path / "other").exists()
