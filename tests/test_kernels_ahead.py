"""`run` compiles the rasterizer's kernels ahead, in a helper at the lowest priority. The helper
is right when it compiles the very signatures the stages then call (numba keys its cache by the
argument types), and when it starts only where a stage will compile them."""

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from cubecloud_cli.core.runtime import Runtime
from cubecloud_cli.pipeline.kernels_ahead import Warmup
from cubecloud_cli.pipeline.runner import _kernels_ahead
from cubecloud_cli.pipeline.table import stage_table
from cubecloud_cli.splat.on_cpu import SplatKernels
from cubecloud_cli.splat.settings import SplatSettings
from cubecloud_cli.splat.stage import SplatStage

# In a process of its own, so that no kernel compiled by another test hides one the helper
# missed: compile ahead, note every kernel's signatures, run the stages as `run` does, and print
# the kernels that gained a signature (compiled by a stage after all).
SCRIPT = r"""
import sys
from pathlib import Path
from numba.core.registry import CPUDispatcher
from cubecloud_cli.pipeline import runner as pipeline
from cubecloud_cli.pipeline.table import stage_table
from cubecloud_cli.cunerf import CunerfSettings
from cubecloud_cli.eval import EvalSettings
from cubecloud_cli.export import ExportSettings
from cubecloud_cli.preprocess import PreprocessSettings
from cubecloud_cli.core.runtime import Runtime
from cubecloud_cli.sample_data import sample_ct_path
from cubecloud_cli.splat.settings import SplatSettings
from cubecloud_cli.pipeline.kernels_ahead import Warmup, warm_up
from cubecloud_cli.splat.on_cpu import SplatKernels

def signatures():
    found = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("cubecloud_cli"):
            for value in vars(module).values():
                if isinstance(value, CPUDispatcher):
                    found[value.py_func.__qualname__] = {str(s) for s in value.signatures}
    return found

splat = SplatSettings(iterations=2)
stages = stage_table(
    sample_ct_path(), Path(sys.argv[1]), PreprocessSettings(size=32),
    CunerfSettings(holdout=2), ExportSettings(resolution=32, views=4, max_points=300, novel_directions=2),
    splat, EvalSettings(turntable_frames=0), Runtime(device="cpu"), baseline=False,
)
assert stages[-2].compile_ahead() is None  # too short a run to compile ahead: the helper is called here
warm_up(SplatKernels(splat))
ahead = signatures()
pipeline.Warmup.start = classmethod(lambda cls, job: Warmup(None))  # this process compiled them
pipeline.run_stages(stages, Path(sys.argv[1]))
after = signatures()
print("compiled ahead:", sorted(k for k, v in ahead.items() if v))
print("compiled by a stage:", sorted(k for k in after if not after[k] <= ahead.get(k, set())))
"""


def test_the_helper_compiles_every_rasterizer_signature_the_splat_and_eval_stages_call(tmp_path):
    done = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path / "work")], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    ahead, by_stage = done.stdout.strip().splitlines()[-2:]
    assert all(kernel in ahead for kernel in ("forward", "backward", "project_forward", "bin_tiles"))
    # Only kernels of the stages before splat (the grid field's, the march), which compile their own.
    compiled_late = eval(by_stage.split(":", 1)[1])
    assert not {"forward", "backward", "project_forward", "project_backward", "bin_tiles"} & set(compiled_late)
    marches = {"dvr_march", "dvr_view", "_slab_interval", "clear_cells"}
    assert set(compiled_late) <= {"encode_forward", "mlp_forward", "encode_backward", "mlp_backward"} | marches


@dataclass(frozen=True)
class StandIn(SplatStage):
    """A stage current or not as the test says; a splat run where ``splat`` (its kernels are the
    ones compiled ahead), else one that compiles none."""

    stand_in_folder: str = ""
    stand_in_upstream: tuple[str, ...] = ()
    current: bool = True
    splat: bool = False

    @property
    def folder(self) -> str:
        return self.stand_in_folder

    @property
    def upstream(self) -> tuple[str, ...]:
        return self.stand_in_upstream

    def is_current(self) -> bool:
        return self.current


def _stage(folder: str, upstream: tuple[str, ...], current: bool, splat: bool = False):
    settings = SplatSettings() if splat else SplatSettings(iterations=1)  # too short to compile ahead
    return StandIn(Path("work"), settings, Runtime(device="cpu"), None, folder, upstream, current, splat)


def test_the_helper_takes_the_kernels_of_the_stages_that_will_run_and_only_behind_another_stage():
    splat = SplatKernels(SplatSettings())
    table = [
        _stage("preprocess", (), True),
        _stage("cunerf", ("preprocess",), False),
        _stage("export", ("cunerf",), True),  # current, but redone after cunerf
        _stage("splat", ("export",), True, splat=True),
    ]
    assert _kernels_ahead(table, force=False) == splat
    everything_current = [_stage(s.folder, s.upstream, True, s.splat) for s in table]
    assert _kernels_ahead(everything_current, force=False) is None
    assert _kernels_ahead(everything_current, force=True) == splat
    assert _kernels_ahead([table[-1]], force=True) is None  # one stage: it compiles its own
    assert _kernels_ahead(table[:3], force=True) is None  # no kernels to compile ahead (or on a GPU)


def test_only_runs_long_enough_to_repay_the_helper_compile_ahead(tmp_path):
    from cubecloud_cli.core.runtime import Runtime
    from cubecloud_cli.cunerf import CunerfSettings
    from cubecloud_cli.eval import EvalSettings
    from cubecloud_cli.export import ExportSettings
    from cubecloud_cli.preprocess import PreprocessSettings
    from cubecloud_cli.splat.on_cpu import COMPILE_AHEAD_MIN_ITERATIONS as MIN_ITERATIONS

    def splat_compiles(iterations: int):
        stages = stage_table(
            tmp_path / "scan.nii.gz", tmp_path, PreprocessSettings(), CunerfSettings(), ExportSettings(),
            SplatSettings(iterations=iterations), EvalSettings(), Runtime(device="cpu"),
        )  # fmt: skip
        return [stage.compile_ahead() for stage in stages if stage.folder.startswith("splat")]

    assert all(job is not None and job.settings.iterations == MIN_ITERATIONS for job in splat_compiles(MIN_ITERATIONS))
    assert splat_compiles(MIN_ITERATIONS - 1) == [None, None]


def test_a_stopped_helper_reports_nothing_compiled(tmp_path):
    helper = Warmup.start(SplatKernels(SplatSettings()))
    helper.stop()
    assert helper.wait() is False and Warmup(None).wait() is False
