"""`cubecloud cunerf` end to end on the bundled CT at 32³: outputs, API, resume, refusals."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal

import nibabel as nib
import numpy as np
import pytest
import torch
from cli_helpers import assert_one_line_error, invoke

from cubecloud_cli.cunerf import CunerfField

# Random features: these tests train the field (the fast preset's volume start trains nothing).
FAST = ["--iterations", "40", "--batch-size", "1024", "--val-every", "20", "--holdout", "2", "--grid-init", "random"]
# Bits repeat on the CPU; on CUDA the grid's backward adds with atomics, in no fixed order.
CPU = ["--device", "cpu"]


@pytest.fixture(scope="module")
def preprocessed(tmp_path_factory):
    work = tmp_path_factory.mktemp("cunerf") / "work"
    result = invoke(*["preprocess", "-o", str(work), "--size", "32", "-q"])
    assert result.exit_code == 0, result.output
    return work


@pytest.fixture(scope="module")
def trained(preprocessed):
    result = invoke(*["cunerf", str(preprocessed), *FAST, "-q"])
    assert result.exit_code == 0, result.output
    return preprocessed


def interrupt_at_step(monkeypatch, step: int) -> None:
    """Send a real SIGINT (Ctrl-C) in the middle of training step ``step``, inside the loss."""
    import cubecloud_cli.cunerf.training as training

    original_loss, calls = training.adaptive_mse, []

    def interrupted_loss(output, target):
        calls.append(1)
        if len(calls) == step:
            os.kill(os.getpid(), signal.SIGINT)
        return original_loss(output, target)

    monkeypatch.setattr(training, "adaptive_mse", interrupted_loss)


def _copy_preprocess(source, tmp_path):
    work = tmp_path / "work"
    shutil.copytree(source / "preprocess", work / "preprocess")
    return work


def test_stage_writes_model_recon_preview_log_and_manifest(trained):
    stage = trained / "cunerf"
    for name in ("model.pt", "recon.nii.gz", "preview.png", "log.csv", "manifest.json"):
        assert (stage / name).is_file(), name
    assert not (stage / "checkpoint.pt").exists()
    manifest = json.loads((stage / "manifest.json").read_text())
    metrics = manifest["metrics"]
    for key in (
        "psnr_3d",
        "ssim_3d",
        "psnr_body_3d",
        "val_psnr",
        "val_ssim",
        "seconds_per_1000_iterations",
        "peak_rss_mb",
    ):
        assert isinstance(metrics[key], float), key
    assert metrics["iterations"] == 40 and metrics["psnr_3d"] > 12
    assert manifest["params"]["model"] == "fast" and manifest["data"]["held_out_slices"]
    assert set(manifest["timings_s"]) >= {"load", "train", "reconstruct", "write", "total"}
    rows = (stage / "log.csv").read_text().splitlines()
    assert rows[0].startswith("iteration,seconds,loss") and len(rows) == 41


def test_recon_lies_exactly_over_the_preprocessed_volume(trained):
    recon = nib.load(trained / "cunerf" / "recon.nii.gz")
    volume = nib.load(trained / "preprocess" / "volume.nii.gz")
    assert recon.shape == volume.shape
    np.testing.assert_allclose(recon.affine, volume.affine, atol=1e-5)
    data = np.asarray(recon.dataobj)
    assert np.isfinite(data).all() and data.min() >= 0 and data.max() <= 1


def test_python_api_queries_renders_and_bakes(trained):
    field = CunerfField.load(trained, device="cpu")
    points = np.random.default_rng(0).uniform(-1.2, 1.2, (1000, 3))
    intensity, density = field.query(points, chunk=300)
    assert intensity.shape == density.shape == (1000,)
    assert (intensity >= 0).all() and (intensity <= 1).all() and (density >= 0).all()
    rendered = field.render_cubes(points[:50], chunk=7)
    np.testing.assert_array_equal(rendered, field.render_cubes(points[:50], chunk=50))
    baked = field.bake(16)
    assert baked.shape == (16, 16, 16) and (baked >= 0).all() and (baked <= 1).all()
    recon = np.asarray(nib.load(trained / "cunerf" / "recon.nii.gz").dataobj)
    np.testing.assert_allclose(field.bake(32), recon, atol=1e-6)
    with pytest.raises(ValueError):
        field.query(np.zeros((4, 2)))


def test_bake_affine_keeps_the_physical_cube(trained):
    field = CunerfField.load(trained, device="cpu")
    volume_affine = nib.load(trained / "preprocess" / "volume.nii.gz").affine
    fine = field.bake_affine(64)
    # Voxel i of the volume covers voxels 2i and 2i+1 at scale 2; its centre lies between them.
    for i in (0, 7, 31):
        centre = volume_affine @ np.array([i, i, i, 1.0])
        between = fine @ np.array([2 * i + 0.5] * 3 + [1.0])
        np.testing.assert_allclose(between, centre, atol=1e-6)


def test_super_resolution_mode_exports_at_a_finer_scale(preprocessed, tmp_path):
    work = _copy_preprocess(preprocessed, tmp_path)
    result = invoke(*["cunerf", str(work), *FAST, "--train-scale", "2", "--export-scale", "2", "--name", "sr", "-q"])
    assert result.exit_code == 0, result.output
    manifest = json.loads((work / "cunerf-sr" / "manifest.json").read_text())
    assert all(k % 2 == 1 for k in manifest["data"]["held_out_slices"])
    assert manifest["data"]["training_voxels"] < 32**3 / 8 + 1
    assert nib.load(work / "cunerf-sr" / "recon.nii.gz").shape == (64, 64, 64)


def test_a_volume_start_records_itself_and_beats_random_features_at_equal_iterations(trained, tmp_path):
    work = _copy_preprocess(trained, tmp_path)
    result = invoke(*["cunerf", str(work), *FAST[:-2], "--grid-init", "volume", "--name", "volume", "-q"])
    assert result.exit_code == 0, result.output
    started = json.loads((work / "cunerf-volume" / "manifest.json").read_text())
    random = json.loads((trained / "cunerf" / "manifest.json").read_text())
    assert started["params"]["grid_init"] == "volume" and random["params"]["grid_init"] == "random"
    assert started["metrics"]["psnr_3d"] > random["metrics"]["psnr_3d"] + 3.0
    assert started["timings_s"]["fit"] > 0 and 0 <= started["metrics"]["volume_fit_rms"] < 0.01


def test_the_fitted_start_alone_is_a_complete_stage_and_a_random_one_is_refused(preprocessed, tmp_path):
    work = _copy_preprocess(preprocessed, tmp_path)
    result = invoke(*["cunerf", str(work), "--iterations", "0", "--grid-init", "volume", "--holdout", "2", "-q"])
    assert result.exit_code == 0, result.output
    manifest = json.loads((work / "cunerf" / "manifest.json").read_text())
    assert manifest["metrics"]["iterations"] == 0 and manifest["metrics"]["train_seconds"] == 0.0
    # The training voxels come back to within float32 and the logit's clipping (~60 dB).
    assert manifest["metrics"]["psnr_3d"] > 35.0 and manifest["metrics"]["val_psnr"] > 20.0
    assert (work / "cunerf" / "log.csv").read_text().splitlines()[1].startswith("0,0,")
    refused = invoke(*["cunerf", str(work), "--iterations", "0", "--grid-init", "random", "--force"])
    assert refused.exit_code == 2 and "--grid-init volume" in refused.output
    assert (work / "cunerf" / "manifest.json").is_file()  # the refused run left the stage alone


def test_interrupted_run_resumes_to_the_same_model(preprocessed, tmp_path, monkeypatch):
    straight = _copy_preprocess(preprocessed, tmp_path / "a")
    assert invoke(*["cunerf", str(straight), *FAST, *CPU, "--checkpoint-every", "10", "-q"]).exit_code == 0

    # A real Ctrl-C arrives mid-step, after the step's random draws: here inside the loss.
    work = _copy_preprocess(preprocessed, tmp_path / "b")
    interrupt_at_step(monkeypatch, 25)
    result = invoke(*["cunerf", str(work), *FAST, *CPU, "--checkpoint-every", "10", "-q"])
    assert result.exit_code == 130 and "--resume" in result.output and "iteration 25 " in result.output
    monkeypatch.undo()
    assert (work / ".cunerf.partial" / "checkpoint.pt").is_file() and not (work / "cunerf").exists()

    refused = invoke(*["cunerf", str(work), *FAST, *CPU, "--checkpoint-every", "10", "-q"])
    assert_one_line_error(refused, "--resume")
    changed = invoke(*["cunerf", str(work), *FAST, *CPU, "--checkpoint-every", "10", "--lr", "0.01", "--resume", "-q"])
    assert_one_line_error(changed, "other settings")

    resumed = invoke(*["cunerf", str(work), *FAST, *CPU, "--checkpoint-every", "10", "--resume", "-q"])
    assert resumed.exit_code == 0, resumed.output
    a = torch.load(straight / "cunerf" / "model.pt", weights_only=True)["model"]
    b = torch.load(work / "cunerf" / "model.pt", weights_only=True)["model"]
    for key in a:
        assert torch.equal(a[key], b[key]), key

    def logged(work):  # everything but the wall-clock seconds
        rows = list(csv.DictReader(open(work / "cunerf" / "log.csv")))
        return [{k: v for k, v in row.items() if k != "seconds"} for row in rows]

    assert logged(work) == logged(straight)


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["--iterations", "0"], "--iterations"),
        (["--cube-radius", "0"], "--cube-radius"),
        (["--samples-per-axis", "1"], "--samples-per-axis"),
        (["--train-scale", "20"], "--train-scale"),
        (["--export-scale", "100"], "--export-scale"),
        (["--lr", "-1"], "--lr"),
        (["--threads", "0"], "--threads"),
        (["--grid-hidden", "-3"], "--grid-hidden"),
        (["--model", "cunerf", "--grid-init", "volume"], "--grid-init volume needs --model fast"),
        (["--grid-init", "volume", "--grid-hidden", "1"], "--grid-hidden of at least 2"),
        (["--batch-size", "1000000", "--importance", "512"], "GiB.*--batch-size"),
        (["--resume"], "no interrupted run"),
        (["--precision", "bf16"], "--precision bf16 is for --model cunerf"),
        (["--model", "cunerf", "--precision", "tf32", "--device", "cpu"], "needs a CUDA GPU.*--precision float32"),
    ],
)
def test_bad_options_give_one_line_errors(preprocessed, tmp_path, arguments, message):
    work = _copy_preprocess(preprocessed, tmp_path)
    result = invoke(*["cunerf", str(work), *FAST, *arguments])
    assert_one_line_error(result, message)
    assert sorted(p.name for p in work.iterdir()) == ["preprocess"]


def test_missing_or_incomplete_preprocess_is_named(tmp_path):
    assert_one_line_error(invoke(*["cunerf", str(tmp_path / "nowhere")]), "cubecloud preprocess")
    (tmp_path / "work" / "preprocess").mkdir(parents=True)
    assert_one_line_error(invoke(*["cunerf", str(tmp_path / "work")]), "incomplete")


def test_a_complete_stage_is_kept_without_force(trained):
    before = (trained / "cunerf" / "manifest.json").read_text()
    assert_one_line_error(invoke(*["cunerf", str(trained), *FAST]), "--force")
    assert (trained / "cunerf" / "manifest.json").read_text() == before


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a GPU")
def test_asking_for_cuda_without_a_gpu_is_refused(preprocessed, tmp_path):
    work = _copy_preprocess(preprocessed, tmp_path)
    assert_one_line_error(invoke(*["cunerf", str(work), "--device", "cuda"]), "--device cpu")


def test_corrupt_model_file_is_named(trained, tmp_path):
    broken = tmp_path / "model.pt"
    broken.write_bytes(b"not a model")
    with pytest.raises(Exception, match="not a readable cubecloud model"):
        CunerfField.from_file(broken, device="cpu")


@pytest.mark.parametrize("value", [40, 100])  # constant tissue; a cube of 0 is refused (test_cli_preprocess)
def test_a_constant_volume_trains_to_finite_outputs(tmp_path, value):
    from conftest import write_nifti

    scan = write_nifti(tmp_path / "flat.nii.gz", np.full((12, 12, 12), value, np.int16), np.diag([2.0, 2.0, 2.0, 1.0]))
    work = tmp_path / "work"
    assert invoke("preprocess", scan, "-o", work, "--size", 16, "--modality", "ct", "-q").exit_code == 0
    result = invoke("cunerf", work, *FAST)
    assert result.exit_code == 0, result.output
    assert "3D PSNR" in result.stderr
    recon = np.asarray(nib.load(work / "cunerf" / "recon.nii.gz").dataobj)
    assert np.isfinite(recon).all() and recon.min() >= 0 and recon.max() <= 1
    json.loads((work / "cunerf" / "manifest.json").read_text())


def test_float16_points_are_accepted(trained):
    field = CunerfField.load(trained, device="cpu")
    points = np.random.default_rng(1).uniform(-1, 1, (64, 3))
    single, _ = field.query(points)
    half, _ = field.query(points.astype(np.float16))
    np.testing.assert_allclose(half, single, atol=5e-3)


def test_resume_is_refused_when_the_volume_changed(preprocessed, tmp_path, monkeypatch):
    work = _copy_preprocess(preprocessed, tmp_path)
    interrupt_at_step(monkeypatch, 5)
    assert invoke("cunerf", work, *FAST, "--checkpoint-every", "10", "-q").exit_code == 130
    monkeypatch.undo()
    assert invoke("preprocess", "-o", work, "--size", 32, "--window", "bone", "--force", "-q").exit_code == 0
    assert_one_line_error(invoke("cunerf", work, *FAST, "--resume"), "preprocess/ changed")


def test_help_shows_the_preset_values():
    # Square brackets would be eaten as rich markup; the hints use parentheses.
    def words(command: str) -> str:  # rich wraps and boxes the text
        return " ".join(re.sub("[│╭╮╰╯─]", " ", invoke(command, "--help").output).split())

    help_text = words("cunerf")
    from cubecloud_cli.presets import CUNERF_PRESETS, PRESETS

    fast = CUNERF_PRESETS["fast"]["fast"]["iterations"]
    assert f"fast {fast}, balanced {CUNERF_PRESETS['balanced']['fast']['iterations']}" in help_text
    assert "isotropic volume rendering" in help_text
    assert f"balanced {PRESETS['preprocess']['balanced']['size']}," in words("preprocess")
    assert f"balanced {PRESETS['splat']['balanced']['max_gaussians']}," in words("splat")
    export_help = words("export")
    assert "fast dvr, balanced dvr, detail dvr, paper slice" in export_help and "preset_note" not in export_help
    assert "detail scan" in words("preprocess") and "detail volume" in export_help


def test_a_second_ctrl_c_before_any_checkpoint_leaves_nothing_to_resume(preprocessed, tmp_path, monkeypatch):
    import cubecloud_cli.cunerf.training as training

    work = _copy_preprocess(preprocessed, tmp_path)
    original_loss, calls = training.adaptive_mse, []

    def twice_interrupted_loss(output, target):
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)  # the second one raises at once
        return original_loss(output, target)

    monkeypatch.setattr(training, "adaptive_mse", twice_interrupted_loss)
    result = invoke("cunerf", work, *FAST, "--checkpoint-every", "10", "-q")
    assert result.exit_code == 130 and "before the first checkpoint" in result.output
    assert sorted(p.name for p in work.iterdir()) == ["preprocess"]


def test_an_interrupt_while_committing_resumes_without_retraining(preprocessed, tmp_path, monkeypatch):
    from cubecloud_cli.core.artifacts import StageWriter
    from cubecloud_cli.cunerf.training import Trainer

    work = _copy_preprocess(preprocessed, tmp_path)
    original_list = StageWriter._list_files

    def interrupted_listing(self):
        raise KeyboardInterrupt

    monkeypatch.setattr(StageWriter, "_list_files", interrupted_listing)
    result = invoke("cunerf", work, *FAST, "-q")
    assert result.exit_code == 130 and "iteration 40 is saved" in result.output

    monkeypatch.setattr(StageWriter, "_list_files", original_list)
    monkeypatch.setattr(Trainer, "step", lambda self: pytest.fail("training ran again"))
    resumed = invoke("cunerf", work, *FAST, "--resume", "-q")
    assert resumed.exit_code == 0, resumed.output
    manifest = json.loads((work / "cunerf" / "manifest.json").read_text())
    assert "checkpoint.pt" not in manifest["files"] and not (work / "cunerf" / "checkpoint.pt").exists()
    assert manifest["metrics"]["iterations"] == 40


def test_the_api_example_runs(trained, tmp_path):
    import subprocess
    import sys

    from conftest import REPO

    out = tmp_path / "x1_5.nii.gz"
    result = subprocess.run(
        [
            sys.executable,
            str(REPO / "examples" / "cunerf_field.py"),
            str(trained),
            "--scale",
            "1.5",
            "--out",
            str(out),
            "--device",
            "cpu",
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert "intensity" in result.stdout and nib.load(out).shape == (48, 48, 48)
