"""The paper's Table I on a real CT, under cubecloud's protocol.

Cube-Cloud 3DGS (points sampled from CuNeRF) against 3DGS from random points, at equal iterations,
in four settings that share one preprocess/ and cunerf/:

    dvr sphere  volume-rendered images from cameras over the whole sphere (cubecloud's default)
    dvr ring    the same images from an orbit about the long axis
    slice       the paper's images: cross-sections facing the camera, orbit about the sagittal (ap) axis
    stack       the paper's own 3DGS baseline as it describes it: random points, sagittal slices,
                one camera pose for every image (`export --cameras stack --axis lr`)

Every run is scored by `cubecloud eval` against renders of the preprocessed volume, never
against CuNeRF's images: on the novel views (directions no training camera had, 0.75–1.33×; the
same views for every camera setup of an image model) and on its own scene's held-out views.

    python examples/table_one.py --out table1                         # bundled CT, fast preset
    python examples/table_one.py --scan ../shared/data/ct_chest_5mm_pyradiomics_lung1.nii.gz \\
        --window lung --out table1-chest

Stages already complete in OUT are kept and interrupted ones resumed, so running the same command
again continues where the study stopped.
Writes OUT/table_one.md and OUT/table_one.json beside cubecloud's own OUT/eval/.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import time
from pathlib import Path

from cubecloud_cli.cli.cohort import CUBECLOUD_JOBS
from cubecloud_cli.cohort.job_server import JobServerOnDemand
from cubecloud_cli.core.artifacts import is_complete as complete

# (run name in eval, setting, images, cameras, initialisation)
RUNS = (
    ("splat", "dvr sphere", "dvr", "sphere", "Cube-Cloud (CuNeRF points)"),
    ("splat-random", "dvr sphere", "dvr", "sphere", "random"),
    ("splat-ring", "dvr ring", "dvr", "orbit about si", "Cube-Cloud (CuNeRF points)"),
    ("splat-ring-random", "dvr ring", "dvr", "orbit about si", "random"),
    ("splat-slice", "slice", "slice", "orbit about ap", "Cube-Cloud (CuNeRF points)"),
    ("splat-slice-random", "slice", "slice", "orbit about ap", "random"),
    ("splat-paper-baseline", "stack", "sagittal slices", "one pose for all", "random"),
)
# (stage directory, command after WORK); each runs unless its stage is already complete.
STEPS = (
    ("cunerf", ["cunerf"]),
    # explicit: the paper preset's own defaults are slices on a ring
    ("export", ["export", "--view", "dvr", "--cameras", "sphere", "--axis", "si"]),
    ("splat", ["splat"]),
    ("splat-random", ["splat", "--init", "random", "--name", "random"]),
    ("export-ring", ["export", "--view", "dvr", "--cameras", "orbit", "--axis", "si", "--name", "ring"]),
    ("splat-ring", ["splat", "--scene", "{work}/export-ring", "--name", "ring"]),
    ("splat-ring-random", ["splat", "--scene", "{work}/export-ring", "--init", "random", "--name", "ring-random"]),
    ("export-slice", ["export", "--view", "slice", "--cameras", "orbit", "--axis", "ap", "--name", "slice"]),
    ("splat-slice", ["splat", "--scene", "{work}/export-slice", "--name", "slice"]),
    ("splat-slice-random", ["splat", "--scene", "{work}/export-slice", "--init", "random", "--name", "slice-random"]),
    ("export-stack", ["export", "--cameras", "stack", "--view", "slice", "--axis", "lr", "--name", "stack"]),
    (
        "splat-paper-baseline",
        ["splat", "--scene", "{work}/export-stack", "--init", "random", "--name", "paper-baseline"],
    ),
)


def run_study(args: argparse.Namespace, jobs: JobServerOnDemand) -> dict:
    """Run what is not complete yet, each command through the job server (a fresh process that
    does not spend 2–5 s importing torch again)."""

    def cubecloud(*arguments: str) -> None:
        print("  cubecloud " + " ".join(arguments), flush=True)
        subprocess.run([*jobs.command(), *arguments], check=True)

    work = args.out.resolve()
    extra = {stage: shlex.split(options) for stage, options in (item.split("=", 1) for item in args.stage_options)}
    common = ["--preset", args.preset, "-q"]
    started = time.perf_counter()
    if not complete(work / "preprocess"):
        scan = [str(args.scan)] if args.scan else []
        window = ["--window", args.window] if args.window else []
        cubecloud("preprocess", *scan, "-o", str(work), *window, *common, *extra.get("preprocess", []))
    for directory, command in STEPS:
        if not complete(work / directory):
            filled = [part.format(work=work) for part in command]
            # A run killed before its first checkpoint leaves a partial folder with nothing to resume.
            if filled[0] in ("cunerf", "splat") and (work / f".{directory}.partial" / "checkpoint.pt").is_file():
                filled.append("--resume")
            cubecloud(filled[0], str(work), *filled[1:], *common, *extra.get(filled[0], []))
    cubecloud("eval", str(work), "--turntable-frames", "0", "--force", "-q")
    return {
        "work": str(work),
        "seconds": time.perf_counter() - started,
        "metrics": json.loads((work / "eval" / "metrics.json").read_text()),
    }


def table(study: dict) -> tuple[str, list[dict]]:
    results = study["metrics"]["results"]
    paper = (study["metrics"].get("paper") or {}).get("results", {})
    rows = []
    for run, setting, images, cameras, init in RUNS:
        scores = results.get(run)
        if scores is None:
            continue
        rows.append(
            {
                "setting": setting,
                "images": images,
                "cameras": cameras,
                "init": init,
                "iterations": scores.get("iterations"),
                "gaussians": scores.get("gaussians"),
                "novel_psnr": scores.get("novel_psnr"),
                "novel_psnr_std": scores.get("novel_psnr_std"),
                "novel_ssim": scores.get("novel_ssim"),
                "novel_views": scores.get("novel_views"),
                "test_views": scores["views"],
                "psnr": scores["psnr"],
                "psnr_std": scores["psnr_std"],
                "ssim": scores["ssim"],
                "mse": scores["mse"],
                "psnr_foreground": scores.get("psnr_foreground"),
                "train_s": scores.get("train_seconds"),
            }
        )
    lines = [
        "| setting | images | cameras | init | iterations | Gaussians | novel PSNR (0.75–1.33×) | novel SSIM | "
        "held-out views | held-out PSNR | held-out SSIM | MSE | PSNR in body |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        gaussians = f"{row['gaussians']:,}".replace(",", " ")
        lines.append(
            f"| {row['setting']} | {row['images']} | {row['cameras']} | {row['init']} | {row['iterations']} | "
            f"{gaussians} | {_number(row['novel_psnr'], 2)} ± {_number(row['novel_psnr_std'], 2)} | "
            f"{_number(row['novel_ssim'], 4)} | {row['test_views']} | {_number(row['psnr'], 2)} ± {_number(row['psnr_std'], 2)} | "
            f"{_number(row['ssim'], 4)} | {_number(row['mse'], 2, 'e')} | {_number(row['psnr_foreground'], 2)} |"
        )
    for method, scores in paper.items():
        if isinstance(scores, dict) and "psnr" in scores:
            lines.append(
                f"| paper (KiTS23, 512³, 30 000 iterations) | | | {method} | 30000 | | | | | "
                f"{scores['psnr']:.3f} | {scores['ssim']:.4f} | {scores['mse']:.4f} | |"
            )
    return "\n".join(lines) + "\n", rows


def _number(value, digits: int, style: str = "f") -> str:
    """A score as eval wrote it: a number, or "inf" / "nan" (strict JSON has no infinities), or absent."""
    return f"{value:.{digits}{style}}" if isinstance(value, (int, float)) else str(value or "–")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scan", type=Path, help="a CT scan (default: the bundled abdomen CT)")
    parser.add_argument("--window", help="CT window for preprocess, e.g. lung for a chest CT")
    parser.add_argument("--preset", default="fast", choices=("fast", "balanced", "paper"))
    parser.add_argument("--out", type=Path, required=True, help="the work directory")
    parser.add_argument(
        "--stage-options",
        action="append",
        default=[],
        metavar="STAGE=OPTIONS",
        help='options every command of a stage gets, e.g. "splat=--iterations 4000"',
    )
    args = parser.parse_args()
    with JobServerOnDemand(CUBECLOUD_JOBS) as jobs:
        study = run_study(args, jobs)
    markdown, rows = table(study)
    (args.out / "table_one.md").write_text(markdown)
    (args.out / "table_one.json").write_text(
        json.dumps({"scan": str(args.scan or "bundled abdomen CT"), "preset": args.preset, "rows": rows}, indent=1)
    )
    print(markdown)
    print(f"{study['seconds']:.0f} s; wrote {args.out / 'table_one.md'}")


if __name__ == "__main__":
    main()
