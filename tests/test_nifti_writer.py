import nibabel as nib
import numpy as np
import pytest

from cubecloud_cli.progress import ProgressBar
from cubecloud_cli.volume.nifti import write_nifti


@pytest.mark.parametrize("name", ["v.nii", "v.nii.gz"])
def test_round_trip_through_nibabel(tmp_path, name):
    rng = np.random.default_rng(0)
    volume = rng.random((7, 5, 9), dtype=np.float32)
    affine = np.array([[0.0, -0.8, 0.1, 10], [0.9, 0.0, 0.0, -5], [0.0, 0.05, 2.0, 30], [0, 0, 0, 1]])
    fractions = []
    write_nifti(volume, affine, tmp_path / name, "test", on_progress=fractions.append, slab_bytes=7 * 5 * 4 * 2)
    image = nib.load(str(tmp_path / name))
    assert np.array_equal(np.asarray(image.dataobj), volume)
    assert np.allclose(image.affine, affine, atol=1e-5)
    assert int(image.header["sform_code"]) == 1 and int(image.header["qform_code"]) == 1
    assert image.header.get_xyzt_units()[0] == "mm"
    assert fractions == sorted(fractions) and fractions[-1] == 1.0 and len(fractions) == 5


def test_progress_bar_draws_and_ignores_when_disabled(capsys):
    with ProgressBar(10, "work", enabled=True) as bar:
        for _ in range(10):
            bar.advance(1, loss=0.5, psnr=30.0)
        bar.set_completed(10)
    assert "work" in capsys.readouterr().err
    with ProgressBar(10, "quiet", enabled=False) as bar:
        bar.advance(5, loss=1.0)
    assert capsys.readouterr().err == ""


def test_a_pipeline_shows_one_display_that_stage_bars_join(capsys):
    from cubecloud_cli.progress import PipelineProgress

    with PipelineProgress(2, "run a → b", enabled=True) as display:
        with ProgressBar(4, "stage a", enabled=True) as bar:
            assert bar._progress is display._progress and len(display._progress.tasks) == 2
            bar.advance(4, loss=0.1)
        assert len(display._progress.tasks) == 1  # the stage's bar leaves; the pipeline line stays
        display.stage_done("a", "ran")
        with ProgressBar(3, "stage b", enabled=True, unit=None) as bar:
            bar.advance(3)
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
