"""One scalar scene against one baked scene per transfer function (issue 52's baseline): quality on
the transfer functions the scalar scene never trained under, and the total time of each way.

    python bench/transfer_baseline.py --keep /tmp/tb -- --hu-min -1000 --hu-max 1000
    python bench/transfer_baseline.py ../shared/data/ct_chest_5mm_pyradiomics_lung1.nii.gz --set 3 \
        --iterations 1500 --keep /tmp/tb_chest -- --hu-min -1000 --hu-max 1000

Runs, in the `fast` preset (the bundled CT unless a scan is given; arguments after `--` go to
preprocess, such as a window wide enough for every held-out tissue):

1. a tiny run of both ways, untimed, which compiles numba's kernels; then preprocess and cunerf
   once (no transfer function enters them, so both ways share them);
2. the scalar way: `export --transfer-set K`, `splat --scalar --iterations N` (the set and length
   docs/results.md chose: 5 and 3000), `eval`; eval scores the scalar run under each held-out
   transfer function;
3. today's way, once per held-out transfer function and once for the export's own: a work
   directory with the same preprocess/ and cunerf/, `export --transfer NAME` (a random ramp by its
   window, `--tf-low/--tf-high/--tf-density`), `splat`, `eval`.

Prints one row per transfer function (the scalar run's novel-view PSNR, whole and foreground, at
0.75–1.33×, beside the baked run trained on that transfer function alone) and the seconds each
way spends in export and splat, with its ratio to one baked run (`fast`'s own time for one
transfer function). Run it alone: two cores shared with anything else give other numbers.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cubecloud_cli.sample_data import sample_ct_path
from cubecloud_cli.transfer.tissue_presets import TRANSFER_PRESETS

SHARED = ("preprocess", "cunerf")


def cubecloud(*arguments: str) -> float:
    """Run one cubecloud command at the fast preset (eval has none); its wall seconds."""
    command = ["cubecloud", *arguments, *([] if arguments[0] == "eval" else ["--preset", "fast"]), "-q"]
    start = time.perf_counter()
    finished = subprocess.run(command, capture_output=True, text=True)
    if finished.returncode != 0:
        sys.exit(f"`{' '.join(command)}` failed ({finished.returncode}): {finished.stderr.strip()[-800:]}")
    return time.perf_counter() - start


def headline(work: Path, run: str = "splat") -> dict:
    return json.loads((work / "eval" / "metrics.json").read_text())["results"][run]["novel"]["headline"]


def baked_arguments(entry: dict) -> list[str]:
    """export's options for one held-out transfer function: a preset by name, a ramp by its window."""
    if entry["name"] in TRANSFER_PRESETS:
        return ["--transfer", entry["name"]]
    window = [str(entry["low"]), str(entry["high"]), str(entry["density"])]
    return ["--transfer", "tissue", "--tf-low", window[0], "--tf-high", window[1], "--tf-density", window[2]]


def baked_run(work: Path, base: Path, name: str, export_arguments: list[str]) -> dict:
    """Today's pipeline after cunerf under one transfer function, in ``base``/``name``; its seconds."""
    own = base / name
    for stage in SHARED:
        shutil.copytree(work / stage, own / stage)
    seconds = {"export": cubecloud("export", str(own), *export_arguments)}
    seconds["splat"] = cubecloud("splat", str(own))
    cubecloud("eval", str(own), "--turntable-frames", "0")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scan", nargs="?", help="a scan (default: the bundled abdomen CT)")
    parser.add_argument("--set", type=int, default=5, help="transfer functions the scalar scene trains under")
    parser.add_argument("--iterations", type=int, default=3000, help="the scalar run's (fast's baked runs: 1500)")
    parser.add_argument("--keep", type=Path, help="keep the work directories here (default: a temporary one)")
    parser.add_argument("--report-only", action="store_true", help="print the report of a --keep directory again")
    arguments = sys.argv[1:]
    split = arguments.index("--") if "--" in arguments else len(arguments)
    options = parser.parse_args(arguments[:split])
    options.preprocess = arguments[split + 1 :]  # preprocess's options
    with tempfile.TemporaryDirectory(prefix="cubecloud-transfer-") as scratch:
        base = options.keep or Path(scratch)
        if not options.report_only:
            run_both_ways(options, base)
        report(options, base)


def warm_up(scan: str, base: Path) -> None:
    """A tiny run of both ways, untimed, so that numba's kernels are compiled (and cached) before
    either way is timed: otherwise the first export pays the compilation (14 s) and the rest not."""
    work = base / "warm-up"
    cubecloud("preprocess", scan, "-o", str(work), "--size", "32")
    cubecloud("cunerf", str(work), "--iterations", "20")
    small = ["--views", "6", "--resolution", "32", "--novel-directions", "2"]
    cubecloud("export", str(work), *small, "--transfer-set", "2")
    cubecloud("splat", str(work), "--scalar", "--iterations", "20")
    cubecloud("splat", str(work), "--iterations", "20", "--name", "baked")
    shutil.rmtree(work)


def run_both_ways(options, base: Path) -> None:
    """Every run, its seconds written to ``base``/seconds.json for the report."""
    work = base / "scalar"
    scan = options.scan or str(sample_ct_path())
    extra = options.preprocess
    warm_up(scan, base)
    seconds = {"preprocess": cubecloud("preprocess", scan, "-o", str(work), *extra)}
    seconds["cunerf"] = cubecloud("cunerf", str(work))
    seconds["scalar export"] = cubecloud("export", str(work), "--transfer-set", str(options.set))
    seconds["scalar splat"] = cubecloud("splat", str(work), "--scalar", "--iterations", str(options.iterations))
    cubecloud("eval", str(work), "--turntable-frames", "0")
    listed = json.loads((work / "export" / "novel" / "transfers.json").read_text())
    primary = json.loads((work / "export" / "manifest.json").read_text())["transfers"][0]["name"]
    seconds["baked"] = {primary: baked_run(work, base, f"baked-{primary}", ["--transfer", primary])}
    for entry in listed["held_out"]:
        seconds["baked"][entry["name"]] = baked_run(work, base, f"baked-{entry['name']}", baked_arguments(entry))
    (base / "seconds.json").write_text(json.dumps(seconds, indent=1))


def report(options, base: Path) -> None:
    seconds = json.loads((base / "seconds.json").read_text())
    work = base / "scalar"
    scores = json.loads((work / "eval" / "metrics.json").read_text())["results"]["splat"]
    listed = json.loads((work / "export" / "novel" / "transfers.json").read_text())
    baked = seconds["baked"]
    primary = next(iter(baked))
    shared = seconds["preprocess"] + seconds["cunerf"]
    print(
        f"scan: {options.scan or 'bundled abdomen CT'}; scalar set {options.set}, {options.iterations} iterations; fast"
    )
    print(f"shared: preprocess {seconds['preprocess']:.1f} s, cunerf {seconds['cunerf']:.1f} s")
    print()
    print("| transfer function | held out | scalar PSNR (fg) | baked on it alone PSNR (fg) | baked export + splat |")
    print("|---|---|---|---|---|")
    rows = {primary: scores["novel"]["headline"], **scores.get("held_out_transfers", {})}
    for name, own_seconds in baked.items():
        mine, own = rows.get(name, {}), headline(base / f"baked-{name}")
        print(
            f"| {name} | {'no' if name == primary else 'yes'} | {mine.get('psnr', float('nan')):.2f} "
            f"({mine.get('psnr_foreground', float('nan')):.2f}) | {own['psnr']:.2f} ({own['psnr_foreground']:.2f}) | "
            f"{own_seconds['export']:.0f} + {own_seconds['splat']:.0f} s |"
        )
    for why in listed.get("not_scored", {}).values():
        print(f"not scored: {why}")
    one_total = shared + baked[primary]["export"] + baked[primary]["splat"]
    scalar_total = shared + seconds["scalar export"] + seconds["scalar splat"]
    baked_total = shared + sum(b["export"] + b["splat"] for b in baked.values())
    print()
    print(f"one baked pipeline (fast, {primary}, preprocess to splat): {one_total:.0f} s")
    print(
        f"scalar pipeline: {scalar_total:.0f} s = {scalar_total / one_total:.2f}x "
        f"(export {seconds['scalar export']:.0f} s, splat {seconds['scalar splat']:.0f} s)"
    )
    print(f"baked, one per transfer function ({len(baked)}): {baked_total:.0f} s = {baked_total / one_total:.2f}x")


if __name__ == "__main__":
    main()
