import json
import subprocess
import sys

import nibabel as nib
import numpy as np
import pytest
from cli_helpers import assert_one_line_error, invoke
from conftest import body_phantom, write_nifti


def _load(work):
    return np.load(work / "preprocess" / "volume.npy")


def _no_partial_left(work):
    return not any(p.name.endswith(".partial") or ".old-" in p.name for p in work.iterdir()) if work.exists() else True


def test_bundled_scan_is_the_default(tmp_path):
    work = tmp_path / "w"
    result = invoke("preprocess", "-o", work, "--size", 32)
    assert result.exit_code == 0, result.output
    assert "bundled abdomen/pelvis CT" in result.stderr
    volume = _load(work)
    assert volume.shape == (32, 32, 32) and volume.dtype == np.float32
    assert 0 <= volume.min() and volume.max() <= 1 and volume.max() > 0.5
    manifest = json.loads((work / "preprocess" / "manifest.json").read_text())
    assert manifest["params"]["size"] == 32 and manifest["params"]["window"] == "abdomen"
    assert manifest["geometry"]["mm_per_world_unit"][0] == pytest.approx(366 / 2)
    assert set(manifest["files"]) == {"volume.npy", "volume.nii.gz", "preview.png"}


def test_preset_paper_and_overrides(phantom_nifti, tmp_path):
    work = tmp_path / "w"
    assert invoke("preprocess", phantom_nifti, "-o", work, "--preset", "paper", "--size", 16).exit_code == 0
    params = json.loads((work / "preprocess" / "manifest.json").read_text())["params"]
    assert params == params | {"size": 16, "fit": "stretch", "window": "full", "interpolation": "nearest"}


def test_console_script_runs_as_a_process(tmp_path, phantom_nifti):
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "cubecloud_cli",
            "preprocess",
            str(tmp_path / "missing.nii.gz"),
            "-o",
            str(tmp_path / "w"),
        ],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().count("\n") == 0 and "does not exist" in result.stderr


def test_nonexistent_path(tmp_path):
    assert_one_line_error(invoke("preprocess", tmp_path / "nope.nii.gz", "-o", tmp_path / "w"), "does not exist")
    assert not (tmp_path / "w").exists()


def test_folder_without_dicom(tmp_path):
    (tmp_path / "dir").mkdir()
    (tmp_path / "dir" / "a.txt").write_text("x")
    assert_one_line_error(invoke("preprocess", tmp_path / "dir", "-o", tmp_path / "w"), "no DICOM image files")


def test_truncated_nifti(tmp_path, phantom_nifti):
    blob = phantom_nifti.read_bytes()
    (tmp_path / "cut.nii.gz").write_bytes(blob[: len(blob) * 2 // 3])
    assert_one_line_error(invoke("preprocess", tmp_path / "cut.nii.gz", "-o", tmp_path / "w"), "truncated or corrupt")
    assert _no_partial_left(tmp_path / "w")


def test_preset_detail_sizes_the_cube_by_the_scan_and_size_still_wins(tmp_path):
    # 40 × 30 × 12 voxels of 0.8 × 0.8 × 2.5 mm: 32 × 24 × 30 mm, finest 0.8 mm -> 40 voxels -> 48.
    scan = write_nifti(tmp_path / "thin.nii.gz", body_phantom((40, 30, 12)), np.diag([0.8, 0.8, 2.5, 1.0]))
    detail = invoke("preprocess", scan, "-o", tmp_path / "a", "--preset", "detail")
    assert detail.exit_code == 0, detail.output
    assert "cube size 48³ from the scan's finest spacing (0.8 mm" in detail.stderr
    manifest = json.loads((tmp_path / "a" / "preprocess" / "manifest.json").read_text())
    assert manifest["params"]["size"] == "scan" and manifest["volume"]["shape"] == [48, 48, 48]
    assert manifest["geometry"]["voxel_size_mm"] == pytest.approx([32 / 48] * 3)  # finer than 0.8 mm: rounded up
    given = invoke("preprocess", scan, "-o", tmp_path / "b", "--preset", "detail", "--size", 16)
    assert given.exit_code == 0 and "cube size" not in given.stderr
    assert _load(tmp_path / "b").shape == (16, 16, 16)


@pytest.mark.parametrize("preset", ["fast", "detail"])
def test_2d_image(tmp_path, preset):
    path = write_nifti(tmp_path / "xray.nii.gz", np.zeros((64, 64), np.int16))
    assert_one_line_error(invoke("preprocess", path, "-o", tmp_path / "w", "--preset", preset), "2D image")


def test_4d_volume_needs_index(tmp_path):
    data = np.stack([body_phantom(), body_phantom(seed=1)], axis=-1)
    path = write_nifti(tmp_path / "4d.nii.gz", data)
    assert_one_line_error(invoke("preprocess", path, "-o", tmp_path / "w"), r"--volume-index 0\.\.1")
    assert invoke("preprocess", path, "-o", tmp_path / "w", "--volume-index", 1, "--size", 16).exit_code == 0


def test_nan_and_inf_voxels_are_replaced_with_a_warning(tmp_path):
    data = body_phantom().astype(np.float32)
    data[0, 0, :5] = np.nan
    data[5, 5, 5] = np.inf
    data[6, 6, 6] = -np.inf
    path = write_nifti(tmp_path / "nan.nii.gz", data)
    result = invoke("preprocess", path, "-o", tmp_path / "w", "--size", 16)
    assert result.exit_code == 0
    assert "warning: 7 voxels were NaN or Inf" in result.stderr
    assert np.all(np.isfinite(_load(tmp_path / "w")))


@pytest.mark.parametrize("window", ["full", "abdomen"])
def test_constant_volume(tmp_path, window):
    path = write_nifti(tmp_path / "c.nii.gz", np.full((8, 8, 8), 42, np.int16))
    result = invoke("preprocess", path, "-o", tmp_path / "w", "--size", 16, "--window", window)
    assert result.exit_code == 0 and "constant" in result.stderr
    volume = _load(tmp_path / "w")
    assert np.all(np.isfinite(volume)) and volume.max() <= 1


def test_a_thin_slab_is_named_with_the_size_that_keeps_it_and_an_all_air_cube_is_refused_by_cunerf(tmp_path):
    slab = np.full((600, 600, 5), -1000, np.int16)
    slab[100:500, 100:500, :] = 40  # soft tissue across the whole slab
    path = write_nifti(tmp_path / "slab.nii.gz", slab, np.diag([0.7, 0.7, 2.5, 1.0]))
    result = invoke("preprocess", path, "-o", tmp_path / "w", "--size", 32)
    assert result.exit_code == 0, result.output
    assert "12.5 mm) thick along its axis 2: 0.95 voxels of the 32³ cube" in result.stderr
    assert "--size 80 keeps 2 voxels across it" in result.stderr
    if not _load(tmp_path / "w").any():  # missed between the voxel centres: said, and refused before training
        assert "0 everywhere" in result.stderr
        assert_one_line_error(invoke("cunerf", tmp_path / "w"), r"volume.npy is 0 everywhere .* nothing to train")
    kept = invoke("preprocess", path, "-o", tmp_path / "k", "--size", 80)
    assert kept.exit_code == 0 and "thick along" not in kept.stderr and _load(tmp_path / "k").any()


def test_a_sheared_affine_is_one_line_that_says_what_is_done_with_the_shear(tmp_path):
    affine = np.diag([1.0, 1.0, 2.0, 1.0])
    affine[1, 2] = 2.0 * np.sin(np.radians(15))  # a 15° gantry tilt
    affine[2, 2] = 2.0 * np.cos(np.radians(15))
    path = write_nifti(tmp_path / "tilt.nii.gz", body_phantom(), affine)
    result = invoke("preprocess", path, "-o", tmp_path / "w", "--size", 16)
    assert result.exit_code == 0, result.output
    lines = [line for line in result.stderr.splitlines() if line.startswith("warning:") and "sheared" in line]
    assert len(lines) == 1 and "sheared by 15.0°" in lines[0] and "keep the shear" in lines[0]
    plain = invoke("preprocess", write_nifti(tmp_path / "s.nii.gz", body_phantom()), "-o", tmp_path / "s", "--size", 16)
    assert "voxel axes are sheared" not in plain.stderr


@pytest.mark.parametrize("spacing", ["0,1,1", "-1,1,1", "1,1,1e9", "1,1"])
def test_bad_spacing_option(tmp_path, phantom_nifti, spacing):
    result = invoke("preprocess", phantom_nifti, "-o", tmp_path / "w", f"--spacing={spacing}")
    assert_one_line_error(result, "--spacing")


def test_absurd_header_spacing(tmp_path):
    path = write_nifti(tmp_path / "a.nii.gz", body_phantom(), np.diag([1e-6, 1, 1, 1]))
    assert_one_line_error(invoke("preprocess", path, "-o", tmp_path / "w"), "outside .* --spacing")


def test_int16_slope_intercept_does_not_overflow(tmp_path):
    raw = np.linspace(-32768, 32767, 16**3).astype(np.int16).reshape(16, 16, 16)
    image = nib.Nifti1Image(raw, np.eye(4))
    image.header.set_slope_inter(4.0, -1024.0)  # 32767*4-1024 does not fit int16
    nib.save(image, str(tmp_path / "s.nii.gz"))
    result = invoke(
        "preprocess",
        tmp_path / "s.nii.gz",
        "-o",
        tmp_path / "w",
        "--size",
        16,
        "--window",
        "full",
        "--fit",
        "stretch",
        "--interpolation",
        "nearest",
    )
    assert result.exit_code == 0, result.output
    volume = _load(tmp_path / "w")
    # Wrapped values would break the monotone ramp along the last axis.
    assert volume[0, 0, 0] == 0 and volume[-1, -1, -1] == 1
    assert np.all(np.diff(volume.ravel()) >= 0)


def test_complete_stage_needs_force_and_survives_a_failed_rerun(tmp_path, phantom_nifti):
    work = tmp_path / "w"
    assert invoke("preprocess", phantom_nifti, "-o", work, "--size", 16).exit_code == 0
    before = (work / "preprocess" / "volume.npy").read_bytes()
    assert_one_line_error(invoke("preprocess", phantom_nifti, "-o", work, "--size", 16), "already complete.*--force")
    assert_one_line_error(invoke("preprocess", tmp_path / "missing.nii", "-o", work, "--force"), "does not exist")
    assert (work / "preprocess" / "volume.npy").read_bytes() == before
    assert invoke("preprocess", phantom_nifti, "-o", work, "--size", 24, "--force").exit_code == 0
    assert _load(work).shape == (24, 24, 24) and _no_partial_left(work)


@pytest.mark.parametrize(
    "args, pattern",
    [
        (["--size", "0"], "--size 0"),
        (["--percentiles", "99,1"], "--percentiles"),
        (["--hu-min", "-100"], "both --hu-min and --hu-max"),
        (["--modality", "mr", "--hu-min", "0", "--hu-max", "100"], "Hounsfield"),
    ],
)
def test_bad_option_values(tmp_path, phantom_nifti, args, pattern):
    assert_one_line_error(invoke("preprocess", phantom_nifti, "-o", tmp_path / "w", *args), pattern)


def test_mr_is_detected_and_normalised_by_percentiles(tmp_path):
    rng = np.random.default_rng(0)
    data = rng.gamma(2.0, 100.0, (12, 12, 12)).astype(np.float32)
    path = write_nifti(tmp_path / "mr.nii.gz", data)
    result = invoke("preprocess", path, "-o", tmp_path / "w", "--size", 16)
    assert result.exit_code == 0 and "modality: MR" in result.stderr
    intensity = json.loads((tmp_path / "w" / "preprocess" / "manifest.json").read_text())["intensity"]
    assert intensity["modality"] == "mr" and intensity["method"] == "percentiles 0.5-99.5"


def test_help_teaches_with_examples():
    result = invoke("preprocess", "--help")
    assert result.exit_code == 0
    for text in ("Examples", "--window", "--fit", "--spacing", "--preset"):
        assert text in result.output
    assert invoke("--version").output.startswith("cubecloud ")


@pytest.mark.parametrize("fmt", ["nii", "nrrd-gzip"])
def test_float32_scans_with_nan_in_read_only_buffers(tmp_path, fmt):
    data = body_phantom().astype(np.float32)
    data[1, 1, 1] = np.nan
    if fmt == "nii":
        path = write_nifti(tmp_path / "f.nii", data)  # uncompressed: nibabel may memory-map it
    else:
        import nrrd

        path = tmp_path / "f.nrrd"
        nrrd.write(
            str(path),
            data,
            {
                "encoding": "gzip",
                "space": "left-posterior-superior",
                "space directions": np.eye(3),
                "space origin": np.zeros(3),
            },
        )
    result = invoke("preprocess", path, "-o", tmp_path / "w", "--size", 16)
    assert result.exit_code == 0, result.output
    assert "1 voxels were NaN" in result.stderr
    assert np.all(np.isfinite(_load(tmp_path / "w")))


def test_torch_out_of_memory_is_one_line_not_a_traceback(tmp_path, phantom_nifti, monkeypatch):
    import cubecloud_cli.preprocess.stage as stage

    def fails(*args, **kwargs):
        raise RuntimeError(
            "[enforce fail at alloc_cpu.cpp:127] DefaultCPUAllocator: can't allocate memory: 136347648 bytes"
        )

    monkeypatch.setattr(stage, "preprocess_scan", fails)
    assert_one_line_error(invoke("preprocess", phantom_nifti, "-o", tmp_path / "w"), "out of memory")
