"""Invoke the CLI in-process and check the bad-input contract: exit 2, one line, no traceback."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

from typer.testing import CliRunner

from cubecloud_cli.cli import app

runner = CliRunner()


def invoke(*args: str):
    return runner.invoke(app, [str(a) for a in args])


def assert_one_line_error(result, pattern: str) -> str:
    assert result.exit_code == 2, (result.exit_code, result.output, result.exception)
    assert "Traceback" not in result.output
    errors = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, result.stderr
    assert re.search(pattern, errors[0]), errors[0]
    return errors[0]


def tiny_export_options(views: int, max_points: int, novel_directions: int) -> list:
    """The export options of a 32³ test scene: 32² views, 8-voxel cubes of 64 points."""
    return ["--resolution", "32", "--views", views, "--cube", "8", "--points-per-cube", "64",
            "--max-points", max_points, "--novel-directions", novel_directions]  # fmt: skip


def tiny_work(work, *, cunerf_iterations: int, views: int, max_points: int, novel_directions: int,
              splat: list[str] | None, baseline: bool = False, export: tuple[str, ...] = ()):  # fmt: skip
    """A finished 32³ work directory made through the CLI: preprocess, cunerf, export (with the
    options ``export`` adds), splat unless ``splat`` is None (and the random-init baseline), each
    asserted to succeed."""
    commands = [
        ["preprocess", "-o", work, "--size", "32"],
        ["cunerf", work, "--iterations", cunerf_iterations, "--batch-size", "1024", "--holdout", "2"],
        ["export", work, *tiny_export_options(views, max_points, novel_directions), *export],
    ]
    if splat is not None:
        commands.append(["splat", work, *splat])
    if baseline and splat is not None:
        commands.append(["splat", work, *splat, "--init", "random", "--random-points", "500", "--name", "random"])
    for args in commands:
        result = invoke(*args, "-q")
        assert result.exit_code == 0, result.output
    return work


def record_as_written(stage_dir, relative: str) -> None:
    """Record a file changed by a test in its stage's manifest, as if the stage had written it so
    (a test of what a stage does with such a file, past the sha256 check that would refuse it)."""
    path = Path(stage_dir) / relative
    manifest_path = Path(stage_dir) / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["files"][relative] = {
        "bytes": path.stat().st_size,
        "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
    }
    manifest_path.write_text(json.dumps(manifest))
