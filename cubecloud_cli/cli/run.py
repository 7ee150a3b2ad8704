"""`cubecloud run`: the whole pipeline with one command."""

from __future__ import annotations

import logging
from pathlib import Path

from cubecloud_cli.cli.preprocess import run_preprocess_with_progress, scan_command
from cubecloud_cli.pipeline import run_pipeline
from cubecloud_cli.preprocess import PreprocessSettings

log = logging.getLogger("cubecloud")


def _run(scan: Path, output: Path, settings: PreprocessSettings, force: bool) -> None:
    outcomes = run_pipeline(scan, output, settings, force=force, run_preprocess=run_preprocess_with_progress)
    for outcome in outcomes:
        when = f"{outcome.seconds:7.1f} s" if outcome.status == "ran" else "skipped (already complete)"
        log.info(f"  {outcome.stage:<12} {when}")
    log.info(f"  {'total':<12} {sum(o.seconds for o in outcomes):7.1f} s   results in {output}")


run_command = scan_command(
    _run,
    """Run every stage on a scan, skipping stages already complete with the same settings.

    Takes the options of `cubecloud preprocess`. Stages run today: preprocess (cunerf, export, splat and eval join as they land).

    Examples:

      cubecloud run -o work            # bundled CT, preset fast

      cubecloud run scan.nii.gz -o work --preset balanced
    """,
)
