"""`cubecloud eval` end to end on a tiny pipeline: numbers, pictures, the report, comparisons and
the bad-input contract."""

import csv
import json
import shutil

import numpy as np
import pytest
from cli_helpers import assert_one_line_error, invoke, record_as_written, tiny_work

QUICK = ["--iterations", "40", "--eval-every", "20", "--checkpoint-every", "20", "-q"]


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    work = tiny_work(tmp_path_factory.mktemp("eval") / "work", cunerf_iterations=60, views=12, max_points=1500,
                     novel_directions=3, splat=QUICK, baseline=True)  # fmt: skip
    result = invoke("eval", work, "--turntable-frames", "6", "-q")
    assert result.exit_code == 0, result.output
    return work


def test_a_report_from_a_tiny_run(work):
    eval_dir = work / "eval"
    metrics = json.loads((eval_dir / "metrics.json").read_text())  # strict JSON: no NaN/Infinity literals
    results = metrics["results"]
    assert list(results) == ["splat", "splat-random", "cunerf", "cunerf-training-views"]
    assert (
        results["splat"]["method_name"] == "Cube-Cloud 3DGS"
        and results["splat-random"]["method_name"] == "3DGS, random init"
    )
    for row in ("splat", "splat-random"):
        result = results[row]
        assert result["views"] == 2 and result["view_names"] == ["view_000.png", "view_008.png"]
        assert 5 < result["psnr"] < 80 and 0 < result["ssim"] <= 1 and result["ms_per_frame"] > 0
        assert (
            result["gaussians"] > 0 and result["size_mb"] > 0 and "psnr_std" in result and "psnr_foreground" in result
        )
    assert results["cunerf-training-views"]["views"] == 10
    # The CuNeRF row is the export's own figure, recomputed per view.
    export = json.loads((work / "export" / "manifest.json").read_text())
    assert results["cunerf"]["psnr"] == pytest.approx(export["metrics"]["cunerf_vs_reference_psnr"], abs=1e-3)
    assert "reference" in metrics["protocol"] and metrics["paper"]["results"]["Cube-Cloud 3DGS"]["psnr"] == 28.104
    with open(eval_dir / "per_view.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 2 + 2 + 2 + 10 + 2 * 15 and {r["row"] for r in rows} == set(results)  # 3 novel directions × 5
    novel_rows = [r for r in rows if r["set"] == "novel"]
    assert {r["magnification"] for r in novel_rows} == {"0.5", "0.75", "1", "1.33", "2"}
    assert all(0 <= float(r["angle_deg"]) <= 180 and r["angle_bin"] for r in novel_rows)
    report = (eval_dir / "report.md").read_text()
    for picture in (
        "views/view_000.png",
        "views/view_008.png",
        "turntable_splat.gif",
        "turntable_splat-random.gif",
        "psnr_vs_iteration.svg",
        "views/novel_m1_d00.png",
        "views/novel_m1_d01.png",
        "views/novel_m2_d02.png",
        "views/novel_m0.5_d02.png",
    ):
        assert f"]({picture})" in report and (eval_dir / picture).is_file()
    assert (
        "| paper | Cube-Cloud 3DGS | KiTS23, their protocol | – | – | – | 28.104 |" in report
        and "the paper's own numbers" in report
    )
    assert "| `splat` | Cube-Cloud 3DGS | volume | " in report and "| angle from nearest training camera |" in report
    for row in ("splat", "splat-random"):
        novel = results[row]["novel"]
        # The headline is the mean over the 0.75–1.33× views, 3 directions each.
        headline = [
            float(r["psnr"]) for r in novel_rows if r["row"] == row and r["magnification"] in ("0.75", "1", "1.33")
        ]
        assert results[row]["novel_views"] == 9 and results[row]["novel_psnr"] == pytest.approx(
            np.mean(headline), rel=1e-5
        )
        assert sum(cell["views"] for cell in novel["cells"]) == 15 and set(novel["by_magnification"]) == {
            "0.5",
            "0.75",
            "1",
            "1.33",
            "2",
        }
    for row in ("cunerf", "cunerf-training-views"):
        assert "novel_psnr" not in results[row]


def test_renders_are_scored_against_the_reference_not_the_training_images(work, tmp_path):
    """Swap the reference for the CuNeRF images: the CuNeRF rows must then become perfect."""
    copy = tmp_path / "work"
    shutil.copytree(work, copy, ignore=shutil.ignore_patterns("eval"))
    np.save(copy / "export" / "reference.npy", np.load(copy / "export" / "images.npy"))
    record_as_written(copy / "export", "reference.npy")
    result = invoke("eval", copy, "--turntable-frames", "0", "-q")
    assert result.exit_code == 0, result.output
    metrics = json.loads((copy / "eval" / "metrics.json").read_text())
    assert metrics["results"]["cunerf"]["psnr"] == "inf" and metrics["results"]["cunerf"]["psnr_std"] == "nan"
    assert "turntable" not in (copy / "eval" / "report.md").read_text()


def test_compare_builds_one_table(work, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(work, other, ignore=shutil.ignore_patterns("eval", "splat-random"))
    # WORK also named in --compare, under another spelling: evaluated once, listed once.
    result = invoke(
        "eval",
        work,
        "--compare",
        work.parent / ".." / work.parent.name / work.name,
        "--compare",
        other,
        "--output",
        tmp_path / "cmp",
        "--turntable-frames",
        "0",
        "-q",
    )
    assert result.exit_code == 0, result.output
    assert (other / "eval" / "metrics.json").is_file()  # evaluated on the way; work's current eval was kept
    records = json.loads((tmp_path / "cmp" / "comparison.json").read_text())
    assert [r["work"] for r in records] == [str(work), str(other)]
    assert set(records[0]["rows"]) == {"splat", "splat-random", "cunerf", "cunerf-training-views"}
    assert records[0]["setup"]["resolution"] == 32 and records[0]["rows"]["splat"]["iterations"] == 40
    row = records[0]["rows"]["splat"]
    assert row["scene"] == "this work's export" and row["pipeline_seconds"] > row["splat_seconds"] > 0
    table = (tmp_path / "cmp" / "comparison.md").read_text().splitlines()
    assert len([line for line in table if line.startswith("| `")]) == 4 + 3
    # A run retrained after its eval makes that eval stale: the comparison redoes it.
    stamp = (other / "eval" / "manifest.json").stat().st_mtime_ns
    assert invoke("splat", other, *QUICK, "--iterations", "30", "--force").exit_code == 0
    assert (
        invoke(
            "eval", "--compare", work, "--compare", other, "--output", tmp_path / "cmp", "--turntable-frames", "0", "-q"
        ).exit_code
        == 0
    )
    assert (other / "eval" / "manifest.json").stat().st_mtime_ns != stamp
    assert json.loads((tmp_path / "cmp" / "comparison.json").read_text())[1]["rows"]["splat"]["iterations"] == 30


def test_a_run_on_a_foreign_scene_is_marked_and_counted(work, tmp_path):
    from cubecloud_cli.eval import EvalSettings, evaluate_work

    copy = tmp_path / "work"
    shutil.copytree(work, copy, ignore=shutil.ignore_patterns("eval"))
    foreign = tmp_path / "foreign"  # a COLMAP scene of PNG files, no reference renders
    shutil.copytree(work / "export", foreign, ignore=shutil.ignore_patterns("*.npy", "manifest.json", "split.json"))
    assert invoke("splat", copy, "--scene", foreign, "--name", "foreign", *QUICK).exit_code == 0
    calls = []
    evaluate_work(copy, EvalSettings(turntable_frames=5), on_progress=lambda *a: calls.append(a[1:3]))
    assert calls[-1][0] == calls[-1][1] and all(done <= total for done, total in calls)
    metrics = json.loads((copy / "eval" / "metrics.json").read_text())
    assert (
        metrics["results"]["splat-foreign"]["reference"] == "images"
        and metrics["results"]["splat"]["reference"] == "volume"
    )
    assert "splat-foreign" in metrics["protocol"]["other scenes"]
    assert "| `splat-foreign` | Cube-Cloud 3DGS | own images |" in (copy / "eval" / "report.md").read_text()
    assert "cunerf" in metrics["results"]  # the work's own export still gives the CuNeRF rows


def test_bad_input(work, tmp_path):
    def copy(name, ignore=("eval",)):
        target = tmp_path / name
        shutil.copytree(work, target, ignore=shutil.ignore_patterns(*ignore))
        return target

    assert_one_line_error(invoke("eval", tmp_path / "nowhere"), r"not a work directory")
    assert_one_line_error(invoke("eval"), r"give a work directory")
    assert_one_line_error(invoke("eval", copy("empty", ("eval", "splat*"))), r"no trained splat run.*cubecloud splat")
    assert_one_line_error(invoke("eval", work), r"already complete.*--force")
    broken = copy("broken")
    (broken / "splat" / "point_cloud.ply").write_bytes(b"ply\nnot really")
    assert_one_line_error(invoke("eval", broken), r"point_cloud.ply is missing or changed")
    assert not (broken / "eval").exists()
    no_reference = copy("no_reference")  # never silently scored against the CuNeRF images instead
    (no_reference / "export" / "reference.npy").unlink()
    assert_one_line_error(invoke("eval", no_reference), r"reference.npy is missing.*cubecloud export")
    changed = copy("changed")  # the export was redone after training: other views, other cameras
    assert (
        invoke(
            "export",
            changed,
            "--resolution",
            "24",
            "--views",
            "16",
            "--cube",
            "8",
            "--points-per-cube",
            "64",
            "--max-points",
            "1500",
            "--force",
            "-q",
        ).exit_code
        == 0
    )
    assert_one_line_error(invoke("eval", changed), r"export is gone or has changed since splat was trained.*--force")
    moved = copy("moved", ("eval", "export"))
    assert_one_line_error(invoke("eval", moved), r"export is gone or has changed")
    nan_run = copy("nan_run")  # the same size, non-finite values
    from cubecloud_cli.splat.gaussian_ply import read_gaussians_ply, write_gaussians_ply

    gaussians = read_gaussians_ply(nan_run / "splat" / "point_cloud.ply")
    gaussians.sh_dc[:] = float("nan")
    write_gaussians_ply(nan_run / "splat" / "point_cloud.ply", gaussians)
    assert_one_line_error(invoke("eval", nan_run), r"point_cloud.ply changed since its stage wrote it.*--force")
    record_as_written(nan_run / "splat", "point_cloud.ply")  # as if training had written them
    assert_one_line_error(invoke("eval", nan_run), r"splat renders NaN or Inf.*retrain")
    bad_novel = copy("bad_novel")  # novel references damaged after the export: refused, never scored
    np.save(bad_novel / "export" / "novel" / "reference.npy", np.zeros((3, 32, 32), dtype=np.float32))
    assert_one_line_error(invoke("eval", bad_novel), r"novel/reference.npy is missing or changed.*cubecloud export")
    np.save(bad_novel / "export" / "novel" / "reference.npy", np.full((15, 32, 32), np.nan, dtype=np.float32))
    assert_one_line_error(invoke("eval", bad_novel), r"novel/reference.npy holds NaN or Inf.*cubecloud export")
    bad_split = copy("bad_split")
    (bad_split / "export" / "split.json").write_text('{"test": ')
    assert_one_line_error(invoke("eval", bad_split), r"split.json")
    assert_one_line_error(invoke("eval", work, "--turntable-frames", "-1", "--force"), r"--turntable-frames")
    assert_one_line_error(invoke("eval", "--compare", tmp_path / "nowhere"), r"not a work directory")
    corrupt = copy("corrupt", ())
    (corrupt / "eval" / "metrics.json").write_text("[1, 2]")
    assert_one_line_error(invoke("eval", "--compare", corrupt, "--compare", work), r"metrics.json")
