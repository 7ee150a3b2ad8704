"""The terminal progress display every command draws through."""

from cubecloud_cli.cli.progress_bar import PipelineProgress, ProgressBar, stage_bar, stage_progress


def test_progress_bar_draws_and_ignores_when_disabled(capsys):
    with ProgressBar(10, "work", enabled=True) as bar:
        for done in range(1, 11):
            bar.update(done, loss=0.5, psnr=30.0)
    assert "work" in capsys.readouterr().err
    with ProgressBar(10, "quiet", enabled=False) as bar:
        bar.update(5, loss=1.0)
    assert capsys.readouterr().err == ""


def test_a_pipeline_shows_one_display_that_stage_bars_join(capsys):
    with PipelineProgress(2, "run a → b", enabled=True) as display:
        with ProgressBar(4, "stage a", enabled=True) as bar:
            assert bar._progress is display._progress and len(display._progress.tasks) == 2
            bar.update(4, loss=0.1)
        assert len(display._progress.tasks) == 1  # the stage's bar leaves; the pipeline line stays
        display.stage_done("a", "ran")
        with ProgressBar(3, "stage b", enabled=True, unit=None) as bar:
            bar.update(3)
            columns = display._progress.columns
            counts = next(c for c in columns if type(c).__name__ == "_Counts")
            assert str(counts.render(display._progress.tasks[1])) == ""  # no M/N for a unitless bar
            assert str(counts.render(display._progress.tasks[0])) == "1/2"
        display.stage_done("b", "skipped")
        assert display._progress.tasks[0].completed == 2
    err = capsys.readouterr().err
    assert "run a → b" in err and "b skipped" in err
    with ProgressBar(2, "alone", enabled=True) as bar:  # after the pipeline, bars draw on their own again
        assert bar._owned


def test_a_stage_bar_restarts_its_count_when_a_phase_counts_to_another_total(capsys):
    with PipelineProgress(1, "run", enabled=True) as display:
        with stage_progress("cunerf", enabled=True) as on_progress:
            on_progress("train", 40, 40, {"loss": 0.25})
            task = display._progress.tasks[1]
            assert (task.completed, task.total, task.description) == (40, 40, "cunerf: train")
            assert task.fields["status"] == "loss 0.25"
            on_progress("reconstruct", 0.5, 1.0, {})
            task = display._progress.tasks[1]
            assert (task.completed, task.total, task.description) == (0.5, 1.0, "cunerf: reconstruct")


def test_stage_bars_join_an_open_pipeline_display_without_being_told(capsys):
    # While rich draws, sys.stderr is its proxy and no terminal, so a bar that checked for one
    # itself never showed inside `cubecloud run`.
    with PipelineProgress(1, "run", enabled=True) as display:
        with stage_bar("splat") as on_progress:
            on_progress("train", 3, 10, {"loss": 0.5})
            assert [task.description for task in display._progress.tasks] == ["run", "splat: train"]
    with ProgressBar(2, "alone") as bar:  # no display open, no terminal: nothing drawn
        assert bar._progress is None
