"""A one-node SLURM cluster on localhost from Debian's packages (munge, slurmctld, slurmd,
slurm-client), for the cohort's cluster test. `.ci/run` installs the packages; this starts the
daemons in a scratch folder and stops them after.

Two settings matter, as docs/cohort.md says:

- No accounting (no slurmdbd): the SLURM executor plugin must poll with `squeue`, and slurm.conf's
  MinJobAge must be at least 3 × its `slurm-init-seconds-before-status-checks`, or a finished job
  leaves the queue before the plugin has seen it end.
- slurm.conf at /etc/slurm/slurm.conf: the plugin's job step drops every SLURM_* variable before
  its inner `srun`, SLURM_CONF too, so `srun` must find the file where it looks by default. This
  is written only where there is none, and removed after.
"""

from __future__ import annotations

import os
import secrets
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

SYSTEM_CONFIG = Path("/etc/slurm/slurm.conf")
DAEMONS = ("munged", "slurmctld", "slurmd")
CLIENTS = ("sbatch", "squeue", "scancel", "srun", "sinfo")
# The plugin checks first after this many seconds, then waits 10 s longer each time no job has
# ended: a job of this machine (Python's and torch's start, twice, and a tiny stage) ends in
# 12-16 s and is seen at the second check, 20 s in.
INIT_SECONDS_BEFORE_STATUS_CHECKS = 5
MIN_JOB_AGE = 30  # over the plugin's floor of 3 × the above


def unavailable_because() -> str | None:
    """Why no cluster can be started here, or None when one can."""
    missing = [name for name in DAEMONS + CLIENTS if shutil.which(name) is None]
    if missing:
        return f"SLURM is not installed ({', '.join(missing)} missing; apt-get install slurmctld slurmd slurm-client munge)"
    if os.geteuid() != 0:
        return "slurmd starts jobs as their user, which needs root"
    if SYSTEM_CONFIG.exists() and "cubecloud test cluster" not in SYSTEM_CONFIG.read_text(errors="replace"):
        return f"{SYSTEM_CONFIG} belongs to a real cluster; this test starts its own only where there is none"
    return None


def _free_ports(count: int) -> list[int]:
    sockets = [socket.socket() for _ in range(count)]
    for sock in sockets:
        sock.bind(("127.0.0.1", 0))
    ports = [sock.getsockname()[1] for sock in sockets]
    for sock in sockets:
        sock.close()
    return ports


def slurm_conf(folder: Path, cpus: int, memory_mb: int) -> str:
    controller_port, node_port = _free_ports(2)
    return f"""# cubecloud test cluster (tests/slurm_cluster.py): removed when the test ends
ClusterName=cubecloud-test
SlurmctldHost=localhost(127.0.0.1)
SlurmUser=root
SlurmctldPort={controller_port}
SlurmdPort={node_port}
AuthType=auth/munge
AuthInfo=socket={folder}/munge.socket
StateSaveLocation={folder}/state
SlurmdSpoolDir={folder}/spool
SlurmctldPidFile={folder}/slurmctld.pid
SlurmdPidFile={folder}/slurmd.pid
SlurmctldLogFile={folder}/slurmctld.log
SlurmdLogFile={folder}/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/filetxt
JobCompLoc={folder}/jobs.txt
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
SchedulerType=sched/backfill
ReturnToService=2
SlurmdParameters=config_overrides
MinJobAge={MIN_JOB_AGE}
KillWait=30
MpiDefault=none
NodeName=localhost NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={memory_mb} State=UNKNOWN
PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP
"""


class Cluster:
    """The running cluster: its scratch folder and the completed-jobs log SLURM keeps there."""

    def __init__(self, folder: Path):
        self.folder = folder

    def completed_jobs(self) -> list[dict[str, str]]:
        """One record per finished job (SLURM's jobcomp/filetxt log): JobId, JobState, Name, ..."""
        path = self.folder / "jobs.txt"
        if not path.exists():
            return []
        return [
            dict(field.split("=", 1) for field in line.split() if "=" in field)
            for line in path.read_text().splitlines()
        ]

    def queued_jobs(self) -> list[str]:
        output = subprocess.run(["squeue", "--noheader", "--format", "%i"], capture_output=True, text=True, check=True)
        return output.stdout.split()


def _wait_until_idle(folder: Path, deadline_seconds: float) -> None:
    deadline = time.monotonic() + deadline_seconds
    state = ""
    while time.monotonic() < deadline:
        probe = subprocess.run(["sinfo", "--noheader", "--format", "%T"], capture_output=True, text=True)
        state = probe.stdout.strip()
        if probe.returncode == 0 and state == "idle":
            return
        time.sleep(0.5)
    logs = "\n".join(
        (folder / name).read_text(errors="replace")[-1500:]
        for name in ("slurmctld.log", "slurmd.log")
        if (folder / name).exists()
    )
    raise RuntimeError(f"the test cluster's node never came up (sinfo: {state!r}):\n{logs}")


@contextmanager
def local_cluster(folder: Path, cpus: int = 3, memory_mb: int = 8000) -> Iterator[Cluster]:
    """munge, slurmctld and slurmd on localhost, their files in ``folder``. The node offers
    ``cpus`` whatever this machine has (config_overrides): 3 lets a 1-thread job run beside a
    2-thread one, as the cohort's jobs mostly wait on Python's start."""
    folder.mkdir(parents=True, exist_ok=True)
    folder.chmod(0o755)  # munged checks its socket's folder
    for name in ("state", "spool"):
        (folder / name).mkdir(exist_ok=True)
    key = folder / "munge.key"
    key.write_bytes(secrets.token_bytes(128))
    key.chmod(0o600)
    wrote_config = unavailable_because() is None  # none there, or one a test left behind
    SYSTEM_CONFIG.parent.mkdir(parents=True, exist_ok=True)
    SYSTEM_CONFIG.write_text(slurm_conf(folder, cpus, memory_mb))
    daemons: list[subprocess.Popen] = []
    try:
        for command in (
            ["munged", "--foreground", "--force", f"--socket={folder}/munge.socket", f"--key-file={key}",
             f"--pid-file={folder}/munged.pid", f"--seed-file={folder}/munged.seed", f"--log-file={folder}/munged.log"],
            ["slurmctld", "-D", "-i"],
            ["slurmd", "-D", "-N", "localhost"],
        ):  # fmt: skip
            log = open(folder / f"{command[0]}.out", "w")
            daemons.append(subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True))
            time.sleep(0.3)  # slurmctld needs munge, slurmd needs slurmctld
        _wait_until_idle(folder, 60)
        yield Cluster(folder)
    finally:
        subprocess.run(["scancel", "--full", "--signal=KILL", "--user=root"], capture_output=True)
        for daemon in reversed(daemons):
            daemon.terminate()
            try:
                daemon.wait(timeout=10)
            except subprocess.TimeoutExpired:
                daemon.kill()
                daemon.wait()
        if wrote_config:
            SYSTEM_CONFIG.unlink(missing_ok=True)
