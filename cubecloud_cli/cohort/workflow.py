"""A cohort from its scans to its report: the scan list, the Snakemake run, the report."""

from __future__ import annotations

import logging
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from cubecloud_cli.cohort.engine import (
    PLAIN_COMMAND,
    EngineOptions,
    cohort_lock,
    completed_stages,
    failure,
    require_snakemake,
    run_snakemake,
    write_config,
)
from cubecloud_cli.cohort.job_server import JobEntry, job_server
from cubecloud_cli.cohort.report import scan_record, write_cohort_report
from cubecloud_cli.cohort.scans import CohortScan, scans_from_arguments, scans_from_csv
from cubecloud_cli.core.errors import CubecloudError

log = logging.getLogger("cubecloud")


def scan_list(arguments: list[Path], csv_path: Path | None) -> list[CohortScan]:
    if arguments and csv_path is not None:
        raise CubecloudError("give the scans either as arguments or as --scans CSV, not both")
    return scans_from_csv(csv_path) if csv_path is not None else scans_from_arguments(arguments)


@contextmanager
def job_launcher(engine: EngineOptions, entry: JobEntry) -> Iterator[list[str]]:
    """How jobs start cubecloud: through a job server running ``entry`` when they all run on this
    machine (a job then starts in 0.1 s instead of 2–3 s), plainly when an executor sends them
    elsewhere."""
    if engine.on_this_machine:
        with job_server(entry) as command:
            yield command
    else:
        yield PLAIN_COMMAND


def interrupted_message(out: Path, scans: list[CohortScan]) -> str:
    """What an interrupted cohort keeps: the stages complete in each scan, found on disk."""
    done = completed_stages(out, [scan.id for scan in scans])
    count = sum(len(stages) for stages in done.values())
    finished = [scan_id for scan_id, stages in done.items() if "eval" in stages]
    return (
        f"interrupted: {count} stages are complete and kept ({len(finished)} of {len(scans)} scans finished); "
        "run the same cohort command again to go on from them"
    )


def run_cohort(
    scans: list[CohortScan],
    out: Path,
    run_options: list[str],
    entry: JobEntry,
    cores: int = 2,
    executor: str | None = None,
    profile: Path | None = None,
    jobs: int | None = None,
) -> Path:
    """Run every scan's pipeline, then write OUT/cohort/. ``entry`` is what a job server on this
    machine runs (cubecloud's own command line, passed in by it). A failed scan is reported, and the
    command ends with a one-line error naming the failures once the report is written."""
    require_snakemake()
    out = Path(out).resolve()
    if profile is not None and not Path(profile).is_dir():
        raise CubecloudError(f"--profile {profile} is not a folder: give a Snakemake profile folder (config.yaml)")
    engine = EngineOptions(cores, executor, Path(profile) if profile else None, jobs)
    with cohort_lock(out):
        with job_launcher(engine, entry) as command:
            config = write_config(out, scans, run_options, command)
            log.info(f"cohort of {len(scans)} scans in {out}: {len(scans) * 6} jobs on Snakemake")
            try:
                code = run_snakemake(out, config, engine)
            except KeyboardInterrupt:
                raise KeyboardInterrupt(interrupted_message(out, scans)) from None
        records = []
        for scan in scans:
            finished = (out / scan.id / "eval" / "manifest.json").is_file()
            records.append(
                scan_record(scan.id, str(scan.scan), out / scan.id, None if finished else failure(out, scan.id))
            )
        setup = "Options for every scan: `" + " ".join(run_options) + "`."
        report = write_cohort_report(out, records, setup)
    failed = [r for r in records if r["status"] != "done"]
    log.info(f"cohort report: {report}")
    if failed:
        first = failed[0]
        raise CubecloudError(
            f"{len(failed)} of {len(scans)} scans failed ({first['id']}: {first['error']}); "
            f"the report lists them: {report}"
        )
    if code != 0:
        raise CubecloudError(f"Snakemake stopped with exit code {code}: see its output above and {out / 'cohort'}")
    return report
