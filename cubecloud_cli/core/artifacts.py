"""Stage directories in a work directory: manifests, atomic writes, refusals.

Every stage (`preprocess`, `cunerf`, `export`, `splat`, `eval`) writes its files through
:class:`StageWriter`, and reads the stage before it through :func:`require_stage`. The rules
(docs/design.md §1):

* A stage directory is complete only when its ``manifest.json`` exists.
* Files are written into a hidden sibling ``WORK/.NAME.partial/`` and renamed into place at the
  end, so an interrupted run never leaves a half-written directory that looks complete.
* A complete stage is replaced only with ``force=True``; the old one is moved aside first and
  deleted only after the new one is in place.
"""

from __future__ import annotations

import csv
import datetime as _dt
import hashlib
import json
import os
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from cubecloud_cli import __version__
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.stage_lock import StageLock

MANIFEST_NAME = "manifest.json"
PARTIAL_SUFFIX = ".partial"

# What to run to create each stage; used in the messages that name the fix.
STAGE_COMMANDS = {
    "preprocess": "cubecloud preprocess SCAN -o {work}",
    "cunerf": "cubecloud cunerf {work}",
    "export": "cubecloud export {work}",
    "splat": "cubecloud splat {work}",
    "eval": "cubecloud eval {work}",
}


def sha256_of_file(path: Path, chunk_bytes: int = 1 << 22) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(chunk_bytes):
            digest.update(block)
    return digest.hexdigest()


def sha256_of_path(path: Path) -> str:
    """sha256 of a file, or of a folder's files (names and bytes, in sorted order)."""
    if path.is_file():
        return sha256_of_file(path)
    digest = hashlib.sha256()
    for child in sorted(p for p in path.rglob("*") if p.is_file()):
        digest.update(str(child.relative_to(path)).encode())
        digest.update(sha256_of_file(child).encode())
    return digest.hexdigest()


def stage_dir_name(stage: str, name: str | None = None) -> str:
    """``splat`` + ``random`` -> ``splat-random`` (runs of one stage side by side)."""
    if name is None or name == "":
        return stage
    if not all(c.isalnum() or c in "-_" for c in name):
        raise CubecloudError(f"--name {name!r} may hold only letters, digits, '-' and '_'; pick a simpler name")
    return f"{stage}-{name}"


def partial_dir(work: Path, folder: str) -> Path:
    """Where stage folder ``folder`` is written before it is renamed into place (``WORK/.NAME.partial``)."""
    return Path(work) / f".{folder}{PARTIAL_SUFFIX}"


def to_jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        return to_jsonable(value.item())  # a numpy NaN still becomes "nan"
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not np.isfinite(value):
        # JSON has no inf/nan; strings keep the file parseable by every reader.
        return "inf" if value > 0 else "-inf" if value < 0 else "nan"
    return value


def read_manifest(stage_dir: Path, fix: str = "rerun the stage with --force") -> dict[str, Any]:
    """A stage's manifest as a dict, or a one-line error ending in ``fix`` (what remakes it)."""
    path = stage_dir / MANIFEST_NAME
    try:
        manifest = json.loads(path.read_text())
    except FileNotFoundError:
        raise CubecloudError(f"{stage_dir} is incomplete: it has no {MANIFEST_NAME}") from None
    except (OSError, ValueError) as exc:
        raise CubecloudError(f"{path} is unreadable ({exc}): {fix} to rebuild it") from None
    if not isinstance(manifest, dict):
        kind = {list: "an array", str: "a string", bool: "a boolean", type(None): "null"}.get(
            type(manifest), "a number"
        )
        raise CubecloudError(f"{path} is damaged (JSON {kind}, not an object): {fix} to rebuild it")
    return manifest


def is_complete(stage_dir: Path) -> bool:
    return (stage_dir / MANIFEST_NAME).is_file()


def require_stage(work: Path, stage: str, name: str | None = None) -> dict[str, Any]:
    """The manifest of a complete input stage, or a one-line error that names the fix.

    Also checks that every file the manifest lists is still there with its recorded size, so a
    stage whose files were deleted or truncated by hand is caught before it is read.
    """
    directory = Path(work) / stage_dir_name(stage, name)
    fix = STAGE_COMMANDS.get(stage, f"cubecloud {stage} {{work}}").format(work=work)
    if not directory.is_dir():
        raise CubecloudError(f"{directory} does not exist: run `{fix}` first")
    if not is_complete(directory):
        raise CubecloudError(
            f"{directory} is incomplete (no {MANIFEST_NAME}; an earlier run was interrupted): run `{fix} --force`"
        )
    manifest = read_manifest(directory, f"run `{fix} --force`")
    verify_stage_files(directory, manifest, f"{fix} --force")
    return manifest


def verify_recorded(path: Path, digest: str, fix: str) -> None:
    """``digest``, just taken of ``path``, against the sha256 that the manifest of the stage folder
    holding it records: a file changed in place keeps its size, not its hash. A file that no
    manifest lists (a foreign scene's) passes."""
    path = Path(path)
    stage_dir = next((folder for folder in path.parents if (folder / MANIFEST_NAME).is_file()), None)
    if stage_dir is None:
        return
    recorded = read_manifest(stage_dir).get("files", {}).get(str(path.relative_to(stage_dir)), {})
    if isinstance(recorded, dict) and recorded.get("sha256") not in (None, digest):
        raise CubecloudError(
            f"{path} changed since its stage wrote it (its sha256 is not the one in {stage_dir / MANIFEST_NAME}): "
            f"run `{fix}`"
        )


def verify_stage_files(directory: Path, manifest: dict[str, Any], fix: str) -> None:
    """Every file the manifest lists is still there with its recorded size, or a one-line error
    that names ``fix``."""
    for relative, info in manifest.get("files", {}).items():
        path = Path(directory) / relative
        if not path.is_file() or path.stat().st_size != info.get("bytes"):
            raise CubecloudError(f"{path} is missing or changed since the stage was written: run `{fix}`")


@dataclass
class StageWriter:
    """Writes one stage directory atomically.

    Use as a context manager; write files into :attr:`directory`, record inputs, phases and
    metrics, and the directory is renamed into place with its manifest on a clean exit. On an
    exception the partial directory is removed, unless ``keep_partial`` is set (stages that
    resume from checkpoints keep it).
    """

    work: Path
    stage: str
    params: Mapping[str, Any]
    force: bool = False
    name: str | None = None
    keep_partial: bool = False
    # Files or folders that only serve an unfinished run (checkpoints, finished views): never
    # listed in the manifest, and deleted only once the stage is in place, so a failure up to
    # then can still resume.
    transient: tuple[str, ...] = ()
    inputs: dict[str, str] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.work = Path(self.work)
        self.final_dir = self.work / stage_dir_name(self.stage, self.name)
        self.directory = partial_dir(self.work, self.final_dir.name)
        self._lock = StageLock(self.work, self.final_dir.name)
        self._started = 0.0

    def check_can_start(self) -> None:
        """Refuse early, before any expensive work, when the result could not be kept."""
        if self.work.exists() and not self.work.is_dir():
            raise CubecloudError(f"{self.work} is a file, not a work directory: pick another -o")
        self._sweep_interrupted_cleanup()
        if self.final_dir.exists() and not self.force:
            if is_complete(self.final_dir):
                raise CubecloudError(
                    f"{self.final_dir} is already complete: pass --force to redo it, or write to another work directory"
                )
            raise CubecloudError(f"{self.final_dir} exists but has no {MANIFEST_NAME}: pass --force to replace it")

    def _sweep_interrupted_cleanup(self) -> None:
        """Finish the cleanup of a commit that was interrupted after its rename: transient files
        left in the complete stage, and the previous stage moved aside."""
        if is_complete(self.final_dir):
            for name in self.transient:
                path = self.final_dir / name
                if path.is_dir():
                    shutil.rmtree(path, ignore_errors=True)
                elif path.exists():
                    path.unlink()
        if self.work.is_dir():
            for old in self.work.glob(f".{self.final_dir.name}.old-*"):
                shutil.rmtree(old, ignore_errors=True)

    def __enter__(self) -> "StageWriter":
        if self.work.exists() and not self.work.is_dir():
            raise CubecloudError(f"{self.work} is a file, not a work directory: pick another -o")
        self._created_work = not self.work.exists()
        try:
            self.work.mkdir(parents=True, exist_ok=True)
            self._lock.acquire()  # before anything of the stage is looked at or touched
            try:
                self.check_can_start()
                if self.directory.exists() and not self.keep_partial:
                    shutil.rmtree(self.directory)
                self.directory.mkdir(exist_ok=True)
            except BaseException:
                self._let_go()
                raise
        except OSError as exc:
            raise CubecloudError(f"cannot write in {self.work} ({exc.strerror}): pick a writable -o") from None
        self._started = time.perf_counter()
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            try:
                self._commit()
            finally:
                self._let_go()
            return
        if not self.keep_partial or not any(self.directory.iterdir()):
            # Keep a partial directory only when it holds something to resume from.
            shutil.rmtree(self.directory, ignore_errors=True)
        self._let_go()

    def _let_go(self) -> None:
        """Release the stage's lock; a failed first run then leaves no trace of its work directory."""
        self._lock.release()
        if self._created_work and self.work.is_dir() and not any(self.work.iterdir()):
            self.work.rmdir()

    def add_input(
        self, path: Path, label: str | None = None, digest: str | None = None, remake: str | None = None
    ) -> str:
        """Record the sha256 of a file or folder that the stage read (``digest``: already taken);
        with ``remake``, the command that rebuilds it, also check it against the sha256 its own
        stage recorded (``verify_recorded``)."""
        digest = digest or sha256_of_path(Path(path))
        self.inputs[label or str(path)] = digest
        if remake is not None:
            verify_recorded(path, digest, remake)
        return digest

    @contextmanager
    def phase(self, label: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.timings[label] = round(self.timings.get(label, 0.0) + time.perf_counter() - start, 4)

    def _list_files(self) -> dict[str, dict[str, Any]]:
        files = {}
        for path in sorted(p for p in self.directory.rglob("*") if p.is_file()):
            relative = str(path.relative_to(self.directory))
            if relative == MANIFEST_NAME or any(relative == t or relative.startswith(f"{t}/") for t in self.transient):
                continue
            files[relative] = {"bytes": path.stat().st_size, "sha256": sha256_of_file(path)}
        return files

    def _commit(self) -> None:
        with self.phase("hash_outputs"):
            files = self._list_files()
        self.timings["total"] = round(time.perf_counter() - self._started, 4)
        manifest = {
            "stage": self.stage,
            "name": self.name,
            "cubecloud_version": __version__,
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "params": dict(self.params),
            "inputs": self.inputs,
            "files": files,
            "timings_s": self.timings,
            "metrics": self.metrics,
            **self.extra,
        }
        manifest_path = self.directory / MANIFEST_NAME
        temporary = manifest_path.with_suffix(".json.tmp")
        temporary.write_text(json.dumps(to_jsonable(manifest), indent=2, allow_nan=False) + "\n")
        os.replace(temporary, manifest_path)

        # Move the old complete stage aside before the new one takes its place, and delete it
        # only afterwards: a crash in between loses nothing.
        backup = None
        if self.final_dir.exists():
            backup = self.work / f".{self.final_dir.name}.old-{os.getpid()}"
            os.replace(self.final_dir, backup)
        os.replace(self.directory, self.final_dir)
        for name in self.transient:
            path = self.final_dir / name
            if path.is_dir():
                shutil.rmtree(path, ignore_errors=True)
            else:
                path.unlink(missing_ok=True)
        if backup is not None:
            shutil.rmtree(backup, ignore_errors=True)


def check_free_disk(directory: Path, needed_bytes: int) -> None:
    """Refuse before writing when the disk cannot hold the stage (with 10% slack)."""
    directory = Path(directory)
    probe = directory
    while not probe.exists():
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if free < needed_bytes * 1.1:
        raise CubecloudError(
            f"not enough disk space in {directory}: {needed_bytes / 1e9:.2f} GB needed, "
            f"{free / 1e9:.2f} GB free; free some space or choose a smaller --size"
        )


def write_csv_log(path: Path, columns: tuple[str, ...], rows: list[dict]) -> None:
    """A training log: one row per entry, floats to 6 significant digits, missing cells empty."""
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
