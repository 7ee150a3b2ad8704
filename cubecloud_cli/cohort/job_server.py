"""The cohort's job server on this machine: one process that imports cubecloud (torch, numba and the
stages) once and forks a child for each job that job_client.py hands it, so that a job does not
spend 2–3 s starting Python and importing torch. Thirty jobs of five scans paid that 30 times.
The studies in examples/ (table_one.py, trade_study.py) start their stages through it too.

What the jobs run is passed in (:class:`JobEntry`: a program's ``main`` and the modules to import
ahead), so that this module knows nothing of the command line above it; the cohort passes
cubecloud's (``cubecloud_cli/cli/cohort.py``). A forked child is the job: it takes the client's
standard streams (passed over the socket), folder and environment, runs ``main`` with the client's
arguments and sends its exit code back. The server runs nothing of
torch or numba itself, so it holds no thread pool that a fork would break, and each job sets its own
thread count as a fresh process would. If the client dies (a killed job), the child is interrupted
as Ctrl-C would: the stage saves its checkpoint and stops. The server stops when the cohort that
started it does. The socket lives in a folder only this user can enter.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Iterator

from cubecloud_cli.core.errors import CubecloudError

READY = "ready"
STARTUP_SECONDS = 120.0  # importing torch on a cold, busy machine
JOB_EXIT_SECONDS = 5.0  # a finished job's process flushing and exiting


@dataclass(frozen=True)
class JobEntry:
    """What a job server's jobs run, named by module paths because the server is a process of its
    own: ``main`` ("module:function") is called with ``sys.argv`` = [``program``, *the client's
    arguments*], and ``preload`` lists the modules the server imports once, before the first job,
    which is what each job then saves."""

    program: str
    main: str
    preload: tuple[str, ...] = ()

    def load_main(self) -> Callable[[], object]:
        module, _, function = self.main.partition(":")
        return getattr(importlib.import_module(module), function)


def _receive_request(connection: socket.socket) -> tuple[dict, list[int]]:
    data, fds, _, _ = socket.recv_fds(connection, 1 << 16, 3)
    if len(data) < 4:
        raise ValueError("a request shorter than its length")
    (length,) = struct.unpack("!I", data[:4])
    body = bytearray(data[4:])
    while len(body) < length:
        chunk = connection.recv(length - len(body))
        if not chunk:
            raise ValueError("a request cut short")
        body += chunk
    if len(fds) != 3:
        raise ValueError(f"a request with {len(fds)} streams instead of 3")
    return json.loads(bytes(body)), list(fds)


def _exit_code(exit: SystemExit) -> int:
    if exit.code is None:
        return 0
    if isinstance(exit.code, int):
        return exit.code
    print(exit.code, file=sys.stderr)
    return 1


def _interrupt_when_client_leaves(connection: socket.socket) -> None:
    """The client sends nothing after its request: end-of-stream means it has gone."""
    try:
        while connection.recv(1024):
            pass
    except OSError:
        pass
    os.kill(os.getpid(), signal.SIGINT)


def _run_job(
    entry: JobEntry, listener: socket.socket, connection: socket.socket, request: dict, fds: list[int]
) -> None:
    """In the forked child: become the job, run it, report its exit code. Never returns."""
    code = 1
    try:
        listener.close()
        for number in (signal.SIGCHLD, signal.SIGTERM, signal.SIGHUP):
            signal.signal(number, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for target, fd in zip((0, 1, 2), fds):
            os.dup2(fd, target)
            os.close(fd)
        sys.stdin = open(0, closefd=False)
        sys.stdout = open(1, "w", closefd=False, buffering=1 if os.isatty(1) else -1)
        sys.stderr = open(2, "w", closefd=False, buffering=1)
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        connection.sendall(f"pid {os.getpid()}\n".encode())
        threading.Thread(target=_interrupt_when_client_leaves, args=(connection,), daemon=True).start()
        sys.argv = [entry.program, *request["argv"]]
        main = entry.load_main()
        try:
            main()
            code = 0
        except SystemExit as exit:
            code = _exit_code(exit)
        except KeyboardInterrupt:
            code = 130
    except BaseException:
        traceback.print_exc()
    finally:
        # The client leaves once it has the code; its leaving must not interrupt this exit.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with contextlib.suppress(BaseException):
            sys.stdout.flush()
            sys.stderr.flush()
        with contextlib.suppress(BaseException):
            connection.sendall(f"exit {code}\n".encode())
        os._exit(code)


def _reap_finished_jobs(signum, frame) -> None:
    """Wait for every finished job, so that their CPU time and memory count in the server's, and
    so in the cohort's (``/usr/bin/time cubecloud cohort`` sees them)."""
    with contextlib.suppress(ChildProcessError):
        while os.waitpid(-1, os.WNOHANG)[0] > 0:
            pass


class _Stopped(Exception):
    """SIGTERM: the cohort is done with the server."""


def _stop(signum, frame) -> None:
    raise _Stopped


def _wait_for_jobs(seconds: float) -> None:
    """Reap the jobs still exiting when the cohort stops the server (their client has its exit
    code already), so that they count in the cohort's resources; a job still running is left."""
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        try:
            if os.waitpid(-1, os.WNOHANG)[0] == 0:
                time.sleep(0.02)
        except ChildProcessError:
            return


def serve(entry: JobEntry, path: str, parent: int) -> None:
    """Accept jobs at ``path`` until ``parent``, the cohort that started the server, is gone.
    ``entry.preload`` is imported first (it starts no thread: a fork would break one)."""
    for module in entry.preload:
        importlib.import_module(module)

    signal.signal(signal.SIGCHLD, _reap_finished_jobs)
    signal.signal(signal.SIGTERM, _stop)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    listener.listen(64)
    listener.settimeout(1.0)
    print(READY, flush=True)
    try:
        _accept_jobs(entry, listener, parent)
    except _Stopped:
        pass
    finally:
        _wait_for_jobs(JOB_EXIT_SECONDS)


def _accept_jobs(entry: JobEntry, listener: socket.socket, parent: int) -> None:
    while os.getppid() == parent:
        try:
            connection, _ = listener.accept()
        except socket.timeout:
            continue
        connection.settimeout(None)
        try:
            request, fds = _receive_request(connection)
        except (OSError, ValueError) as problem:
            print(f"cubecloud job server: a bad request ({problem})", file=sys.stderr, flush=True)
            connection.close()
            continue
        sys.stdout.flush()
        sys.stderr.flush()
        if os.fork() == 0:
            try:
                _run_job(entry, listener, connection, request, fds)
            finally:
                os._exit(1)  # a child never returns to the accept loop
        connection.close()
        for fd in fds:
            os.close(fd)


@contextlib.contextmanager
def job_server(entry: JobEntry) -> Iterator[list[str]]:
    """Start a job server for the calling process (a cohort, a study); yield the command prefix
    its jobs start ``entry`` with (the client and the server's socket). The server stops when the
    block ends."""
    folder = tempfile.mkdtemp(prefix="cubecloud-jobs-")  # mode 0700; short, for the socket path limit
    path = str(Path(folder) / "socket")
    server = subprocess.Popen(
        [sys.executable, "-m", "cubecloud_cli.cohort.job_server", path, str(os.getpid()), json.dumps(asdict(entry))],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        started = _wait_until_ready(server)
        if not started:
            raise CubecloudError("the cohort's job server did not start (see the lines above): run the cohort again")
        yield [sys.executable, "-m", "cubecloud_cli.cohort.job_client", path]
    finally:
        server.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            server.wait(timeout=10)
        if server.poll() is None:
            server.kill()
            server.wait()
        shutil.rmtree(folder, ignore_errors=True)


def _wait_until_ready(server: subprocess.Popen) -> bool:
    result: dict[str, str] = {}

    def read_first_line() -> None:
        result["line"] = server.stdout.readline().strip()

    reader = threading.Thread(target=read_first_line, daemon=True)
    reader.start()
    reader.join(STARTUP_SECONDS)
    return result.get("line") == READY


class JobServerOnDemand:
    """A job server that starts with the first job asking for it, so that a study with nothing
    left to run starts none: ``with JobServerOnDemand(entry) as jobs: run([*jobs.command(), ...])``."""

    def __init__(self, entry: JobEntry) -> None:
        self._entry = entry
        self._stack = contextlib.ExitStack()
        self._command: list[str] | None = None

    def command(self) -> list[str]:
        """The command prefix that starts cubecloud through the server."""
        if self._command is None:
            self._command = self._stack.enter_context(job_server(self._entry))
        return self._command

    def __enter__(self) -> JobServerOnDemand:
        return self

    def __exit__(self, *exc) -> None:
        self._stack.close()


def main() -> None:
    if len(sys.argv) != 4 or not sys.argv[2].isdigit():
        print("usage: python -m cubecloud_cli.cohort.job_server SOCKET PARENT-PID ENTRY-JSON", file=sys.stderr)
        sys.exit(2)
    values = json.loads(sys.argv[3])
    entry = JobEntry(values["program"], values["main"], tuple(values.get("preload", ())))
    with contextlib.suppress(KeyboardInterrupt):
        serve(entry, sys.argv[1], int(sys.argv[2]))


if __name__ == "__main__":
    main()
