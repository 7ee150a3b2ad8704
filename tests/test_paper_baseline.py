"""The paper's own 3DGS baseline (`export --cameras stack`): parallel slices seen from one pose."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, invoke

from cubecloud_cli.cameras import OrbitSpec, PinholeCameras, orbit_cameras, stack_cameras, stack_offsets
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.export import ExportSettings
from cubecloud_cli.render import GridField, ImageModel, render_views
from cubecloud_cli.splat.training_views import TrainingScene


@pytest.mark.parametrize("axis, looking", [("lr", (1, 0, 0)), ("ap", (0, -1, 0)), ("si", (0, 0, 1))])
def test_one_pose_for_every_slice(axis, looking):
    cameras = stack_cameras(OrbitSpec(views=7, axis=axis, resolution=16))
    assert np.allclose(cameras.rotations, cameras.rotations[0]) and np.allclose(
        cameras.translations, cameras.translations[0]
    )
    assert np.allclose(cameras.rotations[0][2], looking)  # the optical axis is the slice normal
    assert np.allclose(cameras.centres()[0], -4.0 * np.asarray(looking))
    offsets = stack_offsets(7)
    assert np.allclose(offsets, -offsets[::-1]) and np.allclose(np.diff(offsets), 2 / 7) and np.all(np.abs(offsets) < 1)


def test_each_view_shows_its_own_slice():
    # A volume that grows linearly from left to right: the sagittal slice at x shows (x + 1) / 2.
    size = 16
    ramp = ((2 * np.arange(size) + 1) / (2 * size)).astype(np.float32)
    volume = np.broadcast_to(ramp[:, None, None], (size,) * 3).copy()
    cameras = stack_cameras(OrbitSpec(views=6, axis="lr", resolution=24))
    offsets = stack_offsets(6)
    images = render_views(GridField(volume), cameras, ImageModel("slice", slice_offsets=tuple(offsets)))
    centre = images[:, 8:16, 8:16]
    # The camera at −x (the patient's left) looks along +x, so the plane at offset d is x = d.
    expected = (1.0 + offsets) / 2.0
    assert np.allclose(centre.min(axis=(1, 2)), expected, atol=1e-5) and np.allclose(
        centre.max(axis=(1, 2)), expected, atol=1e-5
    )
    through_origin = render_views(GridField(volume), cameras, ImageModel("slice"))
    assert np.allclose(through_origin[:, 8:16, 8:16], 0.5, atol=1e-5)


def test_bad_stack_settings():
    with pytest.raises(CubecloudError, match="needs --view slice"):
        ExportSettings(cameras="stack", view="dvr").validate()
    with pytest.raises(CubecloudError, match="--elevation"):
        ExportSettings(cameras="stack", view="slice", elevation=10.0).validate()
    with pytest.raises(CubecloudError, match="--cameras 'spiral'"):
        ExportSettings(cameras="spiral").validate()
    with pytest.raises(ValueError, match="slice offsets"):
        ImageModel("dvr", slice_offsets=(0.0,)).validate()
    with pytest.raises(ValueError, match="slice offsets"):
        ImageModel("slice", slice_offsets=(float("nan"),)).validate()


def test_one_camera_place_gets_the_orbit_extent():
    cameras = stack_cameras(OrbitSpec(views=4, axis="lr", radius=3.0, resolution=8))
    scene = TrainingScene(None, cameras, [str(i) for i in range(4)], None, [1, 2, 3], [0], None)
    assert scene.single_centre and scene.extent == pytest.approx(3.3)
    # Poses that went through a text file differ by rounding: still one place.
    jittered = PinholeCameras(
        cameras.rotations, cameras.translations + 1e-7 * np.arange(12).reshape(4, 3), 8, 8, cameras.focal
    )
    scene = TrainingScene(None, jittered, [str(i) for i in range(4)], None, [1, 2, 3], [0], None)
    assert scene.single_centre and scene.extent == pytest.approx(3.3, rel=1e-6)
    orbit = orbit_cameras(OrbitSpec(views=4, radius=3.0, resolution=8))
    assert not TrainingScene(None, orbit, [str(i) for i in range(4)], None, [1, 2, 3], [0], None).single_centre


def test_a_stack_slices_sagittally_unless_told_otherwise():
    from cubecloud_cli.cli.export import export_settings

    assert export_settings("paper", cameras="stack", axis=None, view="slice").axis == "lr"  # the paper preset orbits ap
    assert export_settings("paper", cameras="stack", axis="si", view="slice").axis == "si"
    assert export_settings("paper", cameras="orbit", axis=None).axis == "ap"


def test_run_accepts_exports_made_before_the_cameras_option():
    from cubecloud_cli.core.stage import parameter_differences as _differences

    assert _differences({"views": 60}, {"views": 60, "cameras": "orbit"}) == []
    assert _differences({"views": 60}, {"views": 60, "cameras": "stack"}) == ["cameras: 'orbit' -> 'stack'"]


def test_the_paper_baseline_end_to_end(tmp_path):
    work = tmp_path / "work"
    for args in (
        ["preprocess", "-o", work, "--size", "32"],
        ["cunerf", work, "--iterations", "40", "--batch-size", "1024", "--holdout", "2"],
        [
            "export",
            work,
            "--cameras",
            "stack",
            "--view",
            "slice",
            "--axis",
            "lr",
            "--resolution",
            "32",
            "--views",
            "16",
            "--cube",
            "8",
            "--points-per-cube",
            "32",
            "--max-points",
            "800",
        ],
        ["splat", work, "--init", "random", "--random-points", "2000", "--iterations", "30", "--eval-every", "15"],
        ["eval", work, "--turntable-frames", "4", "--turntable-resolution", "24"],
    ):
        result = invoke(*args, "-q")
        assert result.exit_code == 0, result.output
        # splat warns that the cameras share one place; eval, which trains nothing, does not repeat it.
        assert ("one place" in result.output) == (args[0] == "splat"), result.output
    manifest = json.loads((work / "export" / "manifest.json").read_text())
    assert manifest["params"]["cameras"] == "stack"
    assert np.allclose(manifest["image_model"]["slice_offsets"], stack_offsets(16))
    centres = np.asarray(manifest["cameras"]["centres"])
    assert np.allclose(centres, centres[0])
    reference = np.load(work / "export" / "reference.npy")
    assert np.abs(np.diff(reference, axis=0)).max() > 0.05  # one pose, different slices
    splat = json.loads((work / "eval" / "metrics.json").read_text())["results"]["splat"]
    assert np.isfinite(splat["psnr"]) and 0.0 < splat["psnr"] < 60.0
    assert list((work / "eval").rglob("*.gif"))  # a turntable across the slice normal


def test_a_stack_needs_slices_on_the_command_line(tmp_path):
    result = invoke("export", tmp_path / "none", "--cameras", "stack", "--view", "dvr")
    assert_one_line_error(result, r"needs --view slice")
