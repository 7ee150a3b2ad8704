"""`cubecloud eval` end to end on a tiny pipeline: numbers, pictures, the report, comparisons and
the bad-input contract."""

import csv
import json
import shutil

import numpy as np
import pytest

from cli_helpers import assert_one_line_error, invoke

QUICK = ["--iterations", "40", "--eval-every", "20", "--checkpoint-every", "20", "-q"]


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    work = tmp_path_factory.mktemp("eval") / "work"
    for args in (["preprocess", "-o", work, "--size", "32"],
                 ["cunerf", work, "--iterations", "60", "--batch-size", "1024", "--holdout", "2"],
                 ["export", work, "--resolution", "32", "--views", "12", "--cube", "8", "--points-per-cube", "64", "--max-points", "1500"],
                 ["splat", work, *QUICK],
                 ["splat", work, *QUICK, "--init", "random", "--random-points", "500", "--name", "random"]):
        result = invoke(*args, "-q")
        assert result.exit_code == 0, result.output
    result = invoke("eval", work, "--turntable-frames", "6", "-q")
    assert result.exit_code == 0, result.output
    return work


def test_a_report_from_a_tiny_run(work):
    eval_dir = work / "eval"
    metrics = json.loads((eval_dir / "metrics.json").read_text())  # strict JSON: no NaN/Infinity literals
    results = metrics["results"]
    assert list(results) == ["splat", "splat-random", "cunerf", "cunerf-training-views"]
    assert results["splat"]["method_name"] == "Cube-Cloud 3DGS" and results["splat-random"]["method_name"] == "3DGS, random init"
    for row in ("splat", "splat-random"):
        result = results[row]
        assert result["views"] == 2 and result["view_names"] == ["view_000.png", "view_008.png"]
        assert 5 < result["psnr"] < 80 and 0 < result["ssim"] <= 1 and result["ms_per_frame"] > 0
        assert result["gaussians"] > 0 and result["size_mb"] > 0 and "psnr_std" in result and "psnr_foreground" in result
    assert results["cunerf-training-views"]["views"] == 10
    # The CuNeRF row is the export's own figure, recomputed per view.
    export = json.loads((work / "export" / "manifest.json").read_text())
    assert results["cunerf"]["psnr"] == pytest.approx(export["metrics"]["cunerf_vs_reference_psnr"], abs=1e-3)
    assert "reference" in metrics["protocol"] and metrics["paper"]["results"]["Cube-Cloud 3DGS"]["psnr"] == 28.104
    with open(eval_dir / "per_view.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 2 + 2 + 2 + 10 and {r["row"] for r in rows} == set(results)
    report = (eval_dir / "report.md").read_text()
    for picture in ("views/view_000.png", "views/view_008.png", "turntable_splat.gif", "turntable_splat-random.gif",
                    "psnr_vs_iteration.svg"):
        assert f"]({picture})" in report and (eval_dir / picture).is_file()
    assert "28.104" in report and "(paper)" in report and "| `splat` | Cube-Cloud 3DGS | 2 |" in report


def test_renders_are_scored_against_the_reference_not_the_training_images(work, tmp_path):
    """Swap the reference for the CuNeRF images: the CuNeRF rows must then become perfect."""
    copy = tmp_path / "work"
    shutil.copytree(work, copy, ignore=shutil.ignore_patterns("eval"))
    np.save(copy / "export" / "reference.npy", np.load(copy / "export" / "images.npy"))
    result = invoke("eval", copy, "--turntable-frames", "0", "-q")
    assert result.exit_code == 0, result.output
    metrics = json.loads((copy / "eval" / "metrics.json").read_text())
    assert metrics["results"]["cunerf"]["psnr"] == "inf" and metrics["results"]["cunerf"]["psnr_std"] == "nan"
    assert "turntable" not in (copy / "eval" / "report.md").read_text()


def test_compare_builds_one_table(work, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(work, other, ignore=shutil.ignore_patterns("eval", "splat-random"))
    result = invoke("eval", "--compare", work, "--compare", other, "--output", tmp_path / "cmp", "--turntable-frames", "0", "-q")
    assert result.exit_code == 0, result.output
    assert (other / "eval" / "metrics.json").is_file()  # evaluated on the way
    records = json.loads((tmp_path / "cmp" / "comparison.json").read_text())
    assert [r["work"] for r in records] == [str(work), str(other)]
    assert set(records[0]["rows"]) == {"splat", "splat-random", "cunerf", "cunerf-training-views"}
    assert records[0]["setup"]["resolution"] == 32 and records[0]["rows"]["splat"]["iterations"] == 40
    assert records[0]["rows"]["splat"]["pipeline_seconds"] > records[0]["rows"]["splat"]["splat_seconds"]
    table = (tmp_path / "cmp" / "comparison.md").read_text().splitlines()
    assert len([line for line in table if line.startswith("| `")]) == 4 + 3


def test_bad_input(work, tmp_path):
    assert_one_line_error(invoke("eval", tmp_path / "nowhere"), r"not a work directory")
    empty = tmp_path / "empty"
    shutil.copytree(work, empty, ignore=shutil.ignore_patterns("eval", "splat*"))
    assert_one_line_error(invoke("eval", empty), r"no trained splat run.*cubecloud splat")
    assert_one_line_error(invoke("eval", work), r"already complete.*--force")
    broken = tmp_path / "broken"
    shutil.copytree(work, broken, ignore=shutil.ignore_patterns("eval"))
    (broken / "splat" / "point_cloud.ply").write_bytes(b"ply\nnot really")
    assert_one_line_error(invoke("eval", broken), r"point_cloud.ply is missing or changed")
    assert not (broken / "eval").exists()
    moved = tmp_path / "moved"  # its runs name a scene that no longer exists, and it has no export of its own
    shutil.copytree(work, moved, ignore=shutil.ignore_patterns("eval", "export"))
    for run in ("splat", "splat-random"):
        manifest = json.loads((moved / run / "manifest.json").read_text())
        manifest["scene"]["directory"] = str(tmp_path / "gone" / "export")
        (moved / run / "manifest.json").write_text(json.dumps(manifest))
    assert_one_line_error(invoke("eval", moved), r"scene .* is gone")
    assert_one_line_error(invoke("eval", work, "--turntable-frames", "-1", "--force"), r"--turntable-frames")
    assert_one_line_error(invoke("eval", "--compare", tmp_path / "nowhere"), r"not a work directory")
