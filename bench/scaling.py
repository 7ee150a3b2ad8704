"""How each stage's time, memory and score grow with the cube size: `cubecloud run` on one scan at
several --size values, views as large as the volume (the detail preset), each in a fresh work
directory with an empty numba cache.

    python bench/scaling.py ../shared/data/ct_chest_5mm_pyradiomics_lung1.nii.gz --sizes 128,192,256 \
        --out docs/scaling -- --window lung

Prints one row per size (wall, each stage's seconds and peak memory, Gaussians, novel PSNR whole
and foreground, file sizes), the fitted growth exponent k of each stage's time (time ∝ size^k, a
least-squares line through log time against log size), and the work each stage's model says it
does (rays × steps for export, pixels × Gaussians for splat) so the two growths can be compared.
With --out it writes scaling.json and the charts time.svg and psnr.svg there; --from-json merges
the rows of earlier runs' scaling.json files (sizes run on different days) and redraws. Run it
alone: two cores shared with anything else give other numbers.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

STAGES = ("preprocess", "cunerf", "export", "splat", "splat-random", "eval")


def folder_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e6


def read_run(work: Path, wall: float) -> dict:
    """One size's figures from its manifests and eval/metrics.json."""
    manifests = {s: json.loads((work / s / "manifest.json").read_text()) for s in STAGES if (work / s).is_dir()}
    results = json.loads((work / "eval" / "metrics.json").read_text())["results"]
    export = manifests["export"]
    width = export["cameras"]["width"]
    row = {
        "size": manifests["preprocess"]["volume"]["shape"][0],
        "resolution": width,
        "views": export["metrics"]["views"],
        "wall_s": round(wall, 1),
        "seconds": {s: m.get("timings_s", {}).get("total") for s, m in manifests.items()},
        "peak_mb": {s: m.get("metrics", {}).get("peak_rss_mb") for s, m in manifests.items()},
        "files_mb": {s: round(folder_mb(work / s), 1) for s in manifests},
        "phases_s": {s: m.get("timings_s", {}) for s, m in manifests.items()},
    }
    for run in ("splat", "splat-random"):
        if run not in results:
            continue
        headline = results[run]["novel"]["headline"]
        row[run] = {
            "gaussians": results[run]["gaussians"],
            "iterations": results[run]["iterations"],
            "novel_psnr": headline["psnr"],
            "novel_psnr_foreground": headline["psnr_foreground"],
            "held_out_psnr": results[run]["psnr"],
            "held_out_psnr_foreground": results[run]["psnr_foreground"],
        }
    # The work each stage's cost model counts: rays × steps through the volume (every rendered
    # view, novel references at 2 × 2 sub-pixel rays), and pixels × Gaussians per splat run.
    novel_views = export.get("novel", {}).get("views", 0)
    rays = (2 * row["views"] + 4 * novel_views) * width * width
    row["export_rays_x_steps"] = rays * row["size"]
    if "splat" in row:
        row["splat_pixels_x_gaussians"] = row["splat"]["iterations"] * width * width * row["splat"]["gaussians"]
    return row


def run_size(scan: str | None, size: int, preset: str, extra: list[str], keep: Path | None) -> dict:
    with tempfile.TemporaryDirectory(prefix="cubecloud-scaling-") as scratch:
        work = (keep / f"size{size}") if keep else Path(scratch) / "work"
        environment = dict(os.environ, NUMBA_CACHE_DIR=str(Path(scratch) / "numba"))
        command = ["cubecloud", "run", *([scan] if scan else []), "-o", str(work), "--preset", preset]
        command += ["--size", str(size), *extra]
        start = time.perf_counter()
        finished = subprocess.run(command, env=environment, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if finished.returncode != 0:
            sys.exit(f"`{' '.join(command)}` failed ({finished.returncode}): {finished.stderr.strip()[-800:]}")
        return read_run(work, wall)


def growth_exponent(sizes: list[float], values: list[float]) -> float:
    """The slope of log value against log size (least squares); NaN with fewer than two points or
    sizes too close together (under about 0.1 % apart) for their rounding not to set the slope."""
    pairs = [(math.log(s), math.log(v)) for s, v in zip(sizes, values) if s > 0 and v and v > 0]
    if len(pairs) < 2:
        return float("nan")
    mean_x = sum(x for x, _ in pairs) / len(pairs)
    mean_y = sum(y for _, y in pairs) / len(pairs)
    spread = sum((x - mean_x) ** 2 for x, _ in pairs)
    return sum((x - mean_x) * (y - mean_y) for x, y in pairs) / spread if spread > 1e-6 else float("nan")


def exponents(rows: list[dict]) -> dict[str, float]:
    sizes = [r["size"] for r in rows]
    result = {stage: growth_exponent(sizes, [r["seconds"].get(stage) for r in rows]) for stage in STAGES}
    result["wall"] = growth_exponent(sizes, [r["wall_s"] for r in rows])
    result["export rays × steps"] = growth_exponent(sizes, [r["export_rays_x_steps"] for r in rows])
    result["splat pixels × Gaussians"] = growth_exponent(sizes, [r.get("splat_pixels_x_gaussians") for r in rows])
    return result


def table(rows: list[dict]) -> str:
    head = (
        "| size | wall | "
        + " | ".join(STAGES)
        + " | peak memory | Gaussians (CC / random) | novel PSNR CC / random | foreground | files |"
    )
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        stage_cells = " | ".join(f"{r['seconds'].get(s) or 0:.1f} s" for s in STAGES)
        peak = max(v for v in r["peak_mb"].values() if v) / 1000
        cc, rnd = r.get("splat", {}), r.get("splat-random", {})
        lines.append(
            f"| {r['size']}³, {r['resolution']}² | {r['wall_s']:.0f} s | {stage_cells} | {peak:.2f} GB | "
            f"{cc.get('gaussians', 0):,} / {rnd.get('gaussians', 0):,} | "
            f"{cc.get('novel_psnr', float('nan')):.2f} / {rnd.get('novel_psnr', float('nan')):.2f} dB | "
            f"{cc.get('novel_psnr_foreground', float('nan')):.2f} / {rnd.get('novel_psnr_foreground', float('nan')):.2f} dB | "
            f"{sum(r['files_mb'].values()):.0f} MB |"
        )
    return "\n".join(lines)


def charts(rows: list[dict], out: Path) -> None:
    from cubecloud_cli.eval.figures import line_plot_svg

    sizes = [float(r["size"]) for r in rows]
    series = [(stage, sizes, [r["seconds"].get(stage) or math.nan for r in rows]) for stage in STAGES]
    series.append(("wall", sizes, [r["wall_s"] for r in rows]))
    (out / "time.svg").write_text(
        line_plot_svg(
            series,
            "Time against cube size (chest CT, detail; log-log)",
            "cube side (voxels; views as many pixels)",
            "seconds",
            log_axes=(True, True),
            x_ticks=tuple(sizes),
        )
    )
    scores = []
    for run, label in (("splat", "Cube-Cloud"), ("splat-random", "random init")):
        scores.append((f"{label}, whole", sizes, [r.get(run, {}).get("novel_psnr", math.nan) for r in rows]))
        scores.append((f"{label}, body", sizes, [r.get(run, {}).get("novel_psnr_foreground", math.nan) for r in rows]))
    (out / "psnr.svg").write_text(
        line_plot_svg(
            scores,
            "Novel-view PSNR against cube size",
            "cube side (voxels; views as many pixels)",
            "PSNR (dB)",
            x_ticks=tuple(sizes),
        )
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scan", nargs="?", help="a scan; the bundled CT when left out")
    parser.add_argument("--sizes", default="128,192,256,384,512")
    parser.add_argument("--preset", default="detail")
    parser.add_argument("--keep", type=Path, help="keep each size's work directory under this folder")
    parser.add_argument("--out", type=Path, help="write scaling.json, time.svg and psnr.svg here")
    parser.add_argument(
        "--from-json",
        type=Path,
        nargs="+",
        help="redraw from scaling.json files (their rows merged) instead of running",
    )
    args, extra = parser.parse_known_args()
    extra = [a for a in extra if a != "--"]
    if args.from_json:
        rows = sorted((r for f in args.from_json for r in json.loads(f.read_text())["rows"]), key=lambda r: r["size"])
    else:
        rows = []
        for size in (int(s) for s in args.sizes.split(",")):
            rows.append(run_size(args.scan, size, args.preset, extra, args.keep))
            print(f"size {size}: {rows[-1]['wall_s']:.0f} s", flush=True)
    print(table(rows))
    if len({row["size"] for row in rows}) > 1:  # a slope needs two sizes
        print(
            "growth exponents (time ∝ size^k):",
            json.dumps({k: round(v, 2) for k, v in exponents(rows).items()}, ensure_ascii=False),
        )
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "scaling.json").write_text(json.dumps({"rows": rows, "exponents": exponents(rows)}, indent=1))
        charts(rows, args.out)


if __name__ == "__main__":
    main()
