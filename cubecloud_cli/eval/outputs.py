"""The files `cubecloud eval` writes: ``metrics.json`` (nerfstudio-like ``{"results": …}``),
``per_view.csv`` and ``report.md`` in the layout of the paper's Table I."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from cubecloud_cli.eval.scoring import METRICS

# The paper's Table I (KiTS23, 30 000 iterations each): its data, its protocol.
PAPER_TABLE_I = {
    "source": "the Cube-Cloud 3DGS paper's Table I: KiTS23, their images, cameras and protocol",
    "results": {
        "Cube-Cloud 3DGS": {"psnr": 28.104, "ssim": 0.7856, "mse": 0.0501},
        "3DGS, random init": {"psnr": 25.397, "ssim": 0.7352, "mse": 0.0682},
    },
}

PER_VIEW_COLUMNS = (
    "row",
    "method",
    "set",
    "view",
    "magnification",
    "angle_deg",
    "angle_bin",
    *METRICS,
    "against",
    "scene",
)


def write_per_view_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=PER_VIEW_COLUMNS, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow(
                {key: (f"{value:.6g}" if isinstance(value, float) else value) for key, value in row.items()}
            )


def _number(value, digits: int = 2, scientific: bool = False) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, float) and math.isinf(value):
        return "∞" if value > 0 else "−∞"
    if isinstance(value, int):
        return f"{value:,}".replace(",", " ")
    return f"{value:.{digits}e}" if scientific else f"{value:.{digits}f}"


def cell_table(novel: dict, metric: str = "psnr") -> list[str]:
    """A markdown table of one run's novel cells: angle bins down, magnifications across."""
    magnifications = list(novel["by_magnification"])
    lines = [
        "| angle from nearest training camera | " + " | ".join(f"{m}×" for m in magnifications) + " |",
        "|---|" + "---|" * len(magnifications),
    ]
    for label in novel["angle_bins"]:
        cells = []
        for m in magnifications:
            cell = next((c for c in novel["cells"] if c["angle"] == label and f"{c['magnification']:g}" == m), None)
            cells.append("–" if cell is None else f"{_number(cell[metric], _digits(metric))} ({cell['views']})")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append(
        "| all | "
        + " | ".join(
            f"{_number(novel['by_magnification'][m][metric], _digits(metric))} "
            f"({novel['by_magnification'][m]['views']})"
            for m in magnifications
        )
        + " |"
    )
    return lines


def _digits(metric: str) -> int:
    return 4 if metric.startswith("ssim") else 2


def _with_std(result: dict, metric: str, digits: int, scientific: bool = False) -> str:
    mean, std = result.get(metric), result.get(f"{metric}_std")
    text = _number(mean, digits, scientific)
    if isinstance(std, float) and math.isfinite(std) and text != "–":
        text += f" ± {_number(std, digits, scientific)}"
    return text


def table_rows(results: dict[str, dict], paper: bool = False) -> list[str]:
    """The Table I layout: one line per row of ``results``, the novel-view headline first (and,
    with ``paper``, the paper's two lines after them, marked as the paper's)."""
    lines = [
        "| row | method | against | novel PSNR ↑ (0.75–1.33×) | novel SSIM ↑ | held-out views | PSNR ↑ (dB) | SSIM ↑ | "
        "MSE ↓ | PSNR fg | SSIM fg | render ms/frame | training | Gaussians | size MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row, result in results.items():
        training = result.get("train_seconds")
        lines.append(
            " | ".join(
                [
                    f"| `{row}`",
                    result["method_name"],
                    "volume" if result.get("reference") == "volume" else "own images",
                    _with_std(result, "novel_psnr", 2),
                    _with_std(result, "novel_ssim", 4),
                    str(result["views"]),
                    _with_std(result, "psnr", 2),
                    _with_std(result, "ssim", 4),
                    _with_std(result, "mse", 2, scientific=True),
                    _with_std(result, "psnr_foreground", 2),
                    _with_std(result, "ssim_foreground", 4),
                    _number(result.get("ms_per_frame"), 1),
                    "–" if training is None else f"{training:.0f} s",
                    _number(result.get("gaussians")),
                    _number(result.get("size_mb"), 1),
                ]
            )
            + " |"
        )
    if paper:
        for method, values in PAPER_TABLE_I["results"].items():
            lines.append(
                f"| paper | {method} | KiTS23, their protocol | – | – | – | {values['psnr']:.3f} | {values['ssim']:.4f} | "
                f"{values['mse']:.2e} | – | – | – | 30 000 it. | – | – |"
            )
    return lines


def report_markdown(title: str, protocol: dict, results: dict[str, dict], pictures: dict[str, list[str]]) -> str:
    lines = [f"# {title}", "", "## Protocol", ""]
    lines += [f"- **{key.replace('_', ' ')}**: {value}" for key, value in protocol.items() if isinstance(value, str)]
    lines += [
        "",
        "## Results (Table I layout, our protocol)",
        "",
        "Mean ± standard deviation over views. `novel`: the "
        "novel views at magnifications 0.75, 1 and 1.33 (the headline); `held-out views`: the scene's own test "
        "views, on its training orbit and zoom. `fg`: inside the foreground (reference > 0). `training`: the "
        "stage's training time.",
        "",
    ]
    lines += table_rows(results, paper=True)
    lines += [
        "",
        f"The `paper` lines are **the paper's own numbers** ({PAPER_TABLE_I['source']}), beside ours for "
        "orientation. They are not comparable number for number: other scans, other images (sagittal slices), "
        "and a baseline trained from one camera pose. `against`: what a row is scored against (the volume's "
        "reference renders, or a foreign scene's own images).",
    ]
    lines += _novel_section(results)
    transferred, not_scored = held_out_transfer_results(results)
    if transferred:
        lines += held_out_transfer_table(transferred, not_scored)
    lines += _pictures_section(pictures)
    lines += ["", "Per-view scores: [per_view.csv](per_view.csv). Machine-readable: [metrics.json](metrics.json).", ""]
    return "\n".join(lines)


def _novel_section(results: dict[str, dict]) -> list[str]:
    """Each run's novel-view cells, and for a chord-length scene its score drawn with one opacity
    per Gaussian, as other splat viewers draw it."""
    lines: list[str] = []
    novel_runs = {row: result["novel"] for row, result in results.items() if result.get("novel")}
    if novel_runs:
        lines += [
            "",
            "## Novel views",
            "",
            "PSNR (dB) per cell: the angle from the nearest training camera (rows) and "
            "the magnification (columns; 1 fits the whole cube), with the number of views in brackets. SSIM per "
            "cell is in metrics.json, every view in per_view.csv.",
        ]
        for row, novel in novel_runs.items():
            lines += ["", f"`{row}`:", ""] + cell_table(novel)
            fixed = results[row].get("novel_fixed_opacity")
            if fixed:
                lines += [
                    "",
                    f"`{row}`'s opacities follow the view (chord lengths; `cubecloud view` and the shared page redraw "
                    f"them when the camera rests). Drawn with one opacity per Gaussian, as its PLY's reference columns "
                    f"and so any other splat viewer draw it: "
                    f"{_number(fixed.get('psnr'))} dB ({_number(fixed.get('psnr_foreground'))} dB in the body) at the "
                    f"novel views 0.75–1.33×, against {_number(novel['headline'].get('psnr'))} dB at the same views drawn as trained.",
                ]
    return lines


# Each kind of picture eval draws, in the report's order, with the lines that introduce it.
PICTURE_SECTIONS: tuple[tuple[str, list[str]], ...] = (
    (
        "held_out_transfers",
        ["", "Each held-out transfer function at one novel view, beside the volume rendered under it:", ""],
    ),
    ("novel", ["", "Novel views beside their references (from above, from below, zoomed in, zoomed out):", ""]),
    (
        "views",
        [
            "",
            "## Held-out views",
            "",
            "Each row: the reference, a method's render, and its absolute error "
            "(one colour scale per view, shown by the bar).",
            "",
        ],
    ),
    ("turntables", ["", "## Turntables", ""]),
    (
        "curves",
        [
            "",
            "## Training curves",
            "",
            "Test PSNR during training, from each run's `log.csv`: against the images it "
            "trained on (CuNeRF renders), not the volume's reference renders.",
            "",
        ],
    ),
)


def _pictures_section(pictures: dict[str, list[str]]) -> list[str]:
    """Every picture eval drew, each kind under its introduction (PICTURE_SECTIONS)."""
    lines: list[str] = []
    for kind, introduction in PICTURE_SECTIONS:
        if pictures.get(kind):
            lines += introduction + [f"![{Path(p).stem}]({p})" for p in pictures[kind]]
    return lines


def held_out_transfer_results(results: dict[str, dict]) -> tuple[dict[str, dict[str, dict]], dict[str, str]]:
    """From metrics.json's results: each scalar run's scores under the transfer functions it never
    trained under, and the held-out presets the volume could not show (why, by name)."""
    transferred = {row: r["held_out_transfers"] for row, r in results.items() if r.get("held_out_transfers")}
    not_scored = {name: why for r in results.values() for name, why in r.get("held_out_not_scored", {}).items()}
    return transferred, not_scored


def held_out_transfer_table(transferred: dict[str, dict[str, dict]], not_scored: dict[str, str]) -> list[str]:
    """The scalar scenes' novel-view scores under transfer functions they never trained under,
    and the held-out presets the volume could not show."""
    lines = [
        "",
        "## Transfer functions held out of training",
        "",
        "Scalar scenes (`splat --scalar`) drawn under transfer functions none of them trained under, at the "
        "headline novel views (0.75–1.33×), against the volume rendered under each. The window is the ramp "
        "in preprocessed intensities [0, 1] (a band's fall after ↘) and its extinction per world unit.",
        "",
        "| run | transfer function | window | PSNR (dB) | fg PSNR (dB) | SSIM | views |",
        "|---|---|---|---|---|---|---|",
    ]
    for row, by_name in transferred.items():
        for name, summary in by_name.items():
            window = summary.get("transfer", {})
            fall = (
                f" ↘ {window['fall_low']:.3f}–{window['fall_high']:.3f}" if window.get("fall_low") is not None else ""
            )
            lines.append(
                f"| {row} | {name} | {window.get('low', math.nan):.3f}–{window.get('high', math.nan):.3f}{fall}, "
                f"{window.get('density', math.nan):.3g} | {_number(summary.get('psnr'))} | "
                f"{_number(summary.get('psnr_foreground'))} | {_number(summary.get('ssim'), 4)} | {summary.get('views')} |"
            )
    if not_scored:
        lines += [""] + [f"Not scored: {why}." for why in not_scored.values()]
    return lines
