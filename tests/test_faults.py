"""Faults a stage must survive (issue 55). A write that fails mid-stage (here a file-size limit, as a
full disk does) is one line naming the file and the cause, exit 2; the stage's previous complete
folder is untouched, no truncated checkpoint is left for --resume to trust, and the next run does
the right thing. A file changed in place since its stage wrote it (the same size, other bytes) is
refused by whatever reads it, by its sha256 against the manifest."""

import hashlib
import io
import json
import resource
import shutil
from contextlib import contextmanager

import numpy as np
import pytest
import torch
from cli_helpers import assert_one_line_error, invoke, tiny_export_options
from plyfile import PlyData

pytestmark = pytest.mark.slow

STAGES = {
    "preprocess": (["--size", "32", "--force"], "volume.npy"),
    "cunerf": (["--iterations", "200", "--batch-size", "1024", "--holdout", "2", "--force"], "checkpoint.pt"),
    "export": ([*tiny_export_options(16, 3000, 0), "--force"], ".npy"),
    "splat": (["--iterations", "200", "--checkpoint-every", "50", "--force"], "checkpoint.pt"),
    "eval": (["--force"], "turntable_splat.gif"),
}
LIMIT_BYTES = 6 * 1024  # every stage writes a larger file than this early on


@contextmanager
def file_size_limit(limit: int):
    """Writes past ``limit`` bytes fail with EFBIG (Python ignores SIGXFSZ), as a full disk fails them."""
    before = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, before[1]))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, before)


def folder_digest(folder) -> str:
    digest = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(folder)).encode() + path.read_bytes())
    return digest.hexdigest()


@pytest.mark.parametrize("stage", STAGES)
def test_a_failed_write_is_one_line_and_loses_nothing(viewable_work, tmp_path, stage):
    work = tmp_path / "work"
    shutil.copytree(viewable_work, work)
    options, file = STAGES[stage]
    target = ["-o", work] if stage == "preprocess" else [work]
    before = folder_digest(work / stage)
    with file_size_limit(LIMIT_BYTES):
        result = invoke(stage, *target, *options)
    # The cause as the writer gave it: EFBIG from Python's own writes, a short write from numpy's or torch's.
    assert_one_line_error(result, rf"cannot write .*{stage}\.partial/\S*{file} \(.+\): .*file-size limit")
    assert folder_digest(work / stage) == before  # the complete stage as it was
    partial = work / f".{stage}.partial"
    for checkpoint in partial.glob("*.pt") if partial.exists() else []:
        torch.load(checkpoint, weights_only=False)  # whatever is left is whole
    assert not list(partial.glob(".*.tmp")) if partial.exists() else True
    assert not (work / f".{stage}.lock").exists()


def test_after_a_failed_checkpoint_the_next_run_trains_to_the_end(viewable_work, tmp_path):
    work = tmp_path / "work"
    shutil.copytree(viewable_work, work)
    with file_size_limit(LIMIT_BYTES):
        assert invoke("splat", work, "--iterations", "60", "--checkpoint-every", "20", "--force").exit_code == 2
    result = invoke("splat", work, "--iterations", "60", "--checkpoint-every", "20", "--force", "-q")
    assert result.exit_code == 0, result.output
    assert (work / "splat" / "manifest.json").is_file() and not (work / ".splat.partial").exists()


def same_size_edit(path, edit) -> None:
    """Rewrite ``path`` with ``edit`` applied, keeping its size (a size check alone passes it)."""
    size = path.stat().st_size
    edit(path)
    assert path.stat().st_size == size


def halve_the_reference(path) -> None:
    np.save(path, np.full_like(np.load(path), 0.5))


def flip_the_last_byte(path) -> None:
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))


def move_one_point(path) -> None:
    ply = PlyData.read(io.BytesIO(path.read_bytes()))  # not a memory map of the file it then rewrites
    ply["vertex"]["x"][0] = 1e6
    ply.write(str(path))


@pytest.mark.parametrize(
    "relative, edit, command, fix",
    [
        ("export/reference.npy", halve_the_reference, ["eval"], "cubecloud export {work} --force"),
        ("export/points3D.ply", move_one_point, ["splat", "--name", "x", "--iterations", "2"],
         "cubecloud export {work} --force"),
        ("preprocess/volume.npy", halve_the_reference, ["cunerf", "--force"], "cubecloud preprocess SCAN -o {work} --force"),
        ("splat/point_cloud.ply", move_one_point, ["eval"], "cubecloud splat {work} --force"),
        ("cunerf/model.pt", flip_the_last_byte, ["eval"], "cubecloud cunerf {work} --force"),
    ],
    ids=["eval-reference", "splat-points", "cunerf-volume", "eval-gaussians", "eval-cunerf-model"],
)  # fmt: skip
def test_a_file_changed_in_place_is_refused_by_its_sha256(viewable_work, tmp_path, relative, edit, command, fix):
    work = tmp_path / "work"
    shutil.copytree(viewable_work, work)
    same_size_edit(work / relative, edit)
    result = invoke(command[0], work, *command[1:])
    assert_one_line_error(result, rf"{relative} changed since .* run `{fix.format(work=work)}`")


def test_a_resumed_splat_refuses_points_that_changed_under_it(viewable_work, tmp_path, monkeypatch):
    import cubecloud_cli.splat.trainer as training

    work = tmp_path / "work"
    shutil.copytree(viewable_work, work)
    original, calls = training.photometric_loss, []

    def stop_at_step_25(*args, **kwargs):
        calls.append(1)
        if len(calls) == 25:
            raise KeyboardInterrupt  # after the checkpoint at 20
        return original(*args, **kwargs)

    monkeypatch.setattr(training, "photometric_loss", stop_at_step_25)
    options = ["--name", "r", "--iterations", "40", "--checkpoint-every", "10"]
    assert invoke("splat", work, *options).exit_code == 130
    monkeypatch.undo()
    # A re-export with other points, recorded in its manifest as a real one would be.
    points = work / "export" / "points3D.ply"
    move_one_point(points)
    manifest = json.loads((work / "export" / "manifest.json").read_text())
    manifest["files"]["points3D.ply"]["sha256"] = hashlib.sha256(points.read_bytes()).hexdigest()
    (work / "export" / "manifest.json").write_text(json.dumps(manifest))
    assert_one_line_error(invoke("splat", work, *options, "--resume"), r"changed since the interrupted run started")
    assert invoke("splat", work, *options, "--force", "-q").exit_code == 0


def test_eval_notices_a_splat_run_that_finished_while_it_scored(viewable_work, tmp_path, monkeypatch):
    import cubecloud_cli.eval.stage as eval_stage

    work = tmp_path / "work"
    shutil.copytree(viewable_work, work, ignore=shutil.ignore_patterns("eval"))
    draw = eval_stage._draw_pictures

    def splat_force_meanwhile(*args, **kwargs):
        draw(*args, **kwargs)
        same_size_edit(work / "splat" / "point_cloud.ply", move_one_point)  # what `splat --force` commits

    monkeypatch.setattr(eval_stage, "_draw_pictures", splat_force_meanwhile)
    result = invoke("eval", work, "--turntable-frames", "0")
    assert_one_line_error(result, r"splat/point_cloud.ply was replaced while eval scored it.*cubecloud eval")
    assert not (work / "eval").exists()  # no scores of Gaussians that are gone
