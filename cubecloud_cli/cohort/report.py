"""The cohort report, OUT/cohort/: every scan's scores, Gaussian counts and stage times
(per_scan.csv, cohort.json) and report.md with the paper's Table I over the cohort (mean ± std
across scans), the paired Cube-Cloud − random differences with their statistics, and a plot of
the differences scan by scan.

Each scan's record comes from its work directory as `cubecloud eval --compare` reads one
(eval/compare.py: describe_work); a scan whose pipeline failed is listed with its error.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from cubecloud_cli.cohort.statistics import PairedSummary, mean_std, paired_summary
from cubecloud_cli.core.artifacts import to_jsonable
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.eval.compare import describe_work
from cubecloud_cli.eval.figures import line_plot_svg

REPORT_DIR = "cohort"
STAGES = ("preprocess", "cunerf", "export", "splat", "splat-random", "eval")
# The table's rows: (work directory row, the paper's name).
METHODS = (("splat", "Cube-Cloud 3DGS"), ("splat-random", "3DGS, random init"), ("cunerf", "CuNeRF"))
# The scores compared scan by scan: eval's headline (novel views) first, then its held-out views.
PAIRED_SCORES = (("novel_psnr", "novel-view PSNR (dB), eval's headline"), ("psnr", "held-out-view PSNR (dB)"))
CSV_COLUMNS = [
    "id", "scan", "modality", "status", "error",
    "splat_novel_psnr", "splat_random_novel_psnr", "splat_psnr", "splat_random_psnr",
    "splat_novel_ssim", "splat_random_novel_ssim", "splat_ssim", "splat_random_ssim", "cunerf_psnr",
    "splat_gaussians", "splat_random_gaussians",
    *[f"{stage.replace('-', '_')}_seconds" for stage in STAGES],
]  # fmt: skip


def scan_record(scan_id: str, scan: str, work: Path, error: str | None = None) -> dict:
    """One scan's line of the report; a scan without a current eval is a failure."""
    record = {"id": scan_id, "scan": scan, "status": "failed", "error": error}
    if error is None:
        try:
            described = describe_work(work)
        except CubecloudError as exc:
            record["error"] = str(exc)
            return record
        rows = described["rows"]
        record.update(status="done", error=None, modality=_modality(work))
        for row, prefix in (("splat", "splat"), ("splat-random", "splat_random"), ("cunerf", "cunerf")):
            values = rows.get(row, {})
            for metric in ("novel_psnr", "psnr", "novel_ssim", "ssim", "gaussians"):
                record[f"{prefix}_{metric}"] = values.get(metric)
            if row.startswith("splat"):
                record[f"{prefix}_seconds"] = values.get("splat_seconds")
        for stage, seconds in described["stage_seconds"].items():
            record[f"{stage}_seconds"] = seconds
        record["eval_seconds"] = _eval_seconds(work)
    return record


def _modality(work: Path) -> str | None:
    """CT or MR, as preprocess decided (the header, the values, or --modality)."""
    try:
        return json.loads((Path(work) / "preprocess" / "manifest.json").read_text())["intensity"]["modality"].upper()
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def _eval_seconds(work: Path) -> float | None:
    try:
        return json.loads((Path(work) / "eval" / "manifest.json").read_text())["timings_s"]["total"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _number(value) -> float:
    """A score as a float for the statistics: missing (None) is NaN."""
    return math.nan if value is None else float(value)


def _mean_std_cell(values, digits: int = 2) -> str:
    mean, std = mean_std([_number(v) for v in values])
    if math.isnan(mean):
        return "–"
    return f"{mean:.{digits}f}" if math.isnan(std) else f"{mean:.{digits}f} ± {std:.{digits}f}"


def table_one(records: list[dict]) -> list[str]:
    """The paper's Table I layout, each cell the mean ± std over the scans that finished."""
    done = [r for r in records if r["status"] == "done"]
    lines = [
        "| method | novel PSNR (dB) ↑ | novel SSIM ↑ | held-out PSNR (dB) ↑ | held-out SSIM ↑ | Gaussians | scans |",
        "|---|---|---|---|---|---|---|",
    ]
    for row, name in METHODS:
        prefix = row.replace("-", "_")
        cells = [
            _mean_std_cell([r.get(f"{prefix}_novel_psnr") for r in done]),
            _mean_std_cell([r.get(f"{prefix}_novel_ssim") for r in done], 4),
            _mean_std_cell([r.get(f"{prefix}_psnr") for r in done]),
            _mean_std_cell([r.get(f"{prefix}_ssim") for r in done], 4),
            _mean_std_cell([r.get(f"{prefix}_gaussians") for r in done], 0) if row != "cunerf" else "–",
            str(sum(r.get(f"{prefix}_psnr") is not None for r in done)),
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def paired(records: list[dict]) -> dict[str, PairedSummary]:
    """Cube-Cloud − random init per scan, for each compared score."""
    done = [r for r in records if r["status"] == "done"]
    return {
        score: paired_summary(
            [_number(r.get(f"splat_{score}")) for r in done], [_number(r.get(f"splat_random_{score}")) for r in done]
        )  # fmt: skip
        for score, _ in PAIRED_SCORES
    }


def paired_lines(summaries: dict[str, PairedSummary]) -> list[str]:
    lines = [
        "| score | scans | mean difference | 95 % bootstrap interval | Wilcoxon p | Cube-Cloud wins | random wins | ties |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for score, label in PAIRED_SCORES:
        s = summaries[score]
        interval = "–" if math.isnan(s.ci_low) else f"[{s.ci_low:+.2f}, {s.ci_high:+.2f}]"
        mean = "–" if math.isnan(s.mean_difference) else f"{s.mean_difference:+.2f} dB"
        lines.append(
            f"| {label} | {s.scans} | {mean} | {interval} | {s.wilcoxon_p:.3g} | {s.wins} | {s.losses} | {s.ties} |"
        )
    return lines


def differences_plot(records: list[dict]) -> str:
    """Each scan's headline difference, scans sorted by it (the grid line at 0 is no difference)."""
    done = [r for r in records if r["status"] == "done"]
    pairs = sorted(
        ((_number(r.get("splat_novel_psnr")) - _number(r.get("splat_random_novel_psnr")), r["id"]) for r in done),
        key=lambda pair: (math.isnan(pair[0]), pair[0]),
    )
    pairs = [pair for pair in pairs if math.isfinite(pair[0])]
    ranks = [float(i + 1) for i in range(len(pairs))]
    series = [("Cube-Cloud − random", ranks, [d for d, _ in pairs])]
    return line_plot_svg(series, "Paired difference per scan (novel-view PSNR)", "scan, sorted by the difference",
                         "Cube-Cloud − random init (dB)", markers_only=True, y_include=(0.0,),
                         point_labels={"Cube-Cloud − random": [name for _, name in pairs]})  # fmt: skip


def _cell(value, digits: int = 2) -> str:
    number = _number(value)
    return "–" if not math.isfinite(number) else f"{number:.{digits}f}"


def per_scan_lines(records: list[dict]) -> list[str]:
    """One line per finished scan: its scores, the paired difference, its size and time."""
    lines = [
        "| id | modality | novel PSNR, Cube-Cloud | random init | difference | held-out PSNR, Cube-Cloud | random init "
        "| Gaussians, Cube-Cloud / random | pipeline min |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in (r for r in records if r["status"] == "done"):
        difference = _number(r.get("splat_novel_psnr")) - _number(r.get("splat_random_novel_psnr"))
        seconds = [_number(r.get(f"{stage.replace('-', '_')}_seconds")) for stage in STAGES]
        minutes = sum(seconds) / 60.0 if all(math.isfinite(v) for v in seconds) else math.nan
        lines.append(
            f"| {r['id']} | {r.get('modality') or '–'} | {_cell(r.get('splat_novel_psnr'))} | "
            f"{_cell(r.get('splat_random_novel_psnr'))} | {'–' if math.isnan(difference) else f'{difference:+.2f}'} | "
            f"{_cell(r.get('splat_psnr'))} | {_cell(r.get('splat_random_psnr'))} | "
            f"{_cell(r.get('splat_gaussians'), 0)} / {_cell(r.get('splat_random_gaussians'), 0)} | {_cell(minutes, 1)} |"
        )
    return lines


def report_markdown(records: list[dict], summaries: dict[str, PairedSummary], setup: str) -> str:
    failed = [r for r in records if r["status"] != "done"]
    lines = [
        "# Cohort report",
        "",
        f"{len(records)} scans, {len(records) - len(failed)} finished. {setup}",
        "",
        "## Table I over the cohort (mean ± std across scans)",
        "",
        *table_one(records),
        "",
        "## Cube-Cloud − random initialisation, scan by scan",
        "",
        "Each scan is one pair; the interval is a percentile bootstrap of the mean over scans, the "
        "p-value the two-sided Wilcoxon signed-rank test.",
        "",
        *paired_lines(summaries),
        "",
        "![paired differences](differences.svg)",
        "",
        "## Per scan",
        "",
        *per_scan_lines(records),
        "",
    ]
    if failed:
        lines += ["## Failed scans", "", "| id | scan | error |", "|---|---|---|"]
        lines += [f"| {r['id']} | `{r['scan']}` | {(r.get('error') or 'no finished eval').replace('|', '/')} |"
                  for r in failed]  # fmt: skip
        lines.append("")
    lines += ["Every number of every scan: `per_scan.csv` and `cohort.json`."]
    return "\n".join(lines) + "\n"


def write_cohort_report(out: Path, records: list[dict], setup: str = "") -> Path:
    """Write OUT/cohort/ from the scans' records; returns the report's path."""
    directory = Path(out) / REPORT_DIR
    directory.mkdir(parents=True, exist_ok=True)
    summaries = paired(records)
    with open(directory / "per_scan.csv", "w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=CSV_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for record in records:
            writer.writerow({column: record.get(column) for column in CSV_COLUMNS})
    cohort = {"scans": records, "paired": {score: s.as_dict() for score, s in summaries.items()}, "setup": setup}
    (directory / "cohort.json").write_text(json.dumps(to_jsonable(cohort), indent=2) + "\n")
    (directory / "differences.svg").write_text(differences_plot(records))
    (directory / "report.md").write_text(report_markdown(records, summaries, setup))
    return directory / "report.md"
