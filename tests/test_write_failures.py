"""A write that fails mid-stage (here a file-size limit, as a full disk does) is one line naming the
file and the cause, exit 2; the stage's previous complete folder is untouched, no truncated
checkpoint is left for --resume to trust, and the next run does the right thing (issue 55)."""

import hashlib
import resource
import shutil
from contextlib import contextmanager

import pytest
import torch
from cli_helpers import assert_one_line_error, invoke

pytestmark = pytest.mark.slow

STAGES = {
    "preprocess": (["--size", "32", "--force"], "volume.npy"),
    "cunerf": (["--iterations", "200", "--batch-size", "1024", "--holdout", "2", "--force"], "checkpoint.pt"),
    "export": (
        [
            "--resolution",
            "32",
            "--views",
            "16",
            "--cube",
            "8",
            "--points-per-cube",
            "64",
            "--max-points",
            "3000",
            "--novel-directions",
            "0",
            "--force",
        ],
        ".npy",
    ),  # fmt: skip
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
