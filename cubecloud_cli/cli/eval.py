"""`cubecloud eval`: options and the call into cubecloud_cli.eval."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Optional

import typer

from cubecloud_cli.cli.common import (
    DeviceOption,
    ForceOption,
    QuietOption,
    ThreadsOption,
    configure_logging,
    reports_errors,
    runtime_from_options,
)
from cubecloud_cli.cli.options import build_settings, settings_option
from cubecloud_cli.cli.progress_bar import stage_bar
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.runtime import Runtime
from cubecloud_cli.eval.settings import EvalSettings

log = logging.getLogger("cubecloud")

WorkArgument = Annotated[
    Optional[Path], typer.Argument(help="Work directory with splat runs (splat/, splat-random/, ...).")
]
CompareOption = Annotated[
    Optional[list[Path]],
    typer.Option(
        "--compare",
        metavar="WORK",
        help="Build one table across these work directories (repeat the option), WORK included; each is evaluated first when its eval/ is missing or older than its runs (all with --force).",
    ),
]
OutputOption = Annotated[
    Path, typer.Option("--output", help="Where --compare writes comparison.md and comparison.json.")
]
FramesOption = Annotated[Optional[int], settings_option(EvalSettings, "turntable_frames")]
TurntableResolutionOption = Annotated[Optional[int], settings_option(EvalSettings, "turntable_resolution")]


def describe_eval(manifest: dict) -> str:
    parts = []
    for row, scores in manifest["metrics"].items():
        if isinstance(scores, dict) and "psnr" in scores:
            psnr = scores["psnr"]
            parts.append(f"{row} {psnr:.2f} dB" if isinstance(psnr, float) else f"{row} {psnr} dB")
    return ", ".join(parts)


@reports_errors
def eval_command(
    work: WorkArgument = None,
    compare: CompareOption = None,
    output: OutputOption = Path("comparison"),
    turntable_frames: FramesOption = None,
    turntable_resolution: TurntableResolutionOption = None,
    device: DeviceOption = None,
    threads: ThreadsOption = None,
    force: ForceOption = False,
    quiet: QuietOption = False,
) -> None:
    """Score every splat run in WORK, and CuNeRF, on the held-out views against the reference renders of the volume.

    Writes WORK/eval/: metrics.json ({"protocol", "results": {run: psnr, ssim, mse (mean and std), foreground variants, ms per frame, Gaussians, MB}, "paper"}), per_view.csv, and report.md in the paper's Table I layout with the pictures: per held-out view reference | render | error grids (views/), a turntable GIF per run, and the PSNR-during-training plot.

    Examples:

      cubecloud eval work

      cubecloud eval work --turntable-frames 0            # numbers and grids only

      cubecloud eval --compare work-fast --compare work-balanced --output sweep
    """
    configure_logging(quiet)
    if work is None and not compare:
        raise CubecloudError(
            "give a work directory (cubecloud eval work), or work directories to compare with --compare"
        )
    options = {"turntable_frames": turntable_frames, "turntable_resolution": turntable_resolution}
    settings = build_settings(EvalSettings, None, options)
    from cubecloud_cli.eval.compare import compare_works  # torch: imported when the stage runs
    from cubecloud_cli.eval.stage import eval_is_current

    runtime = runtime_from_options(device, threads)
    if not compare:
        manifest = _evaluate(work, settings, force, runtime)
        log.info(f"wrote {Path(work) / 'eval'}: {describe_eval(manifest)}")
        return
    # A comparison evaluates each directory whose eval is missing or older than its runs (all of
    # them with --force), once, in the order given.
    targets, seen = [], set()
    for target in ([work] if work is not None else []) + list(compare):
        if Path(target).resolve() not in seen:
            seen.add(Path(target).resolve())
            targets.append(Path(target))
    for target in targets:
        if force or not eval_is_current(target):
            manifest = _evaluate(target, settings, True, runtime)
            log.info(f"wrote {target / 'eval'}: {describe_eval(manifest)}")
    table = compare_works(targets, output)
    log.info(f"wrote {output / 'comparison.md'}:\n{table}")


def _evaluate(work: Path, settings: EvalSettings, force: bool, runtime: Runtime) -> dict:
    from cubecloud_cli.eval.stage import evaluate_work

    with stage_bar("eval") as on_progress:
        return evaluate_work(work, settings, force=force, runtime=runtime, on_progress=on_progress)
