"""One writer per stage folder: an advisory lock on ``WORK/.NAME.lock``, held from the moment a
stage starts to write until it is in place or has failed (docs/design.md §1).

The lock is ``fcntl.flock`` on an open file, so the operating system releases it when the process
ends, however it ends (kill -9 included): a stale lock file never blocks the next run. The file
holds the holder's PID, for the message the second command prints. Where ``fcntl`` does not exist
(Windows) nothing is locked.
"""

from __future__ import annotations

import os
from pathlib import Path

from cubecloud_cli.core.errors import CubecloudError

try:
    import fcntl
except ImportError:  # Windows: no advisory locks of this kind
    fcntl = None


def lock_path(work: Path, folder: str) -> Path:
    return Path(work) / f".{folder}.lock"


class StageLock:
    """``acquire()`` takes the lock or raises a one-line CubecloudError naming the PID that holds
    it; ``release()`` gives it back and removes the file."""

    def __init__(self, work: Path, folder: str):
        self.path = lock_path(work, folder)
        self.folder = Path(work) / folder
        self._fd: int | None = None

    def acquire(self) -> None:
        if fcntl is None or self._fd is not None:
            return
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _read_pid(fd)
                os.close(fd)
                raise CubecloudError(
                    f"{self.folder} is being written by another cubecloud command (PID {holder}): "
                    "wait for it to finish, or stop it and run this one again"
                ) from None
            # The holder before us removes the file as it releases: a lock on that unlinked file
            # would not be the one the next command sees. Take the file that is there now.
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd

    def release(self) -> None:
        if self._fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)
        finally:
            os.close(self._fd)  # closing releases the lock
            self._fd = None


def _read_pid(fd: int) -> str:
    try:
        text = os.pread(fd, 32, 0).decode(errors="replace").strip()
    except OSError:
        return "unknown"
    return text if text.isdigit() else "unknown"
