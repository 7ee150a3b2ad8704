import json
import shutil

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, invoke
from conftest import body_phantom, write_nifti

QUICK = ("--cunerf-iterations", 3, "--views", 4, "--resolution", 16, "--splat-iterations", 3)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """One `run` of the phantom at --size 16 with QUICK settings: the scan, the work folder and
    what the run printed. Tests take a copy of the folder (a moved folder stays current)."""
    root = tmp_path_factory.mktemp("finished")
    scan = write_nifti(root / "phantom.nii.gz", body_phantom(), np.diag([1.5, 1.5, 3.0, 1.0]))
    result = invoke("run", scan, "-o", root / "w", "--size", 16, *QUICK)
    assert result.exit_code == 0, result.output
    return scan, root / "w", result


def copy_of(finished, folder):
    scan, work, result = finished
    shutil.copytree(work, folder)
    return scan, folder, result


def test_run_skips_a_current_stage_and_refuses_changed_settings(tmp_path, finished):
    phantom_nifti, work, first = copy_of(finished, tmp_path / "w")
    assert "preprocess" in first.stderr and "total" in first.stderr
    stamp = (work / "preprocess" / "manifest.json").stat().st_mtime_ns

    again = invoke("run", phantom_nifti, "-o", work, "--size", 16, *QUICK)
    assert again.exit_code == 0 and "skipped" in again.stderr
    assert (work / "preprocess" / "manifest.json").stat().st_mtime_ns == stamp

    error = assert_one_line_error(invoke("run", phantom_nifti, "-o", work, "--size", 24, *QUICK), "other settings")
    assert "size: 16 -> 24" in error and "--force" in error
    assert invoke("run", phantom_nifti, "-o", work, "--size", 24, *QUICK, "--force").exit_code == 0


def test_a_work_directory_named_another_way_or_moved_is_still_current(tmp_path, finished, monkeypatch):
    phantom_nifti, _, _ = copy_of(finished, tmp_path / "w")
    monkeypatch.chdir(tmp_path)
    relative = invoke("run", phantom_nifti, "-o", "w", "--size", 16, *QUICK)
    assert relative.exit_code == 0 and relative.stderr.count("skipped") == 6, relative.output
    shutil.move(tmp_path / "w", tmp_path / "moved")
    moved = invoke("run", phantom_nifti, "-o", tmp_path / "moved", "--size", 16, *QUICK)
    assert moved.exit_code == 0 and moved.stderr.count("skipped") == 6, moved.output


def test_run_notices_a_different_scan(tmp_path, finished):
    _, work, _ = copy_of(finished, tmp_path / "w")
    other = write_nifti(tmp_path / "other.nii.gz", body_phantom(seed=7), np.diag([1.5, 1.5, 3.0, 1.0]))
    assert_one_line_error(invoke("run", other, "-o", work, "--size", 16, *QUICK), "input scan differs")


def test_run_on_the_bundled_scan(tmp_path):
    result = invoke("run", "-o", tmp_path / "w", "--size", 32, *QUICK)
    assert result.exit_code == 0 and "bundled" in result.stderr
    assert (tmp_path / "w" / "preprocess" / "preview.png").exists()
    assert "export:" in result.stderr and "4 views" in result.stderr
    assert len(list((tmp_path / "w" / "export" / "images").iterdir())) == 4


def test_run_trains_the_baseline_and_evaluates_both(tmp_path, finished):
    import json

    phantom_nifti, work, result = copy_of(finished, tmp_path / "w")
    baseline = json.loads((work / "splat-random" / "manifest.json").read_text())
    assert baseline["params"]["init"] == "random" and baseline["params"]["iterations"] == 3
    results = json.loads((work / "eval" / "metrics.json").read_text())["results"]
    assert {"splat", "splat-random", "cunerf", "cunerf-training-views"} <= set(results)
    assert (
        "| `splat` | Cube-Cloud 3DGS |" in result.stderr and "| `splat-random` | 3DGS, random init |" in result.stderr
    )
    # A run the user trained beside them joins the next eval, which is redone rather than refused.
    shutil.copytree(work / "splat-random", work / "splat-mine")
    again = invoke("run", phantom_nifti, "-o", work, "--size", 16, *QUICK)
    assert again.exit_code == 0 and again.stderr.count("skipped") == 5
    assert "splat-mine" in json.loads((work / "eval" / "metrics.json").read_text())["results"]


def test_run_redoes_export_when_its_settings_change(tmp_path, finished):
    phantom_nifti, work, _ = copy_of(finished, tmp_path / "w")
    error = assert_one_line_error(
        invoke("run", phantom_nifti, "-o", work, "--size", 16, *QUICK[:4], "--resolution", 20, *QUICK[6:]),
        "other settings",
    )
    assert "resolution: 16 -> 20" in error
    result = invoke(
        "run",
        phantom_nifti,
        "-o",
        work,
        "--size",
        16,
        *QUICK[:4],
        "--resolution",
        20,
        *QUICK[6:],
        "--view",
        "mip",
        "--force",
    )
    assert result.exit_code == 0, result.output
    assert np.load(work / "export" / "images.npy").shape == (4, 20, 20)


def test_run_trains_cunerf_and_resumes_an_interrupted_one(tmp_path, phantom_nifti, monkeypatch):
    from test_cli_cunerf import interrupt_at_step

    work = tmp_path / "w"
    interrupt_at_step(monkeypatch, 4)
    options = (
        "run",
        phantom_nifti,
        "-o",
        work,
        "--size",
        16,
        "--cunerf-iterations",
        6,
        "--views",
        3,
        "--resolution",
        16,
        "--splat-iterations",
        3,
    )
    interrupted = invoke(*options)
    assert interrupted.exit_code == 130 and (work / "preprocess").is_dir() and not (work / "cunerf").exists()
    assert "resumes by itself" in interrupted.stderr

    monkeypatch.undo()
    resumed = invoke(*options)
    assert resumed.exit_code == 0, resumed.output
    assert "resumed" in resumed.stderr and "skipped" in resumed.stderr and "3D PSNR" in resumed.stderr
    assert (work / "cunerf" / "manifest.json").is_file()
    again = invoke(*options)
    assert again.exit_code == 0 and again.stderr.count("skipped") == 6


def test_run_continues_an_interrupted_export(tmp_path, phantom_nifti, monkeypatch):
    import cubecloud_cli.export.renders as stage

    work = tmp_path / "w"
    original, calls = stage.render_view, []

    def interrupted_render(*args, **kwargs):
        calls.append(1)
        if len(calls) == 6:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(stage, "render_view", interrupted_render)
    options = ("run", phantom_nifti, "-o", work, "--size", 16, *QUICK)
    interrupted = invoke(*options)
    assert (
        interrupted.exit_code == 130 and "5 of 88 views are saved" in interrupted.stderr
    )  # 8 + 16 novel directions × 5
    calls.clear()
    resumed = invoke(*options)
    assert resumed.exit_code == 0, resumed.output
    assert len(calls) == 3 and "resumed from its saved work" in resumed.stderr


def test_a_tiny_detail_run_follows_the_scan_from_cube_to_views(tmp_path):
    # 32 voxels of 1 mm per axis: the detail preset keeps them, 32³, and renders 32² views.
    scan = write_nifti(tmp_path / "scan.nii.gz", body_phantom((32, 32, 32)), np.diag([1.0, 1.0, 1.0, 1.0]))
    work = tmp_path / "w"
    result = invoke("run", scan, "-o", work, "--preset", "detail", "--views", 8, "--splat-iterations", 5)
    assert result.exit_code == 0, result.output
    read = lambda stage: json.loads((work / stage / "manifest.json").read_text())  # noqa: E731
    assert read("preprocess")["volume"]["shape"] == [32, 32, 32]
    export = read("export")
    assert export["params"]["resolution"] == "volume"
    assert (export["cameras"]["width"], export["cameras"]["height"]) == (32, 32)
    assert np.load(work / "export" / "novel" / "reference.npy", mmap_mode="r").shape[1:] == (32, 32)
    assert read("cunerf")["params"]["grid_init"] == "volume"
    assert "novel PSNR" in (work / "eval" / "report.md").read_text()
    again = invoke("run", scan, "-o", work, "--preset", "detail", "--views", 8, "--splat-iterations", 5)
    assert again.exit_code == 0 and again.stderr.count("skipped (already complete)") == 6


def test_run_scalar_trains_one_scalar_scene_under_the_measured_set_and_scores_it_held_out(tmp_path, phantom_nifti):
    work = tmp_path / "w"
    quick = ("--cunerf-iterations", 3, "--views", 12, "--resolution", 16, "--splat-iterations", 3)
    result = invoke(
        "run", phantom_nifti, "-o", work, "--size", 16, *quick, "--scalar", "--hu-min", -1000, "--hu-max", 1000
    )
    assert result.exit_code == 0, result.output
    assert not (work / "splat-random").exists() and "splat-random" not in result.stderr
    export = json.loads((work / "export" / "manifest.json").read_text())["params"]
    splat = json.loads((work / "splat" / "manifest.json").read_text())["params"]
    assert (export["transfer_set"], export["transfer_stride"]) == (41, 6)
    assert splat["scalar"] is True and splat["max_gaussians"] == 50_000 and splat["iterations"] == 3
    assert (splat["filter_scale"], splat["rmse_share"]) == (0.01, 0.5)
    scored = json.loads((work / "eval" / "metrics.json").read_text())["results"]["splat"]["held_out_transfers"]
    assert {"bone", "vessels", "held-out-ramp-0"} <= set(scored)
    assert "never trained under" in result.stderr and "| splat | vessels |" in result.stderr
    assert all(np.isfinite(entry["psnr"]) for entry in scored.values())


def test_run_scalar_refuses_before_any_stage_what_it_cannot_run(tmp_path, phantom_nifti, finished):
    work = tmp_path / "w"
    assert_one_line_error(invoke("run", phantom_nifti, "-o", work, "--scalar", "--preset", "balanced"), "--preset fast")
    # Fewer views than the set's stride: export would refuse it only after preprocess and cunerf.
    assert_one_line_error(invoke("run", phantom_nifti, "-o", work, "--scalar", "--views", 4), "--transfer-stride 6")
    assert not work.exists()
    _, baked, _ = copy_of(finished, tmp_path / "baked")
    before = sorted(p.name for p in baked.iterdir())
    assert_one_line_error(invoke("run", phantom_nifti, "-o", baked, "--scalar"), "splat-random is the baseline")
    assert sorted(p.name for p in baked.iterdir()) == before
