"""One scalar scene against one baked scene per transfer function (issue 52's baseline): quality on
the transfer functions the scalar scene never trained under, and the total time of each way.

    python bench/transfer_baseline.py --keep /tmp/tb -- --hu-min -1000 --hu-max 1000
    python bench/transfer_baseline.py ../shared/data/ct_chest_5mm_pyradiomics_lung1.nii.gz --set 5 --stride 1 \
        --held-out-windows 12 --keep /tmp/tb_chest -- --hu-min -1000 --hu-max 1000

Runs, in the `fast` preset (the bundled CT unless a scan is given; arguments after `--` go to
preprocess, such as a window wide enough for every held-out tissue):

1. a tiny run of both ways, untimed, which compiles numba's kernels; then preprocess and cunerf
   once (no transfer function enters them, so both ways share them);
2. the scalar way: `export --transfer-set K --transfer-stride S`, `splat --scalar --iterations N
   --max-gaussians B --filter-scale F --rmse-share R` (by default `run --scalar`'s, from
   presets.SCALAR_RUN: 41, 6, 4300, 50000, 0.01 and 0.5), `eval`; eval scores the scalar run under
   each held-out transfer function;
3. today's way, once per held-out transfer function and once for the export's own: a work
   directory with the same preprocess/ and cunerf/, `export --transfer NAME` (a random ramp by its
   window, `--tf-low/--tf-high/--tf-density`), `splat`, `eval`.

4. with `--seeds N`, the scalar way again at export seeds 1..N-1 (untimed: scores only), on the
   same preprocess/ and cunerf/; the seed draws the set's random members (and the points and the
   held-out ramp), which moves a held-out preset by up to 1.4 dB (1-4 dB before half the set was
   tiled), so one seed is one draw.

Prints one row per transfer function (the scalar run's novel-view PSNR, whole and foreground, at
0.75–1.33×, beside the baked run trained on that transfer function alone) and the seconds each
way spends in export and splat, with its ratio to one baked run (`fast`'s own time for one
transfer function). Run it alone: two cores shared with anything else give other numbers.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cubecloud_cli.presets import SCALAR_RUN
from cubecloud_cli.sample_data import sample_ct_path
from cubecloud_cli.transfer.tissue_presets import TRANSFER_PRESETS
from cubecloud_cli.transfer.training_set import HELD_OUT_WINDOW

SHARED = ("preprocess", "cunerf")
SCALAR_EXPORT, SCALAR_SPLAT = SCALAR_RUN["fast"]["export"], SCALAR_RUN["fast"]["splat"]
# The one-length scene's own settings (measured at 2f5acc0), where run --scalar's do not apply.
ONE_LENGTH_SPLAT = {"iterations": 4500, "filter_scale": 0.2, "rmse_share": 0.0}


def cubecloud(*arguments: str) -> float:
    """Run one cubecloud command at the fast preset (eval has none); its wall seconds."""
    command = ["cubecloud", *arguments, *([] if arguments[0] == "eval" else ["--preset", "fast"]), "-q"]
    start = time.perf_counter()
    finished = subprocess.run(command, capture_output=True, text=True)
    if finished.returncode != 0:
        sys.exit(f"`{' '.join(command)}` failed ({finished.returncode}): {finished.stderr.strip()[-800:]}")
    return time.perf_counter() - start


def splat_scores(work: Path) -> dict:
    """eval's results for the splat run of ``work``."""
    return json.loads((work / "eval" / "metrics.json").read_text())["results"]["splat"]


def headline(work: Path) -> dict:
    return splat_scores(work)["novel"]["headline"]


def copy_shared_stages(work: Path, own: Path) -> None:
    """``work``'s preprocess/ and cunerf/ into ``own``: no transfer function or seed enters them."""
    for stage in SHARED:
        shutil.copytree(work / stage, own / stage)


def seed_work(base: Path, seed: int) -> Path:
    """The scalar scene's work directory at export seed ``seed`` (0: the timed one)."""
    return base / "scalar" if seed == 0 else base / f"scalar-seed-{seed}"


def baked_arguments(entry: dict) -> list[str]:
    """export's options for one held-out transfer function: a preset by name, a ramp by its window."""
    if entry["name"] in TRANSFER_PRESETS:
        return ["--transfer", entry["name"]]
    window = [str(entry["low"]), str(entry["high"]), str(entry["density"])]
    return ["--transfer", "tissue", "--tf-low", window[0], "--tf-high", window[1], "--tf-density", window[2]]


def baked_run(work: Path, base: Path, name: str, export_arguments: list[str]) -> dict:
    """Today's pipeline after cunerf under one transfer function, in ``base``/``name``; its seconds."""
    own = base / name
    copy_shared_stages(work, own)
    seconds = {"export": cubecloud("export", str(own), *export_arguments)}
    seconds["splat"] = cubecloud("splat", str(own))
    cubecloud("eval", str(own), "--turntable-frames", "0")
    return seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scan", nargs="?", help="a scan (default: the bundled abdomen CT)")
    parser.add_argument(
        "--set",
        type=int,
        default=SCALAR_EXPORT["transfer_set"],
        help="transfer functions the scalar scene trains under",
    )
    parser.add_argument(
        "--no-chord-lengths",
        action="store_true",
        help=f"one optical length for every direction ({ONE_LENGTH_SPLAT['iterations']} iterations, the 3D filter at "
        f"{ONE_LENGTH_SPLAT['filter_scale']:g}, L1 alone)",
    )
    parser.add_argument(
        "--iterations",
        type=int,
        help=f"the scalar run's (default {SCALAR_SPLAT['iterations']}, {ONE_LENGTH_SPLAT['iterations']} with "
        "--no-chord-lengths; fast's baked runs: 1500)",
    )
    parser.add_argument(
        "--filter-scale",
        type=float,
        help=f"the scalar run's 3D filter, squared training pixels (default {SCALAR_SPLAT['filter_scale']:g}, "
        f"{ONE_LENGTH_SPLAT['filter_scale']:g} with --no-chord-lengths)",
    )
    parser.add_argument(
        "--rmse-share",
        type=float,
        help=f"the scalar run's RMSE share of the pixel loss (default {SCALAR_SPLAT['rmse_share']:g}, "
        f"{ONE_LENGTH_SPLAT['rmse_share']:g} with --no-chord-lengths)",
    )
    parser.add_argument(
        "--stride",
        type=int,
        default=SCALAR_EXPORT["transfer_stride"],
        help="export's --transfer-stride for the scalar set",
    )
    parser.add_argument(
        "--budget",
        type=int,
        default=SCALAR_SPLAT["max_gaussians"],
        help="the scalar run's --max-gaussians (fast's baked runs: 75000)",
    )
    parser.add_argument(
        "--held-out-windows",
        type=int,
        default=0,
        help="also score the scalar run under this many random bands and ramps (no baked run for them; their "
        "references add to the scalar export's seconds, so time the two ways without them)",
    )
    parser.add_argument(
        "--seeds",
        type=int,
        default=1,
        help="also train and score the scalar scene at export seeds 1..N-1 (scores only; about 4 minutes each at "
        "128³) and print each held-out transfer function's mean and lowest over the N seeds",
    )
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
    cubecloud("splat", str(work), "--scalar", "--no-chord-lengths", "--iterations", "20", "--name", "one-length")
    cubecloud("splat", str(work), "--iterations", "20", "--name", "baked")
    shutil.rmtree(work)


def scalar_setting(options, name: str):
    """The scalar run's splat setting ``name`` (iterations, filter_scale, rmse_share): the one
    given, else the one-length scene's or run --scalar's."""
    given = getattr(options, name)
    if given is not None:
        return given
    return (ONE_LENGTH_SPLAT if options.no_chord_lengths else SCALAR_SPLAT)[name]


def run_both_ways(options, base: Path) -> None:
    """Every run, the timed ones' seconds written to ``base``/seconds.json for the report (the
    scalar scene's runs at the other export seeds are scored, not timed)."""
    work = seed_work(base, 0)
    scan = options.scan or str(sample_ct_path())
    extra = options.preprocess
    warm_up(scan, base)
    seconds = {"preprocess": cubecloud("preprocess", scan, "-o", str(work), *extra)}
    seconds["cunerf"] = cubecloud("cunerf", str(work))
    windows = ["--held-out-windows", str(options.held_out_windows)] if options.held_out_windows else []
    spread = ["--transfer-set", str(options.set), "--transfer-stride", str(options.stride)]
    scalar = scalar_splat_arguments(options)
    seconds["scalar export"], seconds["scalar splat"] = scalar_way(work, [*spread, *windows], scalar)
    listed = json.loads((work / "export" / "novel" / "transfers.json").read_text())
    primary = json.loads((work / "export" / "manifest.json").read_text())["transfers"][0]["name"]
    seconds["baked"] = {primary: baked_run(work, base, f"baked-{primary}", ["--transfer", primary])}
    for entry in listed["held_out"]:
        if entry["name"].startswith(HELD_OUT_WINDOW):
            continue  # scored on the scalar run only: see report's summary line
        seconds["baked"][entry["name"]] = baked_run(work, base, f"baked-{entry['name']}", baked_arguments(entry))
    (base / "seconds.json").write_text(json.dumps(seconds, indent=1))
    for seed in range(1, options.seeds):
        again = seed_work(base, seed)
        shutil.rmtree(again, ignore_errors=True)
        copy_shared_stages(work, again)
        scalar_way(again, [*spread, *windows, "--seed", str(seed)], scalar)


def scalar_way(work: Path, export_arguments: list[str], splat_arguments: list[str]) -> tuple[float, float]:
    """The scalar scene's export, splat and eval in ``work``; the export's and the splat's seconds."""
    export_seconds = cubecloud("export", str(work), *export_arguments)
    splat_seconds = cubecloud("splat", str(work), *splat_arguments)
    cubecloud("eval", str(work), "--turntable-frames", "0")
    return export_seconds, splat_seconds


def scalar_splat_arguments(options) -> list[str]:
    arguments = ["--scalar", "--max-gaussians", str(options.budget)]
    for name in ONE_LENGTH_SPLAT:
        arguments += ["--" + name.replace("_", "-"), str(scalar_setting(options, name))]
    return arguments + (["--no-chord-lengths"] if options.no_chord_lengths else [])


def over_seeds(held_out_by_seed: list[dict]) -> dict[str, list[float]]:
    """Each held-out transfer function's whole-image PSNR at every seed, from eval's
    ``held_out_transfers`` of each; the random ramp and windows, another transfer function at each
    seed, under their names as they are."""
    scores: dict[str, list[float]] = {}
    for held_out in held_out_by_seed:
        for name, row in held_out.items():
            scores.setdefault(name, []).append(row["psnr"])
    return scores


def report_over_seeds(options, base: Path) -> None:
    results = [splat_scores(seed_work(base, seed)) for seed in range(options.seeds)]
    scores = over_seeds([result.get("held_out_transfers", {}) for result in results])
    print()
    print(f"over export seeds 0-{options.seeds - 1} (the ramp: another transfer function at each seed)")
    print("| held out | each seed | mean | lowest |")
    print("|---|---|---|---|")
    for name, values in scores.items():
        each = " / ".join(f"{v:.2f}" for v in values)
        print(f"| {name} | {each} | {statistics.mean(values):.2f} | {min(values):.2f} |")


def report(options, base: Path) -> None:
    seconds = json.loads((base / "seconds.json").read_text())
    work = seed_work(base, 0)
    scores = splat_scores(work)
    listed = json.loads((work / "export" / "novel" / "transfers.json").read_text())
    baked = seconds["baked"]
    primary = next(iter(baked))
    shared = seconds["preprocess"] + seconds["cunerf"]
    print(
        f"scan: {options.scan or 'bundled abdomen CT'}; scalar set {options.set} (stride {options.stride}), "
        f"{scalar_setting(options, 'iterations')} iterations{', one length' if options.no_chord_lengths else ''}, "
        f"3D filter {scalar_setting(options, 'filter_scale'):g} px², RMSE share {scalar_setting(options, 'rmse_share'):g}, "
        f"{options.budget} Gaussians at most; fast"
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
    windows = [row["psnr"] for name, row in rows.items() if name.startswith(HELD_OUT_WINDOW)]
    if windows:
        print(
            f"| {len(windows)} random held-out windows | yes | mean {statistics.mean(windows):.2f}, median "
            f"{statistics.median(windows):.2f}, lowest {min(windows):.2f}; {sum(w >= 40 for w in windows)} at 40 dB "
            "or more | – | – |"
        )
    for why in listed.get("not_scored", {}).values():
        print(f"not scored: {why}")
    fixed = scores.get("novel_fixed_opacity")
    if fixed:  # chord lengths: what one opacity per Gaussian (the PLY, for other viewers) shows of the own
        print(
            f"{primary} with one opacity per Gaussian (the PLY): {fixed['psnr']:.2f} ({fixed['psnr_foreground']:.2f})"
        )
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
    if options.seeds > 1:
        report_over_seeds(options, base)


if __name__ == "__main__":
    main()
