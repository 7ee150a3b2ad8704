"""Writing a stage's files when the disk may be full, a file-size limit set, or the folder
read-only: a failed write is one line that names the file and the cause (docs/design.md §1), and
a checkpoint is replaced whole or not at all, so ``--resume`` never trusts a truncated one.

numpy reports a short write as ``OSError("N requested and M written")`` with no file name, and
torch's writer as a RuntimeError ("unexpected pos", "file write failed"); both are turned into
:class:`WriteFailed` here, where the path is known.
"""

from __future__ import annotations

import errno
import os
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from cubecloud_cli.core.errors import CubecloudError

# What to do about each cause of a failed write; then run the command again.
FIXES = {
    errno.ENOSPC: "free disk space",
    errno.EDQUOT: "free space within your disk quota",
    errno.EFBIG: "lift the file-size limit (`ulimit -f unlimited`)",
    errno.EACCES: "make the folder writable, or choose another -o",
    errno.EPERM: "make the folder writable, or choose another -o",
    errno.EROFS: "choose a folder on a writable disk with -o",
}
SHORT_WRITE_FIX = "free disk space or lift the file-size limit"  # numpy's and torch's writers say no more


def fix_for(error: BaseException) -> str:
    return f"{FIXES.get(getattr(error, 'errno', None), SHORT_WRITE_FIX)}, then run the command again"


# torch's zip writer says these when the file it writes cannot grow.
TORCH_WRITE_FAILURES = ("unexpected pos", "file write failed", "PytorchStreamWriter failed")


class WriteFailed(CubecloudError):
    """A file of a stage could not be written."""

    def __init__(self, path: Path, error: BaseException):
        super().__init__(f"cannot write {path} ({describe(error)}): {fix_for(error)}")
        self.path = Path(path)


def describe(error: BaseException) -> str:
    """The cause of a failed write in a few words: the errno's text, else the error's own."""
    number = getattr(error, "errno", None)
    if number in errno.errorcode and getattr(error, "strerror", None):
        return f"{error.strerror}, {errno.errorcode[number]}"
    if isinstance(error, RuntimeError):
        return "torch could not write it whole"  # its own text is an assertion of its zip writer
    return str(error).splitlines()[0][:120] if str(error) else type(error).__name__


def is_write_failure(error: BaseException) -> bool:
    if isinstance(error, OSError):
        return True
    return isinstance(error, RuntimeError) and any(text in str(error) for text in TORCH_WRITE_FAILURES)


@contextmanager
def writing(path: Path) -> Iterator[None]:
    """Turn a failed write of ``path`` inside the block into :class:`WriteFailed`."""
    try:
        yield
    except WriteFailed:
        raise
    except (OSError, RuntimeError) as error:
        if not is_write_failure(error):
            raise
        raise WriteFailed(path, error) from None


def write_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """``write(temporary)`` then rename it to ``path``: ``path`` is the old file or the new one,
    never half of one, and a failed write leaves no temporary file behind."""
    path = Path(path)
    temporary = path.with_name(f".{path.name}.tmp")
    try:
        with writing(path):
            write(temporary)
            os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def save_array(path: Path, array) -> None:
    """``np.save`` with a failed write named (no temporary: the file lies in a stage's partial folder)."""
    import numpy as np  # here: the command line imports this module for its messages alone

    with writing(path):
        np.save(path, array)


def write_bytes(path: Path, data: bytes) -> None:
    """``data`` to ``path``, a failed write named."""
    with writing(path):
        Path(path).write_bytes(data)


def save_picture(image, path: Path) -> None:
    """A PIL image, encoded in memory first (its format from the suffix) so that a failed write is
    one named error, not a half-closed encoder complaining at exit."""
    import io

    buffer = io.BytesIO()
    image.save(buffer, format=picture_format(path))
    write_bytes(path, buffer.getvalue())


def picture_format(path: Path) -> str:
    return {".png": "PNG", ".gif": "GIF", ".jpg": "JPEG", ".jpeg": "JPEG"}.get(Path(path).suffix.lower(), "PNG")
