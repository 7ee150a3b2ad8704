"""The speed–accuracy trade of cubecloud, measured: a preset and single-knob variations of it,
each run through the whole pipeline, with every stage's wall time and the held-out scores.

    python examples/trade_study.py --out trade                        # bundled CT, every knob
    python examples/trade_study.py --scan ../shared/data/ct_chest_5mm_pyradiomics_lung1.nii.gz --window lung --out trade-chest
    python examples/trade_study.py --knobs iterations,budget --out quick   # only the splat knobs
    cubecloud run -o trade/balanced --preset balanced && python examples/trade_study.py --out trade --include balanced=trade/balanced
    cubecloud run -o work-bal --preset balanced && python examples/trade_study.py --preset balanced --base work-bal --out trade-bal
    python examples/trade_study.py --knobs iterations --values iterations=500,1000 --out smoke   # a quick look

Knobs (each varied alone around the preset; ``--preset`` fast by default). Unless ``--values``
says otherwise, a numeric knob takes values relative to the preset's own: volume ×0.75 and ×1.5,
CuNeRF iterations ×0.125, ×0.25 and ×0.5 (none for a preset that trains none), CuNeRF batch ×0.5 and ×2, views ×0.5 and ×2, points
per cube ×0.25 and ×4, iterations ×0.5 and ×2, budget ×1/8 and ×1/4; a choice takes every value
but the preset's.

    volume             preprocess --size
    cunerf_start       cunerf: the fitted start alone (volume: --grid-init volume --iterations 0), or
                       random features trained 3000 iterations (random), the fast preset before
    cunerf_iterations  cunerf --iterations
    cunerf_batch       cunerf --batch-size
    cameras            export --cameras (orbit, sphere)
    views              export --views
    points_per_cube    export --points-per-cube
    iterations         splat --iterations (both runs)
    budget             splat --max-gaussians (both runs)
    antialias          splat --antialias / --no-antialias (both runs: on, off)

Scores: the novel-view headline (mean over 0.75–1.33×, docs/design.md §5), its 0.5× and 2× means, and
the held-out views, all against renders of the preprocessed volume.

Each configuration gets a work directory OUT/<config>/. Stages whose options and inputs match an
earlier configuration's are hard-linked from it rather than rerun, and keep that run's recorded
wall time, so every configuration's time is that of a run from the scan. Rerunning into the same
OUT keeps the stages whose command chain is unchanged and redoes the others (an interrupted one
from scratch, so that its time stays whole). Writes:

    OUT/trade.csv, OUT/trade.json   one line per configuration and method
    OUT/trade.md                    the table
    OUT/time_vs_psnr.svg            pipeline time against held-out PSNR, one point per configuration
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

from cubecloud_cli.cli.cohort import CUBECLOUD_JOBS
from cubecloud_cli.cohort.job_server import JobServerOnDemand
from cubecloud_cli.core.artifacts import is_complete

STAGES = ("preprocess", "cunerf", "export", "splat", "splat-random", "eval")


@dataclass(frozen=True)
class Knob:
    stage: str
    option: str  # for an on/off knob, the flag that turns it on ("--no-" + name turns it off)
    factors: tuple[float, ...] = ()  # default values as multiples of the preset's own
    choices: tuple[str, ...] = ()  # or: the values of a choice
    with_choice: tuple[tuple[str, tuple[str, ...]], ...] = ()  # more options a choice brings along

    def arguments(self, value) -> list[str]:
        more = list(dict(self.with_choice).get(value, ()))
        if more:
            return [self.option, str(value), *more]
        if self.choices == ("on", "off"):
            return [self.option if value == "on" else self.option.replace("--", "--no-", 1)]
        return [self.option, str(value)]

    def parse(self, text: str):
        return text if self.choices else int(text)


KNOBS = {
    "volume": Knob("preprocess", "--size", (0.75, 1.5)),  # fast: 96, 192
    "cunerf_start": Knob(
        "cunerf",
        "--grid-init",
        choices=("volume", "random"),
        with_choice=(("volume", ("--iterations", "0")), ("random", ("--iterations", "3000"))),
    ),
    "cunerf_iterations": Knob("cunerf", "--iterations", (0.125, 0.25, 0.5)),  # from 5000: 625, 1250, 2500
    "cunerf_batch": Knob("cunerf", "--batch-size", (0.5, 2.0)),  # from 2048: 1024, 4096
    "cameras": Knob("export", "--cameras", choices=("orbit", "sphere")),
    "views": Knob("export", "--views", (0.5, 2.0)),  # fast: 60, 240
    "points_per_cube": Knob("export", "--points-per-cube", (0.25, 4.0)),  # fast: 128, 2048
    "iterations": Knob("splat", "--iterations", (0.5, 2.0)),  # fast: 750, 3000
    "budget": Knob("splat", "--max-gaussians", (0.125, 0.25)),  # fast: 25 000, 50 000 (smaller budgets)
    "antialias": Knob("splat", "--antialias", choices=("on", "off")),
}


def preset_values(preset: str, extra: dict[str, list[str]]) -> dict:
    """Each knob's value in the base configuration: the preset's, or the --stage-options one."""
    from cubecloud_cli.presets import PRESETS, resolve_cunerf

    cunerf = resolve_cunerf(preset, None, {})
    values = {
        "volume": PRESETS["preprocess"][preset]["size"],
        "views": PRESETS["export"][preset]["views"],
        "cunerf_start": cunerf["grid_init"],
        "cunerf_iterations": cunerf["iterations"],
        # A preset that trains no iteration has no batch to vary.
        "cunerf_batch": cunerf["batch_size"] if cunerf["iterations"] else None,
        "cameras": PRESETS["export"][preset]["cameras"],
        "points_per_cube": PRESETS["export"][preset]["points_per_cube"],
        "iterations": PRESETS["splat"][preset]["iterations"],
        "budget": PRESETS["splat"][preset]["max_gaussians"],
        "antialias": "on" if PRESETS["splat"][preset]["antialias"] else "off",
    }
    for name, knob in KNOBS.items():
        options = extra.get(knob.stage, [])
        if knob.choices == ("on", "off"):  # the last flag given wins, as on the CLI
            flags = [o for o in options if o in (knob.option, knob.option.replace("--", "--no-", 1))]
            if flags:
                values[name] = "on" if flags[-1] == knob.option else "off"
        elif knob.option in options and options.index(knob.option) + 1 < len(options):
            values[name] = knob.parse(options[len(options) - 1 - options[::-1].index(knob.option) + 1])
    return values


def stage_commands(
    scan: str | None,
    work: Path,
    preset: str,
    window: str | None,
    overrides: dict,
    extra: dict[str, list[str]] | None = None,
) -> dict[str, list[str]]:
    """The command line of each stage for one configuration (``overrides``: the knob's options;
    ``extra``: options every configuration passes to a stage, e.g. shorter cunerf training)."""
    extra = extra or {}
    scan_args = [scan] if scan else []
    window_args = ["--window", window] if window else []
    splat = ["--preset", preset, *extra.get("splat", []), *overrides.get("splat", [])]
    return {
        "preprocess": [
            "preprocess",
            *scan_args,
            "-o",
            str(work),
            "--preset",
            preset,
            *window_args,
            *extra.get("preprocess", []),
            *overrides.get("preprocess", []),
        ],
        "cunerf": ["cunerf", str(work), "--preset", preset, *extra.get("cunerf", []), *overrides.get("cunerf", [])],
        "export": ["export", str(work), "--preset", preset, *extra.get("export", []), *overrides.get("export", [])],
        "splat": ["splat", str(work), *splat],
        "splat-random": ["splat", str(work), *splat, "--init", "random", "--name", "random"],
        "eval": ["eval", str(work), "--turntable-frames", "0"],
    }


def default_values(knob: str, base) -> list:
    """The knob's values around the preset's ``base``: every other choice, or multiples of a number
    (none for a budget the preset leaves open, nor multiples of 0)."""
    if KNOBS[knob].choices:
        return [choice for choice in KNOBS[knob].choices if choice != base]
    if not base:  # a budget the preset leaves open, or CuNeRF's iterations where it trains none
        return []
    return [max(1, round(base * factor)) for factor in KNOBS[knob].factors]


def configurations(knobs: list[str], base: dict, values: dict[str, list] | None = None) -> list[tuple[str, dict]]:
    configs = [("preset", {})]
    for name in knobs:
        knob = KNOBS[name]
        for value in dict.fromkeys((values or {}).get(name) or default_values(name, base[name])):  # in order, once each
            if value != base[name]:
                configs.append((f"{name}={value}", {knob.stage: knob.arguments(value)}))
    return configs


def run_configuration(
    name: str,
    commands: dict[str, list[str]],
    keys: dict[str, tuple],
    work: Path,
    done: dict[tuple, Path],
    jobs: JobServerOnDemand,
) -> None:
    """Run the stages in order. A stage whose command chain (``keys``) an earlier configuration
    ran is hard-linked from it; one already here from the same chain is kept; anything else is
    (re)done, with every stage after it, through the job server (a fresh process that does not
    spend 2–5 s importing torch again)."""
    record = work / ".trade"
    record.mkdir(parents=True, exist_ok=True)
    stale = False
    for stage in STAGES:
        key, marker = keys[stage], record / f"{stage}.json"
        here = is_complete(work / stage) and marker.is_file() and json.loads(marker.read_text()) == list(map(list, key))
        if here and not stale:
            done.setdefault(key, work / stage)
            continue
        stale = True
        if stage != "eval" and key in done:
            link_stage(done[key], work, stage, key)
            print(f"  {name}: {stage} reused from {done[key].parent.name}", flush=True)
        else:
            if (work / stage).exists():
                shutil.rmtree(work / stage)
            print(f"  {name}: cubecloud {' '.join(commands[stage])}", flush=True)
            # --force: a run interrupted earlier restarts, so its recorded time is whole.
            subprocess.run([*jobs.command(), *commands[stage], "--force", "-q"], check=True)
            marker.write_text(json.dumps(list(map(list, key))))
        done[key] = work / stage


def link_stage(source: Path, work: Path, stage: str, key: tuple) -> None:
    """Hard-link a finished stage into ``work`` (replacing what is there) and mark it as made by
    the command chain ``key``, so later runs of the study keep it."""
    if (work / stage).exists():
        shutil.rmtree(work / stage)
    shutil.copytree(source, work / stage, copy_function=os.link)
    (work / ".trade").mkdir(parents=True, exist_ok=True)
    (work / ".trade" / f"{stage}.json").write_text(json.dumps(list(map(list, key))))


def base_mismatches(base: Path, scan: str | None, preset: str, window: str | None) -> list[str]:
    """Why a finished `cubecloud run` work directory is not the study's base configuration
    (none: it is). It must hold every stage, run on the same scan with the preset's parameters."""
    from cubecloud_cli.core.artifacts import read_manifest, sha256_of_path
    from cubecloud_cli.presets import PRESETS, resolve_cunerf
    from cubecloud_cli.sample_data import sample_ct_path

    missing = [stage for stage in STAGES if not is_complete(base / stage)]
    if missing:
        return [f"stages not complete: {', '.join(missing)}"]
    manifests = {stage: read_manifest(base / stage) for stage in STAGES}
    wanted = {
        stage: dict(PRESETS[key][preset])
        for stage, key in (
            ("preprocess", "preprocess"),
            ("export", "export"),
            ("splat", "splat"),
            ("splat-random", "splat"),
        )
    }
    wanted["cunerf"] = resolve_cunerf(preset, None, {})
    if window:
        wanted["preprocess"]["window"] = window
    wanted["splat"]["init"], wanted["splat-random"]["init"] = "cloud", "random"
    problems = [
        f"{stage} {key} is {manifests[stage]['params'].get(key)!r}, the preset's is {value!r}"
        for stage, params in wanted.items()
        for key, value in params.items()
        if manifests[stage]["params"].get(key) != value
    ]
    scan_sha = sha256_of_path(Path(scan) if scan else sample_ct_path())
    if scan_sha not in manifests["preprocess"]["inputs"].values():
        problems.append(f"preprocess ran on another scan ({', '.join(manifests['preprocess']['inputs'])})")
    return problems


def seed_from_base(base: Path, work: Path, keys: dict[str, tuple]) -> None:
    """Hard-link a finished run's stages into the base configuration's work directory and mark
    them done, so the study keeps them (and their recorded wall times) instead of rerunning."""
    for stage in STAGES:
        link_stage(base / stage, work, stage, keys[stage])


def chain_keys(commands: dict[str, list[str]]) -> dict[str, tuple]:
    """Per stage, the commands of it and every stage before it: equal keys, equal outputs."""
    keys, chain = {}, ()
    for stage in STAGES:
        chain = chain + (tuple(commands[stage]),)
        keys[stage] = chain
    return keys


def collect(name: str, work: Path) -> list[dict]:
    seconds = {
        stage: json.loads((work / stage / "manifest.json").read_text())["timings_s"]["total"] for stage in STAGES
    }
    results = json.loads((work / "eval" / "metrics.json").read_text())["results"]
    rows = []
    for run in ("splat", "splat-random"):
        result = results[run]
        by_magnification = (result.get("novel") or {}).get("by_magnification", {})
        rows.append(
            {
                "config": name,
                "method": result["method_name"],
                "novel_psnr": result.get("novel_psnr"),
                "novel_ssim": result.get("novel_ssim"),
                "novel_psnr_0.5x": by_magnification.get("0.5", {}).get("psnr"),
                "novel_psnr_2x": by_magnification.get("2", {}).get("psnr"),
                "psnr": result["psnr"],
                "ssim": result["ssim"],
                "psnr_foreground": result["psnr_foreground"],
                "gaussians": result["gaussians"],
                **{f"{stage}_s": round(seconds[stage], 1) for stage in ("preprocess", "cunerf", "export")},
                "splat_s": round(seconds[run], 1),
                # From the scan to this model: the shared stages and its own training.
                "pipeline_s": round(seconds["preprocess"] + seconds["cunerf"] + seconds["export"] + seconds[run], 1),
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scan", help="a CT scan (default: the bundled abdomen CT)")
    parser.add_argument("--window", help="CT window for preprocess, e.g. lung for a chest CT")
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--knobs", default=",".join(KNOBS), help="comma-separated subset of: " + ", ".join(KNOBS))
    parser.add_argument(
        "--values",
        action="append",
        default=[],
        metavar="KNOB=V1,V2",
        help="values of a knob instead of its defaults, e.g. iterations=500,1000 (repeatable)",
    )
    parser.add_argument(
        "--stage-options",
        action="append",
        default=[],
        metavar="STAGE=OPTIONS",
        help='options every configuration passes to a stage, e.g. "cunerf=--iterations 1000"',
    )
    parser.add_argument(
        "--include",
        action="append",
        default=[],
        metavar="NAME=WORK",
        help="add a finished `cubecloud run` work directory as a configuration, e.g. "
        "balanced=work-balanced from `cubecloud run -o work-balanced --preset balanced` (repeatable)",
    )
    parser.add_argument(
        "--base",
        type=Path,
        metavar="WORK",
        help="a finished `cubecloud run -o WORK --preset PRESET` on the same scan: its stages become "
        "the preset configuration (hard-linked, times kept) instead of being rerun",
    )
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    knobs = [k.strip() for k in args.knobs.split(",") if k.strip()]
    values = {key: text.split(",") for key, text in (item.split("=", 1) for item in args.values)}
    extra = {stage: text.split() for stage, text in (item.split("=", 1) for item in args.stage_options)}
    unknown = (set(knobs) | set(values)) - set(KNOBS)
    if set(values) - set(knobs):
        parser.error(f"--values for knobs not in --knobs: {', '.join(sorted(set(values) - set(knobs)))}")
    if unknown or set(extra) - set(STAGES):
        parser.error(f"unknown knobs or stages: {', '.join(sorted(unknown | (set(extra) - set(STAGES))))}")
    try:
        values = {key: [KNOBS[key].parse(v) for v in texts] for key, texts in values.items()}
    except ValueError as exc:
        parser.error(f"--values: {exc}")
    wrong = [
        f"{key}={v}"
        for key, texts in values.items()
        for v in texts
        if KNOBS[key].choices and v not in KNOBS[key].choices
    ]
    if wrong:
        parser.error(f"--values not among the knob's choices: {', '.join(wrong)}")

    if args.base and extra:
        parser.error("--base with --stage-options: the base run has the preset's own options; drop one of them")
    if args.base and (problems := base_mismatches(args.base, args.scan, args.preset, args.window)):
        parser.error(f"--base {args.base} is not a `--preset {args.preset}` run of this scan: {'; '.join(problems)}")

    args.out.mkdir(parents=True, exist_ok=True)
    done: dict[tuple, Path] = {}
    rows = []
    base = preset_values(args.preset, extra)
    with JobServerOnDemand(CUBECLOUD_JOBS) as jobs:
        for name, overrides in configurations(knobs, base, values):
            work = args.out / name.replace("=", "-")
            commands = stage_commands(args.scan, work, args.preset, args.window, overrides, extra)
            keys = chain_keys(stage_commands(args.scan, Path("WORK"), args.preset, args.window, overrides, extra))
            if name == "preset" and args.base:
                seed_from_base(args.base, work, keys)
            run_configuration(name, commands, keys, work, done, jobs)
            rows += collect(name, work)
    for item in args.include:
        name, _, directory = item.partition("=")
        missing = [stage for stage in STAGES if not is_complete(Path(directory) / stage)]
        if not name or missing:
            parser.error(
                f"--include {item}: needs NAME=WORK with every stage complete (missing: {', '.join(missing) or '-'})"
            )
        rows += collect(name, Path(directory))

    with open(args.out / "trade.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (args.out / "trade.json").write_text(json.dumps(rows, indent=2))
    lines = [
        "| config | method | pipeline s | cunerf s | export s | splat s | novel PSNR | novel SSIM | novel 0.5× | "
        "novel 2× | held-out PSNR | held-out SSIM | Gaussians |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['config']} | {r['method']} | {r['pipeline_s']:.0f} | {r['cunerf_s']:.0f} | {r['export_s']:.0f} | "
        f"{r['splat_s']:.0f} | {_number(r['novel_psnr'])} | {_number(r['novel_ssim'], 4)} | {_number(r['novel_psnr_0.5x'])} | "
        f"{_number(r['novel_psnr_2x'])} | {r['psnr']:.2f} | {r['ssim']:.4f} | {r['gaussians']} |"
        for r in rows
    ]
    (args.out / "trade.md").write_text("\n".join(lines) + "\n")
    write_plot(rows, args.out / "time_vs_psnr.svg")
    print("\n".join(lines))


def write_plot(rows: list[dict], path: Path) -> None:
    """Novel-view PSNR against pipeline time, one point per configuration and method, each named."""
    # Imported here: the eval package brings torch (3 s), which a refused or --help run never needs.
    from cubecloud_cli.eval.figures import line_plot_svg

    scored = [r for r in rows if isinstance(r["novel_psnr"], (int, float))]
    series = []
    labels = {}
    for method in dict.fromkeys(r["method"] for r in scored):
        mine = [r for r in scored if r["method"] == method]
        series.append((method, [r["pipeline_s"] for r in mine], [r["novel_psnr"] for r in mine]))
        labels[method] = [r["config"] for r in mine]
    if series:
        path.write_text(
            line_plot_svg(
                series,
                "novel-view PSNR (0.75–1.33×) against pipeline time",
                "pipeline time from the scan (s)",
                "novel-view PSNR vs the volume's renders (dB)",
                markers_only=True,
                point_labels=labels,
                size=(960, 600),
            )
        )


def _number(value, digits: int = 2) -> str:
    return f"{value:.{digits}f}" if isinstance(value, (int, float)) else "–"


if __name__ == "__main__":
    main()
