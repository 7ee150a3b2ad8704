import json
import subprocess
import sys

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, invoke

from cubecloud_cli.core.artifacts import StageWriter, require_stage, sha256_of_file, stage_dir_name
from cubecloud_cli.core.errors import CubecloudError


def _write_stage(work, value="a", force=False, name=None):
    with StageWriter(work, "preprocess", {"value": value, "ratio": np.float32(0.5)}, force=force, name=name) as writer:
        (writer.directory / "data.txt").write_text(value)
        with writer.phase("compute"):
            writer.metrics["psnr"] = float("inf")
    return writer


def test_manifest_records_everything(tmp_path):
    source = tmp_path / "input.bin"
    source.write_bytes(b"abc")
    with StageWriter(tmp_path / "w", "preprocess", {"size": 8}) as writer:
        writer.add_input(source, "scan")
        (writer.directory / "sub").mkdir()
        (writer.directory / "sub" / "out.bin").write_bytes(b"xyz")
    manifest = json.loads((tmp_path / "w" / "preprocess" / "manifest.json").read_text())
    assert manifest["stage"] == "preprocess" and manifest["params"] == {"size": 8}
    assert manifest["inputs"]["scan"] == sha256_of_file(source)
    assert manifest["files"]["sub/out.bin"]["bytes"] == 3
    assert "total" in manifest["timings_s"] and manifest["cubecloud_version"]


def test_nonfinite_metrics_stay_valid_json(tmp_path):
    _write_stage(tmp_path)
    manifest = json.loads((tmp_path / "preprocess" / "manifest.json").read_text())
    assert manifest["metrics"]["psnr"] == "inf" and manifest["params"]["ratio"] == 0.5


def test_failure_leaves_nothing_behind(tmp_path):
    with pytest.raises(RuntimeError):
        with StageWriter(tmp_path, "preprocess", {}) as writer:
            (writer.directory / "half.bin").write_bytes(b"x")
            raise RuntimeError("crash")
    assert list(tmp_path.iterdir()) == []


def test_keep_partial_keeps_checkpoints_for_resume(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with StageWriter(tmp_path, "cunerf", {}, keep_partial=True) as writer:
            (writer.directory / "checkpoint.pt").write_bytes(b"x")
            raise KeyboardInterrupt
    assert (tmp_path / ".cunerf.partial" / "checkpoint.pt").exists()
    assert not (tmp_path / "cunerf").exists()


def test_keep_partial_drops_a_partial_with_nothing_to_resume(tmp_path):
    work = tmp_path / "w"
    with pytest.raises(RuntimeError):
        with StageWriter(work, "cunerf", {}, keep_partial=True):
            raise RuntimeError("failed before the first checkpoint")
    assert not work.exists()


def test_complete_stage_is_kept_unless_forced(tmp_path):
    _write_stage(tmp_path, "first")
    with pytest.raises(CubecloudError, match="--force"):
        _write_stage(tmp_path, "second")
    assert (tmp_path / "preprocess" / "data.txt").read_text() == "first"
    _write_stage(tmp_path, "second", force=True)
    assert (tmp_path / "preprocess" / "data.txt").read_text() == "second"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["preprocess"]  # no leftovers


def test_failed_forced_rerun_keeps_the_old_stage(tmp_path):
    _write_stage(tmp_path, "first")
    with pytest.raises(RuntimeError):
        with StageWriter(tmp_path, "preprocess", {}, force=True):
            raise RuntimeError
    assert (tmp_path / "preprocess" / "data.txt").read_text() == "first"


def test_require_stage_names_the_fix(tmp_path):
    with pytest.raises(CubecloudError, match="does not exist: run `cubecloud preprocess SCAN"):
        require_stage(tmp_path, "preprocess")
    (tmp_path / "preprocess").mkdir()
    with pytest.raises(CubecloudError, match="incomplete"):
        require_stage(tmp_path, "preprocess")


def test_require_stage_detects_changed_files(tmp_path):
    _write_stage(tmp_path)
    assert require_stage(tmp_path, "preprocess")["params"]["value"] == "a"
    (tmp_path / "preprocess" / "data.txt").write_text("tampered!")
    with pytest.raises(CubecloudError, match="missing or changed"):
        require_stage(tmp_path, "preprocess")


def test_named_runs_sit_side_by_side(tmp_path):
    _write_stage(tmp_path, name="random")
    _write_stage(tmp_path)
    assert (tmp_path / "preprocess-random" / "manifest.json").exists()
    assert require_stage(tmp_path, "preprocess", "random")
    with pytest.raises(CubecloudError):
        stage_dir_name("splat", "../evil")


def test_work_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "work").write_text("x")
    with pytest.raises(CubecloudError, match="is a file"):
        _write_stage(tmp_path / "work")


@pytest.mark.parametrize("text, kind", [("[]", "an array"), ("null", "null"), ('"x"', "a string"), ("3", "a number")])
def test_a_manifest_that_is_json_but_not_an_object_is_damaged_with_the_command_that_remakes_it(tmp_path, text, kind):
    work = tmp_path / "work"
    (work / "preprocess").mkdir(parents=True)
    (work / "preprocess" / "manifest.json").write_text(text)
    with pytest.raises(CubecloudError, match=rf"damaged \(JSON {kind}, not an object\): run `cubecloud preprocess"):
        require_stage(work, "preprocess")


HOLD = """
import sys
from pathlib import Path
from cubecloud_cli.core.artifacts import StageWriter
writer = StageWriter(Path(sys.argv[1]), "preprocess", {}, force=True)
writer.__enter__()
print("held", flush=True)
sys.stdin.readline()  # then ends without leaving the stage: as if killed, the OS frees the lock
"""


def holding_the_stage(work):
    """A second process that has started to write WORK/preprocess and holds it until told to end."""
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(work)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                              text=True)  # fmt: skip
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_one_writer_per_stage_the_second_is_refused_with_the_first_ones_pid(tmp_path):
    work = tmp_path / "work"
    holder = holding_the_stage(work)
    try:
        with pytest.raises(
            CubecloudError, match=rf"preprocess is being written by another cubecloud command \(PID {holder.pid}\)"
        ):
            with StageWriter(work, "preprocess", {}, force=True):
                pass
        assert not (work / "preprocess").exists()  # the refused one wrote nothing
    finally:
        holder.communicate("\n", timeout=60)
    assert (work / ".preprocess.lock").exists()  # left by a holder that never let go, as kill -9 would
    with StageWriter(work, "preprocess", {}, force=True) as writer:  # the OS freed it: the next one writes
        (writer.directory / "a.txt").write_text("a")
    assert (work / "preprocess" / "manifest.json").is_file() and not (work / ".preprocess.lock").exists()
    with StageWriter(work, "cunerf", {}):  # another stage of the same work directory is not held up
        pass


def test_a_second_command_on_a_stage_being_written_exits_2_at_once(tmp_path):
    work = tmp_path / "work"
    holder = holding_the_stage(work)
    try:
        result = invoke("preprocess", "-o", work, "--size", "32", "--force")
        assert_one_line_error(result, rf"being written by another cubecloud command \(PID {holder.pid}\)")
    finally:
        holder.communicate("\n", timeout=60)
