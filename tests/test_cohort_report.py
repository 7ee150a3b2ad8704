"""The cohort report from per-scan records: Table I over the cohort, the paired statistics, the
failures, and the files a researcher opens."""

import csv
import json

import pytest

from cubecloud_cli.cohort.report import paired, scan_record, table_one, write_cohort_report


def record(scan_id: str, cube: float, random: float, gaussians: int = 1000) -> dict:
    return {
        "id": scan_id, "scan": f"{scan_id}.nii.gz", "status": "done", "error": None,
        "splat_novel_psnr": cube, "splat_random_novel_psnr": random,
        "splat_psnr": cube - 1.0, "splat_random_psnr": random - 2.0,
        "splat_novel_ssim": 0.99, "splat_random_novel_ssim": 0.98, "splat_ssim": 0.99, "splat_random_ssim": 0.97,
        "cunerf_psnr": 50.0, "cunerf_ssim": 0.999, "splat_gaussians": gaussians, "splat_random_gaussians": gaussians // 2,
        "cunerf_seconds": 100.0, "splat_seconds": 60.0,
    }  # fmt: skip


def test_table_one_is_the_mean_and_std_across_finished_scans(tmp_path):
    records = [record("a", 40.0, 38.0), record("b", 44.0, 41.0), scan_record("c", "c.nii.gz", tmp_path / "gone")]
    lines = table_one(records)
    cube = next(line for line in lines if line.startswith("| Cube-Cloud 3DGS"))
    assert "| 42.00 ± 2.83 |" in cube and cube.endswith("| 2 |")  # the failed scan is not a zero
    random = next(line for line in lines if line.startswith("| 3DGS, random init"))
    assert "| 39.50 ± 2.12 |" in random and "| 500 ± 0 |" in random


def test_the_paired_statistics_take_cube_cloud_minus_random_per_scan():
    records = [record(str(i), 40.0 + i, 39.0 + i + (1.5 if i == 3 else 0.0)) for i in range(8)]
    summary = paired(records)["novel_psnr"]
    assert summary.scans == 8 and (summary.wins, summary.losses) == (7, 1)
    assert summary.mean_difference == pytest.approx((7 * 1.0 - 0.5) / 8)
    assert summary.ci_low <= summary.mean_difference <= summary.ci_high


def test_the_report_lists_failures_with_their_error_and_writes_every_file(tmp_path):
    failed = scan_record("broken", "broken.nii.gz", tmp_path / "nowhere", error="preprocess: the file is corrupt")
    records = [record("a", 40.0, 38.0), record("b", 44.0, 41.0), failed]
    report = write_cohort_report(tmp_path / "out", records, "preset fast").read_text()
    assert (
        "3 scans, 2 finished." in report and "| broken | `broken.nii.gz` | preprocess: the file is corrupt |" in report
    )
    folder = tmp_path / "out" / "cohort"
    rows = list(csv.DictReader(open(folder / "per_scan.csv")))
    assert [row["id"] for row in rows] == ["a", "b", "broken"] and rows[2]["status"] == "failed"
    assert float(rows[1]["splat_novel_psnr"]) == 44.0
    cohort = json.loads((folder / "cohort.json").read_text())
    assert cohort["paired"]["novel_psnr"]["scans"] == 2 and cohort["paired"]["novel_psnr"]["wins"] == 2
    svg = (folder / "differences.svg").read_text()
    assert svg.startswith("<svg") and ">a<" in svg and ">b<" in svg
    assert ">0</text>" in svg  # both differences are positive, and the axis still shows no difference


def test_a_cohort_with_no_finished_scan_still_reports(tmp_path):
    records = [scan_record("x", "x.nii.gz", tmp_path / "none")]
    report = write_cohort_report(tmp_path / "out", records).read_text()
    assert "1 scans, 0 finished." in report and "| – |" in report
    assert json.loads((tmp_path / "out" / "cohort" / "cohort.json").read_text())["paired"]["novel_psnr"] == {
        "scans": 0, "mean_difference": "nan", "ci_low": "nan", "ci_high": "nan", "wilcoxon_p": 1.0,
        "wins": 0, "losses": 0, "ties": 0,
    }  # fmt: skip
