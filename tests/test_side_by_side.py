"""The two splat runs of `cubecloud run` trained side by side, each in a process of its own."""

from __future__ import annotations

import multiprocessing.spawn
import shutil
import sys
import types

import numba
import pytest
from cli_helpers import invoke

from cubecloud_cli.cli.options import build_settings
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.runtime import Runtime
from cubecloud_cli.cunerf import CunerfSettings
from cubecloud_cli.eval import EvalSettings
from cubecloud_cli.export import ExportSettings
from cubecloud_cli.pipeline import side_by_side
from cubecloud_cli.pipeline.runner import run_stages
from cubecloud_cli.pipeline.side_by_side import available_cores, without_main_module
from cubecloud_cli.pipeline.table import stage_table
from cubecloud_cli.preprocess import PreprocessSettings
from cubecloud_cli.splat import on_cpu
from cubecloud_cli.splat import stage as splat_stage
from cubecloud_cli.splat.on_cpu import threads_each
from cubecloud_cli.splat.settings import SplatSettings
from cubecloud_cli.splat.stage import train_splat

ITERATIONS = 60
# The runs share the machine's cores, as in `run`; slow tests run first (pytest-xdist's workers end together).
pytestmark = [pytest.mark.usefixtures("every_core"), pytest.mark.slow]


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A 32³ work directory up to its exported scene."""
    work = tmp_path_factory.mktemp("side-by-side") / "work"
    commands = [
        ["preprocess", "-o", work, "--size", "32"],
        ["cunerf", work, "--iterations", "40", "--batch-size", "1024"],
        ["export", work, "--resolution", "32", "--views", "8", "--cube", "8", "--points-per-cube", "64",
         "--max-points", "800", "--novel-directions", "0"],
    ]  # fmt: skip
    for args in commands:
        result = invoke(*args, "-q")
        assert result.exit_code == 0, result.output
    return work


@pytest.fixture
def work(exported, tmp_path):
    copy = tmp_path / "work"
    shutil.copytree(exported, copy)
    return copy


def splat_settings() -> SplatSettings:
    return build_settings(SplatSettings, "fast", {"iterations": ITERATIONS, "eval_every": 30})


def splat_stages(work, monkeypatch):
    """The stage table's two splat runs, marked to train side by side (short as they are)."""
    monkeypatch.setattr(on_cpu, "SIDE_BY_SIDE_MIN_ITERATIONS", 1)
    stages = stage_table(
        work / "scan.nii.gz",
        work,
        PreprocessSettings(),
        CunerfSettings(),
        ExportSettings(),
        splat_settings(),
        EvalSettings(),
        Runtime(device="cpu"),
    )
    runs = [stage for stage in stages if stage.folder.startswith("splat")]
    assert sorted(side_by_side.side_by_side_runs(runs)) == ["splat", "splat-random"]
    return runs


def test_runs_train_side_by_side_only_where_it_pays():
    long, short = SplatSettings(iterations=1500), SplatSettings(iterations=100)
    cpu = Runtime(device="cpu")
    assert threads_each(cpu, long, runs=2, cores=2) == 1
    assert threads_each(cpu, long, runs=2, cores=16) == 8
    assert threads_each(cpu, short, runs=2, cores=2) is None  # a process's start costs more
    assert threads_each(Runtime(device="cpu", threads=2), long, runs=2, cores=2) is None  # the user chose
    assert threads_each(cpu, long, runs=1, cores=2) is None
    assert threads_each(cpu, long, runs=2, cores=1) is None


def test_side_by_side_runs_repeat_bit_for_bit_alone_on_their_share_of_the_cores(work, monkeypatch):
    outcomes = run_stages(splat_stages(work, monkeypatch), work)
    assert [(o.stage, o.status) for o in outcomes] == [("splat", "ran"), ("splat-random", "ran")]
    settings = splat_settings()
    # Each run's share of the cores: 1 on a 2-core CI host, 8 on a 16-core one.
    share = Runtime(device="cpu", threads=threads_each(Runtime(device="cpu"), settings, 2, available_cores()))
    train_splat(work, settings, runtime=share, name="alone")
    train_splat(
        work, SplatSettings(**{**settings.as_dict(), "init": "random"}), runtime=share, name="alone-random"
    )  # fmt: skip
    for together, alone in (("splat", "splat-alone"), ("splat-random", "splat-alone-random")):
        assert (work / together / "point_cloud.ply").read_bytes() == (work / alone / "point_cloud.ply").read_bytes()


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="one core: the kernels cannot widen")
def test_widening_the_kernels_changes_no_bit(work, monkeypatch):
    """The run left alone takes every core for its kernels, and torch keeps one thread."""
    settings = splat_settings()
    train_splat(work, settings, runtime=Runtime(device="cpu", threads=1), name="narrow")
    monkeypatch.setattr(splat_stage, "_bound_kernel_threads", lambda runtime, device: numba.set_num_threads(2))
    train_splat(work, settings, runtime=Runtime(device="cpu", threads=1), name="wide")
    assert (work / "splat-narrow" / "point_cloud.ply").read_bytes() == (
        work / "splat-wide" / "point_cloud.ply"
    ).read_bytes()


def test_a_run_that_fails_stops_the_other_and_says_why_in_one_line(work, monkeypatch):
    (work / "export" / "points3D.ply").unlink()
    with pytest.raises(CubecloudError, match=r"^splat: .*points3D.ply is missing") as error:
        run_stages(splat_stages(work, monkeypatch), work)
    assert "\n" not in str(error.value)
    assert not (work / "splat").exists()


def test_a_child_does_not_run_the_callers_script_again(tmp_path, monkeypatch):
    # A user's script as __main__ (pytest's own, or none under a pytest-xdist worker, would not
    # stand for one): spawn would import it in the child.
    script = types.ModuleType("__main__")
    script.__file__, script.__spec__ = str(tmp_path / "users_script.py"), None
    monkeypatch.setitem(sys.modules, "__main__", script)
    assert "init_main_from_path" in multiprocessing.spawn.get_preparation_data("x")
    with without_main_module():
        data = multiprocessing.spawn.get_preparation_data("x")
    assert not {"init_main_from_path", "init_main_from_name"} & set(data)
