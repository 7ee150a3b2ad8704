"""run_stages, the loop over the stage table, with stand-in stages: what is skipped, resumed and redone."""

from cubecloud_cli.pipeline.runner import PipelineStage, run_stages


def table(tmp_path, current: set[str], checkpoints: set[str] = frozenset(), ran: list | None = None):
    ran = [] if ran is None else ran
    upstream = {"a": (), "b": ("a",), "c": ("b",), "d": ("b",), "e": ("a", "b", "c", "d")}

    def stage(folder):
        checkpoint = tmp_path / f"{folder}.ckpt"
        if folder in checkpoints:
            checkpoint.write_text("saved")

        def run(force, resume, on_progress):
            ran.append((folder, force, resume))
            on_progress("work", 1, 1, {})
            return {}

        return PipelineStage(folder, upstream[folder], lambda: folder in current, run, checkpoint=checkpoint)

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
