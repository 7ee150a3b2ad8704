"""The cohort's job server: a job started through it behaves as `python -m cubecloud_cli` would
(its streams, folder, exit code and one-line errors, the same bits out), a killed job saves and
stops, and the server goes when its cohort goes."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

import pytest
from cli_helpers import invoke

from cubecloud_cli.cli.cohort import CUBECLOUD_JOBS
from cubecloud_cli.cohort.job_server import job_server

pytestmark = pytest.mark.slow  # runs first: pytest-xdist's workers then end together

PLAIN = [sys.executable, "-m", "cubecloud_cli"]


@pytest.fixture(scope="module")
def server_command():
    with job_server(CUBECLOUD_JOBS) as command:
        yield command


def run(command, *args, cwd=None):
    return subprocess.run([*command, *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=600)


def server_children(parent: int) -> list[int]:
    children = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == parent:
                children.append(int(entry.name))
    return children


def wait_until(condition, seconds: float = 300.0) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


# The server's jobs are compared with the CLI run in this process: a plain `python -m
# cubecloud_cli` for a light command would spend 5 s importing every stage (the client's own
# fallback to such a process is tested below).


def test_a_job_through_the_server_writes_to_the_clients_streams(server_command):
    assert server_command[2] == "cubecloud_cli.cohort.job_client" and Path(server_command[3]).is_socket()
    through_server, here = run(server_command, "--version"), invoke("--version")
    assert through_server.returncode == here.exit_code == 0
    assert through_server.stdout == here.stdout == f"cubecloud {__import__('cubecloud_cli').__version__}\n"


def test_bad_input_through_the_server_is_the_same_one_line_error(server_command, tmp_path):
    arguments = ("run", tmp_path / "nowhere.nii.gz", "-o", tmp_path / "w", "--stage", "preprocess")
    through_server, here = run(server_command, *arguments), invoke(*arguments)
    assert through_server.returncode == here.exit_code == 2
    assert through_server.stderr == here.stderr and through_server.stderr.startswith("error: ")
    assert "Traceback" not in through_server.stderr and through_server.stderr.count("\n") == 1


def test_without_a_server_the_client_runs_cubecloud_plainly(tmp_path):
    client = [sys.executable, "-m", "cubecloud_cli.cohort.job_client", str(tmp_path / "no-socket")]
    result = run(client, "run", tmp_path / "nowhere.nii.gz", "-o", tmp_path / "w", "--stage", "preprocess")
    assert result.returncode == 2 and "nowhere.nii.gz does not exist" in result.stderr


def test_stages_through_the_server_run_in_the_clients_folder_and_write_the_same_bits(server_command, tmp_path):
    """preprocess through the server; then cunerf, which trains (threads, generators), through the
    server and plainly from copies of it. (A plain preprocess would add a Python start and
    nothing the cunerf comparison does not cover.)"""
    tiny = ["--size", "32", "--cunerf-iterations", "40", "--threads", "2", "--device", "cpu", "-q"]  # bits: the CPU
    server, plain = tmp_path / "server", tmp_path / "plain"
    server.mkdir()
    result = run(server_command, "run", "-o", "work", *tiny, "--stage", "preprocess", cwd=server)  # -o relative to cwd
    assert result.returncode == 0, result.stderr
    assert (server / "work" / "preprocess" / "manifest.json").is_file()
    shutil.copytree(server, plain)
    for command, folder in ((server_command, server), (PLAIN, plain)):
        result = run(command, "run", "-o", "work", *tiny, "--stage", "cunerf", cwd=folder)
        assert result.returncode == 0, result.stderr
    assert (server / "work/cunerf/model.pt").read_bytes() == (plain / "work/cunerf/model.pt").read_bytes()


def test_a_job_whose_client_is_killed_saves_its_checkpoint_and_stops(server_command, tmp_path):
    work = tmp_path / "work"
    assert run(server_command, "run", "-o", work, "--size", "32", "--stage", "preprocess", "-q").returncode == 0
    log = open(tmp_path / "job.log", "w")
    client = subprocess.Popen(
        [*server_command, "cunerf", str(work), "--iterations", "1000000", "--checkpoint-every", "20"],
        stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    server_pid = next(pid for pid in server_children(os.getpid()) if server_command[3] in _cmdline(pid))
    checkpoint = work / ".cunerf.partial" / "checkpoint.pt"
    assert wait_until(lambda: checkpoint.is_file() and server_children(server_pid)), "the job never trained"
    jobs = server_children(server_pid)
    client.send_signal(signal.SIGKILL)  # as a scheduler would kill the job's process
    client.wait()
    assert wait_until(lambda: not any(Path(f"/proc/{pid}").exists() for pid in jobs)), "the job kept running"
    log.close()
    assert "interrupted: iteration" in (tmp_path / "job.log").read_text()
    assert not (work / "cunerf").exists()


def test_the_server_stops_when_the_cohort_that_started_it_is_gone(tmp_path):
    socket_path = tmp_path / "socket"
    starter = subprocess.run(
        [sys.executable, "-c",
         "import os, subprocess, sys\n"
         f"server = subprocess.Popen([sys.executable, '-m', 'cubecloud_cli.cohort.job_server', {str(socket_path)!r},"
         f" str(os.getpid()), {json.dumps(asdict(CUBECLOUD_JOBS))!r}], stdout=subprocess.PIPE, text=True)\n"
         "assert server.stdout.readline().strip() == 'ready'\n"
         "print(server.pid)\n"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert starter.returncode == 0, starter.stderr
    server_pid = int(starter.stdout.strip())
    assert wait_until(lambda: not _running(server_pid), 30), "the server outlived its cohort"


def _cmdline(pid) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"  # a zombie has stopped; only its parent, gone here, would reap it
