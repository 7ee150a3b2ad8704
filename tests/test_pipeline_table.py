"""run_stages, the loop over the stage table, with stand-in stages: what is skipped, resumed and redone."""

from pathlib import Path

from cubecloud_cli.core.stage import Stage
from cubecloud_cli.pipeline.runner import run_stages


class StandIn(Stage):
    """A stage that only notes how it was run: current or not as the test says."""

    folder, upstream, checkpoint = "", (), None  # plain attributes here, not the contract's properties

    def __init__(self, work: Path, folder: str, upstream: tuple, current: bool, checkpoint: Path, ran: list):
        self.work, self.folder, self.upstream, self.settings = work, folder, upstream, None
        self.current, self.checkpoint, self.ran = current, checkpoint, ran

    def input_files(self) -> list[Path]:
        return []

    def recorded_params(self) -> dict:
        return {}

    def is_current(self) -> bool:
        return self.current

    def run(self, force, resume, on_progress):
        self.ran.append((self.folder, force, resume))
        on_progress("work", 1, 1, {})
        return {}


def table(tmp_path, current: set[str], checkpoints: set[str] = frozenset(), ran: list | None = None):
    ran = [] if ran is None else ran
    upstream = {"a": (), "b": ("a",), "c": ("b",), "d": ("b",), "e": ("a", "b", "c", "d")}

    def stage(folder):
        checkpoint = tmp_path / f"{folder}.ckpt"
        if folder in checkpoints:
            checkpoint.write_text("saved")
        return StandIn(tmp_path, folder, upstream[folder], folder in current, checkpoint, ran)

    return [stage(folder) for folder in upstream], ran


def statuses(outcomes):
    return {outcome.stage: outcome.status for outcome in outcomes}


def test_current_stages_are_skipped_and_a_rebuilt_stage_rebuilds_only_what_reads_it(tmp_path):
    stages, ran = table(tmp_path, current={"a", "b", "d", "e"})
    outcomes = run_stages(stages, tmp_path)
    # c is stale: it is redone, d (a sibling reading b) is kept, e (reading c) is redone.
    assert statuses(outcomes) == {"a": "skipped", "b": "skipped", "c": "ran", "d": "skipped", "e": "ran"}
    assert [folder for folder, _, _ in ran] == ["c", "e"]


def test_an_interrupted_stage_resumes_unless_its_input_changed(tmp_path):
    stages, ran = table(tmp_path, current={"a"}, checkpoints={"b", "c"})
    outcomes = run_stages(stages, tmp_path)
    assert statuses(outcomes)["b"] == "resumed" and ("b", False, True) in ran
    assert statuses(outcomes)["c"] == "ran" and ("c", True, False) in ran  # b ran, so c's saved work is stale


def test_force_redoes_every_stage_from_scratch(tmp_path):
    stages, ran = table(tmp_path, current={"a", "b", "c", "d", "e"}, checkpoints={"b"})
    seen = []
    outcomes = run_stages(stages, tmp_path, force=True, on_stage=seen.append)
    assert set(statuses(outcomes).values()) == {"ran"} and all(force and not resume for _, force, resume in ran)
    assert [outcome.stage for outcome in seen] == ["a", "b", "c", "d", "e"]


def test_the_five_stages_implement_the_contract(tmp_path):
    from cubecloud_cli.core.runtime import Runtime
    from cubecloud_cli.cunerf import CunerfSettings
    from cubecloud_cli.eval import EvalSettings
    from cubecloud_cli.export import ExportSettings
    from cubecloud_cli.pipeline.table import stage_table
    from cubecloud_cli.preprocess import PreprocessSettings
    from cubecloud_cli.splat.settings import SplatSettings

    scan = tmp_path / "scan.nii.gz"
    stages = stage_table(
        scan, tmp_path, PreprocessSettings(), CunerfSettings(), ExportSettings(), SplatSettings(),
        EvalSettings(), Runtime(device="cpu"),
    )  # fmt: skip
    assert [stage.folder for stage in stages] == ["preprocess", "cunerf", "export", "splat", "splat-random", "eval"]
    assert [type(stage).__name__ for stage in stages] == [
        "PreprocessStage", "CunerfStage", "ExportStage", "SplatStage", "SplatStage", "EvalStage",
    ]  # fmt: skip
    for stage in stages:
        assert Stage in type(stage).__mro__  # each subclasses the contract, inheriting its defaults
        for member in ("folder", "upstream", "input_files", "recorded_params", "run"):
            assert getattr(type(stage), member) is not getattr(Stage, member), f"{stage.folder} lacks {member}"
        assert stage.work == tmp_path and stage.settings is not None
        assert all(name in [s.folder for s in stages] for name in stage.upstream)
        assert not stage.is_current()  # nothing written yet
    assert stages[0].input_files() == [scan]
    assert [stage.checkpoint is not None for stage in stages] == [False, True, False, True, True, False]
    assert stages[4].recorded_params()["init"] == "random"
    assert stages[-1].upstream == ("preprocess", "cunerf", "export", "splat", "splat-random")
