"""The whole pipeline's time as a new user meets it: `cubecloud run` on a scan, each stage's
seconds and both splat runs' novel-view PSNR, median of --repeats runs.

    python bench/pipeline.py                          # bundled CT, --preset fast, 3 runs
    python bench/pipeline.py --repeats 1 --keep work-bench -- --cunerf-iterations 2000
    python bench/pipeline.py --warm                   # numba's compiled kernels kept between runs

Every run starts in an empty work directory and, unless --warm, with an empty numba cache
(NUMBA_CACHE_DIR points at a fresh folder), so the first compilation of every kernel is in the
time, as on a fresh install. Arguments after `--` go to `cubecloud run`. Run it alone: two
cores shared with anything else give other numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cubecloud_cli.eval.compare import describe_work

STAGE_ORDER = ("preprocess", "cunerf", "export", "splat", "splat-random", "eval")


def stage_seconds(work: Path) -> dict[str, float]:
    """Each stage's own wall time from its manifest (eval's too)."""
    seconds = {}
    for stage in STAGE_ORDER:
        manifest = work / stage / "manifest.json"
        if manifest.is_file():
            seconds[stage] = json.loads(manifest.read_text()).get("timings_s", {}).get("total")
    return seconds


def one_run(scan: str | None, preset: str, extra: list[str], warm_cache: Path | None, keep: Path | None) -> dict:
    with tempfile.TemporaryDirectory(prefix="cubecloud-bench-") as scratch:
        work = keep if keep is not None else Path(scratch) / "work"
        environment = dict(os.environ, NUMBA_CACHE_DIR=str(warm_cache or Path(scratch) / "numba"))
        command = ["cubecloud", "run", *([scan] if scan else []), "-o", str(work), "--preset", preset, *extra]
        start = time.perf_counter()
        finished = subprocess.run(command, env=environment, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if finished.returncode != 0:
            sys.exit(f"`{' '.join(command)}` failed ({finished.returncode}): {finished.stderr.strip()[-500:]}")
        rows = describe_work(work)["rows"]
        return {
            "wall": wall,
            "stages": stage_seconds(work),
            # CuNeRF's rows have no novel views: only the splat runs are scored on them.
            "novel_psnr": {row: v["novel_psnr"] for row, v in rows.items() if v["novel_psnr"] is not None},
        }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scan", nargs="?", help="a scan; the bundled CT when left out")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--warm", action="store_true", help="keep numba's cache between runs (after the first)")
    parser.add_argument("--keep", type=Path, help="work directory to keep (the last run's)")
    # Everything after `--` goes to `cubecloud run` untouched (argparse would read it as the scan).
    argv = sys.argv[1:]
    split = argv.index("--") if "--" in argv else len(argv)
    args = parser.parse_args(argv[:split])
    extra = argv[split + 1 :]

    with tempfile.TemporaryDirectory(prefix="cubecloud-numba-") as shared_cache:
        runs = []
        for repeat in range(args.repeats):
            keep = args.keep if args.keep is not None and repeat == args.repeats - 1 else None
            if keep is not None and keep.exists():
                sys.exit(f"{keep} exists: give --keep a new folder")
            run = one_run(args.scan, args.preset, extra, Path(shared_cache) if args.warm else None, keep)
            runs.append(run)
            stages = "  ".join(f"{stage} {seconds:.1f}" for stage, seconds in run["stages"].items())
            novel = "  ".join(f"{row} {psnr:.2f} dB" for row, psnr in run["novel_psnr"].items())
            print(f"run {repeat + 1}: wall {run['wall']:.1f} s | {stages} | novel PSNR {novel}", flush=True)

    print(
        f"\nmedian of {len(runs)} ({'warm' if args.warm else 'cold'} numba cache), preset {args.preset} {' '.join(extra)}"
    )
    print(f"  pipeline wall: {statistics.median(r['wall'] for r in runs):.1f} s")
    for stage in STAGE_ORDER:
        values = [r["stages"][stage] for r in runs if r["stages"].get(stage) is not None]
        if values:
            print(f"  {stage:13s} {statistics.median(values):7.1f} s")
    for row in runs[0]["novel_psnr"]:
        values = [r["novel_psnr"][row] for r in runs if r["novel_psnr"].get(row) is not None]
        print(f"  novel PSNR {row}: {statistics.median(values):.2f} dB (runs: {', '.join(f'{v:.2f}' for v in values)})")


if __name__ == "__main__":
    main()
