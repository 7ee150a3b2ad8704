"""`cubecloud cohort` on Snakemake: the config the shipped Snakefile reads, the Snakemake command
(local cores, or any executor plugin or profile), a lock against two cohorts in one folder, and
what each scan's logs say when it failed."""

from __future__ import annotations

import json
import os
import shlex
import signal
import socket
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from cubecloud_cli.cohort.scans import CohortScan
from cubecloud_cli.core.errors import CubecloudError

SNAKEFILE = Path(__file__).with_name("Snakefile")
STAGES = ("preprocess", "cunerf", "export", "splat", "splat-random", "eval")
# What a scheduler reserves for each stage's job: cunerf and splat train, and eval renders, on every
# thread they get (a one-thread eval left a core idle); preprocess is one thread of reading. Memory
# is the fast preset's peak (under 1 GB) with room for the balanced one.
STAGE_RESOURCES = {
    "preprocess": {"threads": 1, "mem_mb": 2000},
    "cunerf": {"threads": 2, "mem_mb": 4000},
    "export": {"threads": 2, "mem_mb": 4000},
    "splat": {"threads": 2, "mem_mb": 4000},
    "splat-random": {"threads": 2, "mem_mb": 4000},
    "eval": {"threads": 2, "mem_mb": 3000},
}
COHORT_DIR = "cohort"


@dataclass(frozen=True)
class EngineOptions:
    """How Snakemake runs the jobs: ``cores`` locally, or through ``executor`` / ``profile``."""

    cores: int = 2
    executor: str | None = None
    profile: Path | None = None
    jobs: int | None = None  # jobs at once through an executor (Snakemake's --jobs)

    @property
    def on_this_machine(self) -> bool:
        """Every job runs here, so one job server can start them all (a profile may name an executor)."""
        return self.executor is None and self.profile is None


def require_snakemake() -> None:
    try:
        import snakemake  # noqa: F401
    except ImportError:
        raise CubecloudError(
            "cubecloud cohort runs on Snakemake, which is not installed: pip install 'cubecloud[cohort]'"
        ) from None


def per_scan_options(scan: CohortScan) -> list[str]:
    options = []
    if scan.window:
        options += ["--window", scan.window]
    if scan.modality:
        options += ["--modality", scan.modality]
    return options


PLAIN_COMMAND = [sys.executable, "-m", "cubecloud_cli"]  # the same Python, on every node of a shared filesystem


def write_config(
    out: Path, scans: list[CohortScan], run_options: list[str], command: list[str] = PLAIN_COMMAND
) -> Path:
    """OUT/cohort/config.json, written whole before it replaces the old one. ``command`` is how a
    job starts cubecloud: plainly, or through this machine's job server (job_server.py)."""
    directory = Path(out) / COHORT_DIR
    directory.mkdir(parents=True, exist_ok=True)
    config = {
        "scans": {scan.id: {"scan": str(scan.scan), "options": per_scan_options(scan)} for scan in scans},
        "run_options": run_options,
        "cubecloud": list(command),
        "resources": STAGE_RESOURCES,
    }
    partial = directory / "config.json.partial"
    partial.write_text(json.dumps(config, indent=2) + "\n")
    partial.replace(directory / "config.json")
    return directory / "config.json"


def snakemake_command(out: Path, config: Path, engine: EngineOptions) -> list[str]:
    command = [
        sys.executable, "-m", "snakemake", "--snakefile", str(SNAKEFILE), "--directory", str(out),
        "--configfile", str(config),
        "--keep-going",  # a bad scan fails its own jobs only
        "--rerun-incomplete",  # a job killed mid-way runs again, and the stage resumes its saved work
        "--rerun-triggers", "mtime",  # the stages themselves decide what is current
        "--nolock",  # our own lock (cohort_lock) knows a dead cohort from a running one
        "--quiet", "rules", "host",  # progress and errors; each job's detail is in its log
    ]  # fmt: skip
    if engine.profile is not None:
        command += ["--profile", str(engine.profile)]
    if engine.executor is not None:
        command += ["--executor", engine.executor, "--jobs", str(engine.jobs or 100)]
    else:
        command += ["--cores", str(engine.cores)]
    return command


class cohort_lock:
    """OUT/cohort/lock holds the host and PID of the cohort running there; a lock whose process is
    gone (a killed cohort) is taken over, a live one refused."""

    def __init__(self, out: Path):
        self.path = Path(out) / COHORT_DIR / "lock"

    def __enter__(self) -> "cohort_lock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.is_file():
            host, _, pid = self.path.read_text().strip().partition(" ")
            if host == socket.gethostname() and pid.isdigit() and _alive(int(pid)):
                raise CubecloudError(
                    f"another cohort (process {pid}) is running in {self.path.parent.parent}: wait for it or stop it"
                )
        self.path.write_text(f"{socket.gethostname()} {os.getpid()}\n")
        return self

    def __exit__(self, *exc) -> None:
        self.path.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def run_snakemake(out: Path, config: Path, engine: EngineOptions) -> int:
    """Snakemake's exit code; its progress goes to the terminal."""
    command = snakemake_command(out, config, engine)
    (Path(out) / COHORT_DIR / "snakemake_command.txt").write_text(shlex.join(command) + "\n")
    return wait_passing_on_interrupts(subprocess.Popen(command))


SNAKEMAKE_STOP_SECONDS = 120  # for it to stop its jobs (each saves its checkpoint) before it is killed


def wait_passing_on_interrupts(process: subprocess.Popen) -> int:
    """``process``'s exit code. Ctrl-C or SIGTERM here (a KeyboardInterrupt: cli/common.py) is
    passed on to it as SIGINT, on which Snakemake stops its jobs, and waited for: a terminal's
    Ctrl-C reached it already, a scheduler's SIGTERM reached this process alone."""
    try:
        return process.wait()
    except KeyboardInterrupt:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=SNAKEMAKE_STOP_SECONDS)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        raise


def completed_stages(out: Path, scan_ids: list[str]) -> dict[str, list[str]]:
    """The stage folders with a manifest in each scan's work directory (what an interrupted cohort keeps)."""
    return {
        scan_id: [p.parent.name for p in sorted((Path(out) / scan_id).glob("*/manifest.json"))] for scan_id in scan_ids
    }


def failure(out: Path, scan_id: str) -> str:
    """Why a scan has no finished eval: the one-line error of the first stage that did not finish,
    from its log (or the log's last line, or that the stage never ran)."""
    logs = Path(out) / COHORT_DIR / "logs" / scan_id
    for stage in STAGES:
        if (Path(out) / scan_id / stage / "manifest.json").is_file():
            continue
        log = logs / f"{stage}.log"
        if not log.is_file():
            return f"{stage} did not run (the cohort was stopped before it)"
        lines = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
        errors = [line for line in lines if line.startswith("error: ")]
        if errors:
            return f"{stage}: {errors[-1][len('error: ') :]}"
        return f"{stage} did not finish: {lines[-1] if lines else 'its log is empty'} ({log})"
    return "no finished eval"
