"""A cohort job's command on this machine: ``python -m cubecloud_cli.cohort.job_client SOCKET ARGS...``
runs ``cubecloud ARGS...`` in a process forked from the cohort's job server (job_server.py), which
has torch, numba and cubecloud imported already, instead of starting Python and importing them
again: 0.1 s instead of 2–3 s per job. The job gets this process's standard streams, folder and
environment; its exit code is this process's. Without a server at SOCKET (a job on another machine,
a server that has stopped) it becomes a plain ``python -m cubecloud_cli ARGS...``.

Only the standard library is imported here: the point is a start that costs nothing.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import struct
import sys

FORWARDED_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def request_bytes(argv: list[str]) -> bytes:
    """The job as the server reads it: a 4-byte length, then JSON of the arguments, folder and environment."""
    body = json.dumps({"argv": argv, "cwd": os.getcwd(), "env": dict(os.environ)}).encode()
    return struct.pack("!I", len(body)) + body


def run_plain(argv: list[str]) -> None:
    os.execv(sys.executable, [sys.executable, "-m", "cubecloud_cli", *argv])


def run_on_server(path: str, argv: list[str]) -> int:
    """The job's exit code, or 1 with a line on stderr when the job ended without one (killed)."""
    connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        connection.connect(path)
    except OSError:
        connection.close()
        run_plain(argv)  # does not return
    with connection:
        socket.send_fds(connection, [request_bytes(argv)], [0, 1, 2])
        job = {"pid": None}

        def forward(signum, frame) -> None:
            # Snakemake stops a job by signalling the process it started: this one.
            if job["pid"] is not None:
                os.kill(job["pid"], signum)

        for number in FORWARDED_SIGNALS:
            signal.signal(number, forward)
        reader = connection.makefile("r", encoding="utf-8")
        for line in reader:
            kind, _, value = line.strip().partition(" ")
            if kind == "pid":
                job["pid"] = int(value)
            elif kind == "exit":
                return int(value)
    print("error: the cohort job ended without an exit code (its process was killed)", file=sys.stderr)
    return 1


def main() -> None:
    if len(sys.argv) < 2:
        print("usage: python -m cubecloud_cli.cohort.job_client SOCKET CUBECLOUD-ARGS...", file=sys.stderr)
        sys.exit(2)
    sys.exit(run_on_server(sys.argv[1], sys.argv[2:]))


if __name__ == "__main__":
    main()
