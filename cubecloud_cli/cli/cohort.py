"""`cubecloud cohort`: the whole pipeline over many scans on Snakemake, then the cohort report."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Optional

import typer

from cubecloud_cli.cli.common import (
    DeviceOption,
    FitOption,
    HuMaxOption,
    HuMinOption,
    InterpolationOption,
    ModalityOption,
    PercentilesOption,
    PresetOption,
    QuietOption,
    ResolutionOption,
    SeriesOption,
    SizeOption,
    SpacingOption,
    ViewOption,
    ViewsOption,
    VolumeIndexOption,
    WindowOption,
    configure_logging,
    reports_errors,
)
from cubecloud_cli.cli.options import settings_option
from cubecloud_cli.cohort.job_server import JobEntry
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.cunerf import CunerfSettings
from cubecloud_cli.presets import DEFAULT_PRESET
from cubecloud_cli.splat.settings import SplatSettings

log = logging.getLogger("cubecloud")

# What the cohort's job server on this machine runs: this command line, with the stages and eval's
# comparison imported once ahead of the jobs (torch, numba), which the command line itself imports
# only when a stage runs.
CUBECLOUD_JOBS = JobEntry(
    program="cubecloud",
    main="cubecloud_cli.cli:main",
    preload=("cubecloud_cli.cli", "cubecloud_cli.eval.compare", "cubecloud_cli.pipeline.table"),
)

ScansArgument = Annotated[
    Optional[list[Path]],
    typer.Argument(
        help="Scan files, DICOM series folders, or folders of them (each NIfTI file and DICOM series folder in it).",
        show_default=False,
    ),
]
OutOption = Annotated[
    Path, typer.Option("--output", "-o", help="Cohort folder: OUT/<id>/ per scan, OUT/cohort/ the report.")
]
ScansCsvOption = Annotated[
    Optional[Path],
    typer.Option(
        "--scans", help="A CSV with columns id,scan (and optionally window, modality per scan).", show_default=False
    ),
]
CoresOption = Annotated[int, typer.Option("--cores", help="CPU cores for the jobs run on this machine.")]
ExecutorOption = Annotated[
    Optional[str],
    typer.Option("--executor", help="A Snakemake executor plugin (slurm, lsf, cluster-generic, ...) instead of this machine.",
                 show_default=False),
]  # fmt: skip
ProfileOption = Annotated[
    Optional[Path],
    typer.Option("--profile", help="A Snakemake profile folder (e.g. examples/slurm/).", show_default=False),
]
JobsOption = Annotated[
    Optional[int],
    typer.Option("--jobs", help="Jobs queued at once through --executor (default 100).", show_default=False),
]


@reports_errors
def cohort_command(
    scans: ScansArgument = None,
    output: OutOption = Path("cohort"),
    scans_csv: ScansCsvOption = None,
    preset: PresetOption = DEFAULT_PRESET,
    size: SizeOption = None,
    fit: FitOption = None,
    window: WindowOption = None,
    hu_min: HuMinOption = None,
    hu_max: HuMaxOption = None,
    modality: ModalityOption = None,
    percentiles: PercentilesOption = None,
    interpolation: InterpolationOption = None,
    spacing: SpacingOption = None,
    volume_index: VolumeIndexOption = None,
    series: SeriesOption = None,
    cunerf_iterations: Annotated[
        Optional[int], settings_option(CunerfSettings, "iterations", "--cunerf-iterations")
    ] = None,
    splat_iterations: Annotated[
        Optional[int], settings_option(SplatSettings, "iterations", "--splat-iterations")
    ] = None,
    views: ViewsOption = None,
    resolution: ResolutionOption = None,
    view: ViewOption = None,
    device: DeviceOption = None,
    cores: CoresOption = 2,
    executor: ExecutorOption = None,
    profile: ProfileOption = None,
    jobs: JobsOption = None,
    quiet: QuietOption = False,
) -> None:
    """Run the whole pipeline on every scan of a cohort, then report the cohort with paired statistics.

    Each scan gets OUT/<id>/, a normal `cubecloud run` work directory (every other command works on it). The stages run as Snakemake jobs: on this machine with --cores, or on a cluster through --executor or --profile. A stopped cohort resumes where it stopped; a bad scan fails only its own jobs. OUT/cohort/ holds report.md (Table I over the cohort, Cube-Cloud − random init per scan with a bootstrap interval and the Wilcoxon p), per_scan.csv, cohort.json and each job's log. --preset and the run options apply to every scan.

    Examples:

      cubecloud cohort scans/ -o out --cores 2

      cubecloud cohort --scans cohort.csv -o out --preset balanced

      cubecloud cohort scans/ -o out --profile examples/slurm
    """
    from cubecloud_cli.cohort.workflow import run_cohort, scan_list

    configure_logging(quiet)
    given = {"size": size, "fit": fit, "window": window, "hu_min": hu_min, "hu_max": hu_max, "modality": modality,
             "percentiles": percentiles, "interpolation": interpolation, "spacing": spacing,
             "volume_index": volume_index, "series": series,
             "cunerf_iterations": cunerf_iterations, "splat_iterations": splat_iterations, "views": views,
             "resolution": resolution, "view": view, "device": device}  # fmt: skip
    run_options = ["--preset", preset]
    for name, value in given.items():
        if value is not None:
            run_options += [f"--{name.replace('_', '-')}", str(value)]
    if cores < 1:
        raise CubecloudError(f"--cores {cores} must be at least 1")
    run_cohort(scan_list(scans or [], scans_csv), output, run_options, CUBECLOUD_JOBS, cores, executor, profile, jobs)
