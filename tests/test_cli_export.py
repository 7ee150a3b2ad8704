"""`cubecloud export` end to end on the bundled CT at 32³: files, interop, refusals."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, invoke
from PIL import Image
from plyfile import PlyData

from cubecloud_cli.core.pictures import to_uint8
from cubecloud_cli.numerics.metrics import psnr
from cubecloud_cli.scene import read_point_cloud_ply

SMALL = ["--resolution", "32", "--views", "9", "--cube", "8", "--points-per-cube", "64", "--max-points", "1500"]
NAMES = [f"view_{i:03d}.png" for i in range(9)]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    work = tmp_path_factory.mktemp("export") / "work"
    for args in (
        ["preprocess", "-o", work, "--size", "32"],
        ["cunerf", work, "--iterations", "60", "--batch-size", "1024", "--holdout", "2"],
    ):
        result = invoke(*args, "-q")
        assert result.exit_code == 0, result.output
    return work


@pytest.fixture(scope="module")
def exported(trained):
    result = invoke("export", trained, *SMALL, "-q")
    assert result.exit_code == 0, result.output
    return trained / "export"


def _copy_upstream(trained, tmp_path):
    work = tmp_path / "work"
    for stage in ("preprocess", "cunerf"):
        shutil.copytree(trained / stage, work / stage)
    return work


def test_stage_writes_the_scene(exported):
    manifest = json.loads((exported / "manifest.json").read_text())
    for folder in ("images", "reference"):
        assert sorted(p.name for p in (exported / folder).iterdir()) == NAMES
        stack = np.load(exported / f"{folder}.npy")
        assert stack.shape == (9, 32, 32) and stack.dtype == np.float32
        assert stack.min() >= 0 and stack.max() <= 1 and stack.max() > 0.05
        png = np.asarray(Image.open(exported / folder / NAMES[3]))
        # RGB, as the reference 3DGS loader and gsplat's imread(...)[..., :3] expect: the float
        # render, rounded, in three equal channels.
        assert png.shape == (32, 32, 3)
        for channel in range(3):
            np.testing.assert_array_equal(png[..., channel], to_uint8(stack[3]))
    sparse = exported / "sparse" / "0"
    for name in ("cameras", "images", "points3D"):
        assert (sparse / f"{name}.bin").is_file() and (sparse / f"{name}.txt").is_file()
    assert (sparse / "test.txt").read_text().split() == ["view_000.png", "view_008.png"]
    assert (sparse / "points3D.ply").read_bytes() == (exported / "points3D.ply").read_bytes()
    split = json.loads((exported / "split.json").read_text())
    assert split["test"] == ["view_000.png", "view_008.png"] and len(split["train"]) == 7
    assert manifest["split"] == {"train": split["train"], "test": split["test"]}
    transforms = json.loads((exported / "transforms.json").read_text())
    assert [f["file_path"] for f in transforms["frames"]] == [f"images/{n}" for n in NAMES]
    assert transforms["ply_file_path"] == "sparse_pc.ply"
    from test_scene_interop import opensplat_fast_ply

    # nerfstudio-format readers (OpenSplat) get the cloud in the plain layout, our stages the extras.
    plain_xyz, plain_rgb = opensplat_fast_ply(exported / "sparse_pc.ply")
    ours_xyz, ours_rgb, extras = read_point_cloud_ply(exported / "points3D.ply")
    np.testing.assert_array_equal(plain_xyz, ours_xyz.astype(np.float32))
    np.testing.assert_array_equal(plain_rgb, ours_rgb)
    assert sorted(extras) == ["density", "intensity"]
    for name in ("contact_sheet.png", "contact_sheet_reference.png"):
        assert Image.open(exported / name).size[0] > 32
    assert set(manifest["timings_s"]) >= {"load", "bake", "render_images", "render_reference", "point_cloud", "write"}
    assert manifest["params"]["resolution"] == 32 and manifest["params"]["cunerf"] == "cunerf"
    assert set(manifest["inputs"]) == {"preprocess/volume.npy", "cunerf/model.pt", "cunerf/recon.nii.gz"}
    assert manifest["render_source"]["bake_size"] == 32
    assert manifest["image_model"]["kind"] == "dvr" and 0 <= manifest["image_model"]["transfer"]["low"] <= 1
    assert manifest["metrics"]["points"] == manifest["point_cloud"]["points"] == 1500
    assert manifest["metrics"]["cunerf_vs_reference_psnr"] > 15


def test_pycolmap_reads_the_exported_scene(exported):
    pycolmap = pytest.importorskip("pycolmap")
    manifest = json.loads((exported / "manifest.json").read_text())
    reconstruction = pycolmap.Reconstruction(str(exported / "sparse" / "0"))
    assert len(reconstruction.images) == 9 and len(reconstruction.points3D) == manifest["metrics"]["points"]
    camera = next(iter(reconstruction.cameras.values()))
    assert camera.model.name == "PINHOLE" and (camera.width, camera.height) == (32, 32)
    np.testing.assert_allclose(camera.params, [manifest["cameras"][k] for k in ("fx", "fy", "cx", "cy")])
    centres = {image.name: image.projection_center() for image in reconstruction.images.values()}
    np.testing.assert_allclose([centres[n] for n in NAMES], manifest["cameras"]["centres"], atol=1e-9)


def test_point_cloud_ply_has_what_3dgs_reads(exported):
    vertex = PlyData.read(str(exported / "points3D.ply"))["vertex"]
    types = {p.name: p.val_dtype for p in vertex.properties}
    assert [p.name for p in vertex.properties][:9] == ["x", "y", "z", "nx", "ny", "nz", "red", "green", "blue"]
    assert all(types[n] in ("f4", "float32") for n in ("x", "y", "z", "nx", "ny", "nz", "intensity", "density"))
    assert all(types[n] in ("u1", "uint8") for n in ("red", "green", "blue"))
    xyz = np.stack([vertex[a] for a in "xyz"], axis=1)
    assert np.abs(xyz).max() <= 1.0 and len(xyz) == 1500
    np.testing.assert_array_equal(vertex["red"], np.rint(vertex["intensity"] * 255).astype(np.uint8))
    assert (vertex["intensity"] > 0.02).all() and (vertex["density"] >= 0).all()


@pytest.mark.parametrize("view", ["slice", "mip"])
def test_other_image_models(trained, tmp_path, view):
    work = _copy_upstream(trained, tmp_path)
    result = invoke("export", work, *SMALL, "--view", view, "--axis", "ap", "-q")
    assert result.exit_code == 0, result.output
    manifest = json.loads((work / "export" / "manifest.json").read_text())
    assert manifest["image_model"]["kind"] == view and manifest["params"]["axis"] == "ap"
    assert np.load(work / "export" / "reference.npy").max() > 0.1


def test_rendering_from_the_field_agrees_with_the_baked_grid(trained, exported, tmp_path):
    work = _copy_upstream(trained, tmp_path)
    result = invoke("export", work, *SMALL, "--render-from", "field", "-q")
    assert result.exit_code == 0, result.output
    direct = np.load(work / "export" / "images.npy")
    baked = np.load(exported / "images.npy")
    assert psnr(baked, direct) > 30
    assert json.loads((work / "export" / "manifest.json").read_text())["render_source"]["bake_size"] is None


def test_refuses_to_overwrite_and_force_replaces(trained, exported, tmp_path):
    work = _copy_upstream(trained, tmp_path)
    shutil.copytree(exported, work / "export")
    assert_one_line_error(invoke("export", work, *SMALL), r"already complete: pass --force")
    result = invoke("export", work, *SMALL, "--views", "4", "--force", "-q")
    assert result.exit_code == 0, result.output
    assert len(list((work / "export" / "images").iterdir())) == 4


@pytest.mark.parametrize(
    "args, pattern",
    [
        (["--resolution", "0"], r"--resolution 0 must be a positive number of pixels"),
        (["--resolution", "16000", "--views", "60"], r"export needs about .* GiB .* lower --resolution"),
        (["--resolution", "20000"], r"beyond 16384"),
        (["--views", "1"], r"at least 2 views"),
        (["--radius", "1.2"], r"inside the volume"),
        (["--tf-low", "0.9", "--tf-high", "0.1"], r"low <= high"),
        (["--cube", "64"], r"larger than the 32³ volume"),
        (["--radius", "1e308"], r"beyond 10000 world units"),
        (["--resolution", "8", "--cube", "1", "--points-per-cube", "100000"], r"raise --cube"),
    ],
)
def test_bad_options_are_one_line_errors(trained, tmp_path, args, pattern):
    work = _copy_upstream(trained, tmp_path)
    assert_one_line_error(invoke("export", work, *SMALL[:2], *args), pattern)
    assert not (work / "export").exists() and not list(work.glob(".export*"))


def test_refuses_a_cunerf_trained_on_another_volume(trained, tmp_path):
    work = _copy_upstream(trained, tmp_path)
    assert invoke("preprocess", "-o", work, "--size", "32", "--window", "bone", "--force", "-q").exit_code == 0
    assert_one_line_error(
        invoke("export", work, *SMALL), r"trained on an earlier preprocess/ volume: rerun `cubecloud cunerf"
    )


def test_missing_or_incomplete_cunerf(trained, tmp_path):
    work = tmp_path / "work"
    shutil.copytree(trained / "preprocess", work / "preprocess")
    assert_one_line_error(invoke("export", work), r"cunerf does not exist: run `cubecloud cunerf")
    shutil.copytree(trained / "cunerf", work / "cunerf")
    (work / "cunerf" / "manifest.json").unlink()
    assert_one_line_error(invoke("export", work), r"cunerf is incomplete")
    assert_one_line_error(invoke("export", tmp_path / "nowhere"), r"preprocess does not exist")


def test_presets_and_overrides():
    from cubecloud_cli.cli.export import export_settings

    paper = export_settings("paper")
    assert (paper.view, paper.axis, paper.resolution, paper.views, paper.max_points) == ("slice", "ap", 512, 60, 0)
    fast = export_settings("fast", resolution=64, view=None, radius=5.0)
    assert (fast.view, fast.axis, fast.resolution, fast.radius) == ("dvr", "si", 64, 5.0)


def test_a_step_as_long_as_the_volume_is_refused():
    from cubecloud_cli.core.errors import CubecloudError
    from cubecloud_cli.export import ExportSettings

    ExportSettings(step=7.5, cube=4).check_for_volume(8)
    with pytest.raises(CubecloudError, match="spans the whole 8³ volume"):
        ExportSettings(step=8, cube=4).check_for_volume(8)


def test_ctrl_c_keeps_finished_views_and_the_same_command_continues(trained, exported, tmp_path, monkeypatch):
    import os
    import signal

    import cubecloud_cli.export.renders as stage

    work = _copy_upstream(trained, tmp_path)
    original, calls = stage.render_view, []

    def interrupted_render(*args, **kwargs):
        calls.append(1)
        if len(calls) == 12:  # a real Ctrl-C in the middle of the 3rd reference view
            os.kill(os.getpid(), signal.SIGINT)
        return original(*args, **kwargs)

    monkeypatch.setattr(stage, "render_view", interrupted_render)
    result = invoke("export", work, *SMALL)
    assert result.exit_code == 130
    assert "11 of 98 views are saved" in result.stderr and "run the same command to continue" in result.stderr
    assert not (work / "export").exists() and (work / ".export.partial" / "progress" / "bake.npy").is_file()

    calls.clear()
    resumed = invoke("export", work, *SMALL)
    assert resumed.exit_code == 0, resumed.output
    assert "11 of 98 views are already rendered" in resumed.stderr and len(calls) == 7  # training and reference views
    for name in ("images.npy", "reference.npy", "novel/reference.npy"):
        np.testing.assert_array_equal(np.load(work / "export" / name), np.load(exported / name))
    assert not (work / "export" / "progress").exists() and not (work / ".export.partial").exists()
    assert "progress" not in json.dumps(json.loads((work / "export" / "manifest.json").read_text())["files"])


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the printed one
def test_a_ctrl_c_that_python_could_only_print_still_stops_the_export(trained, tmp_path, monkeypatch):
    """Numba compiles through ctypes callbacks, where a KeyboardInterrupt is printed and dropped
    (what let a SLURM job's SIGTERM go unheeded): the export stops once the view is saved."""
    import ctypes
    import os
    import signal

    import cubecloud_cli.export.renders as stage

    work = _copy_upstream(trained, tmp_path)
    original, calls = stage.render_view, []
    lost_interrupt = ctypes.CFUNCTYPE(None)(lambda: os.kill(os.getpid(), signal.SIGINT))

    def render_then_lose_an_interrupt(*args, **kwargs):
        calls.append(1)
        if len(calls) == 12:
            lost_interrupt()
        return original(*args, **kwargs)

    monkeypatch.setattr(stage, "render_view", render_then_lose_an_interrupt)
    result = invoke("export", work, *SMALL)
    assert result.exit_code == 130 and len(calls) == 12, result.output
    assert "12 of 98 views are saved" in result.stderr and not (work / "export").exists()


def _interrupt_after(monkeypatch, renders: int) -> None:
    import cubecloud_cli.export.renders as stage

    original, calls = stage.render_view, []

    def interrupted_render(*args, **kwargs):
        calls.append(1)
        if len(calls) > renders:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(stage, "render_view", interrupted_render)


def test_a_changed_option_discards_saved_views(trained, tmp_path, monkeypatch):
    work = _copy_upstream(trained, tmp_path)
    _interrupt_after(monkeypatch, 4)
    assert invoke("export", work, *SMALL).exit_code == 130
    monkeypatch.undo()
    result = invoke("export", work, *SMALL, "--view", "mip")
    assert result.exit_code == 0 and "already rendered" not in result.stderr
    fresh = _copy_upstream(trained, tmp_path / "fresh")
    assert invoke("export", fresh, *SMALL, "--view", "mip", "-q").exit_code == 0
    for name in ("images.npy", "reference.npy"):
        np.testing.assert_array_equal(np.load(work / "export" / name), np.load(fresh / "export" / name))
    assert json.loads((work / "export" / "manifest.json").read_text())["resumed"] == {"views": 0, "bake": False}


def test_a_retrained_cunerf_discards_saved_views(trained, tmp_path, monkeypatch):
    work = _copy_upstream(trained, tmp_path)
    _interrupt_after(monkeypatch, 4)
    assert invoke("export", work, *SMALL).exit_code == 130
    monkeypatch.undo()
    assert (
        invoke(
            "cunerf", work, "--iterations", "30", "--batch-size", "1024", "--holdout", "2", "--force", "-q"
        ).exit_code
        == 0
    )
    result = invoke("export", work, *SMALL)
    assert result.exit_code == 0 and "already rendered" not in result.stderr
    assert json.loads((work / "export" / "manifest.json").read_text())["resumed"]["views"] == 0


def test_a_damaged_saved_view_is_rendered_again(trained, exported, tmp_path, monkeypatch):
    work = _copy_upstream(trained, tmp_path)
    _interrupt_after(monkeypatch, 5)
    assert invoke("export", work, *SMALL).exit_code == 130
    monkeypatch.undo()
    progress = work / ".export.partial" / "progress"
    (progress / "images_view_00002.npy").write_bytes(b"")  # what a power cut may leave
    (progress / "images_view_00003.npy").write_bytes(b"\x93NUMPY garbage")
    result = invoke("export", work, *SMALL)
    assert result.exit_code == 0, result.output
    np.testing.assert_array_equal(np.load(work / "export" / "images.npy"), np.load(exported / "images.npy"))


def test_a_failure_leaves_no_partial_without_saved_work(trained, tmp_path):
    work = _copy_upstream(trained, tmp_path)
    (work / "preprocess" / "volume.npy").write_bytes(b"x" * (work / "preprocess" / "volume.npy").stat().st_size)
    assert_one_line_error(
        invoke("export", work, *SMALL), r"volume.npy changed since its stage was written: run `cubecloud preprocess"
    )
    assert not (work / ".export.partial").exists() and not (work / "export").exists()


def test_leftovers_of_an_interrupted_cleanup_are_swept(exported, tmp_path):
    work = tmp_path / "work"
    shutil.copytree(exported.parent / "preprocess", work / "preprocess")
    shutil.copytree(exported.parent / "cunerf", work / "cunerf")
    shutil.copytree(exported, work / "export")
    (work / "export" / "progress").mkdir()
    (work / "export" / "progress" / "bake.npy").write_bytes(b"stale")
    (work / ".export.old-123").mkdir()
    assert_one_line_error(invoke("export", work, *SMALL), r"already complete")
    assert not (work / "export" / "progress").exists() and not (work / ".export.old-123").exists()
    assert invoke("export", work, *SMALL, "--force", "-q").exit_code == 0


def test_the_overlay_example_reads_the_scene(exported, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / "examples" / "scene_overlay.py"
    out = tmp_path / "overlay.png"
    result = subprocess.run(
        [sys.executable, str(script), str(exported), "--view", "2", "--out", str(out)],
        capture_output=True,
        text=True,
        check=True,
    )
    assert "9 PINHOLE views of 32x32" in result.stdout and "1500 drawn points land inside the image" in result.stdout
    assert Image.open(out).size == (32, 32)


def test_export_takes_the_cunerf_stages_own_bake_where_baking_would_give_the_same_grid(
    trained, exported, tmp_path, monkeypatch
):
    import cubecloud_cli.export.renders as export_stage

    assert "cunerf/recon.nii.gz" in json.loads((exported / "manifest.json").read_text())["inputs"]
    monkeypatch.setattr(export_stage, "saved_bake", lambda *args: None)
    baked = _copy_upstream(trained, tmp_path / "baked")
    result = invoke("export", baked, *SMALL, "-q")
    assert result.exit_code == 0, result.output
    assert "cunerf/recon.nii.gz" not in json.loads((baked / "export" / "manifest.json").read_text())["inputs"]
    for name in ("images.npy", "points3D.ply", "novel/reference.npy"):
        assert (exported / name).read_bytes() == (baked / "export" / name).read_bytes(), name
    monkeypatch.undo()
    # A reconstruction changed since cunerf wrote it (one byte, the size kept) is not taken:
    # export bakes the field again.
    changed = _copy_upstream(trained, tmp_path / "changed")
    recon = changed / "cunerf" / "recon.nii.gz"
    data = bytearray(recon.read_bytes())
    data[len(data) // 2] ^= 0xFF
    recon.write_bytes(bytes(data))
    result = invoke("export", changed, *SMALL, "-q")
    assert result.exit_code == 0, result.output
    assert "cunerf/recon.nii.gz" not in json.loads((changed / "export" / "manifest.json").read_text())["inputs"]
    assert (changed / "export" / "images.npy").read_bytes() == (exported / "images.npy").read_bytes()
    # Nor one that another torch wrote: its bits may differ from this torch's bake.
    other_torch = _copy_upstream(trained, tmp_path / "other-torch")
    manifest_path = other_torch / "cunerf" / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["runtime"]["torch"] = "0.0"
    manifest_path.write_text(json.dumps(manifest))
    result = invoke("export", other_torch, *SMALL, "-q")
    assert result.exit_code == 0, result.output
    assert "cunerf/recon.nii.gz" not in json.loads((other_torch / "export" / "manifest.json").read_text())["inputs"]


def test_saved_work_is_found_from_its_header_and_a_damaged_file_is_not(tmp_path):
    from cubecloud_cli.export.finished_views import ExportProgress

    progress = ExportProgress(tmp_path / ".export.partial", {"volume": "a"})
    progress.prepare()
    assert not progress.has("bake")
    progress.save("bake", np.ones((4, 4, 4), dtype=np.float32))
    assert progress.has("bake") and progress.load("bake").shape == (4, 4, 4)
    path = progress.directory / "bake.npy"
    whole = path.read_bytes()
    for cut in (40, len(whole) - 4):  # inside the header, inside the values
        path.write_bytes(whole[:cut])
        assert not progress.has("bake") and progress.load("bake") is None
