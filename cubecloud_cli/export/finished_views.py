"""Finished work of an interrupted export, so the same command continues instead of restarting.

Everything export computes is deterministic, so a baked grid or a rendered view saved by an
interrupted run is exactly what a new run would compute, as long as the parameters and inputs are
the same: a fingerprint of both guards the reuse. The files live in
WORK/.export.partial/progress/ and are deleted once the stage is in place.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Sequence

import numpy as np

from cubecloud_cli.core.interrupts import raise_if_interrupted
from cubecloud_cli.core.writes import write_atomically

PROGRESS_DIR = "progress"
FINGERPRINT_FILE = "fingerprint.json"


class ExportProgress:
    def __init__(self, stage_partial_dir: Path, fingerprint: dict):
        self.partial = Path(stage_partial_dir)
        self.directory = self.partial / PROGRESS_DIR
        self.fingerprint = json.loads(json.dumps(fingerprint, sort_keys=True))
        # The stage's remembered_interrupt flag, while it runs: each save, once its work is safe,
        # raises a Ctrl-C that was lost.
        self.interrupt: dict | None = None

    def prepare(self) -> int:
        """Keep the saved work of a run with the same fingerprint and clear everything else in
        the partial directory; returns how many saved views there are."""
        recorded = None
        try:
            recorded = json.loads((self.directory / FINGERPRINT_FILE).read_text())
        except (OSError, ValueError):
            pass
        if self.partial.exists():
            for child in self.partial.iterdir():
                if child.name == PROGRESS_DIR and recorded == self.fingerprint:
                    continue
                shutil.rmtree(child) if child.is_dir() else child.unlink()
        self.directory.mkdir(parents=True, exist_ok=True)
        (self.directory / FINGERPRINT_FILE).write_text(json.dumps(self.fingerprint, sort_keys=True))
        return self.saved_views()

    def saved_views(self) -> int:
        if not self.directory.is_dir():
            return 0
        return sum(1 for path in self.directory.glob("*_view_*.npy") if not path.name.startswith("."))

    def _path(self, name: str) -> Path:
        return self.directory / f"{name}.npy"

    def has_work(self) -> bool:
        """Whether anything here would save time on the next run."""
        return self.saved_views() > 0 or self._path("bake").is_file()

    def load(self, name: str) -> np.ndarray | None:
        try:
            return np.load(self._path(name))
        except Exception:  # missing, empty or damaged (np.load raises several types): redo it
            return None

    def load_views(self, names: Sequence[str], shape: tuple[int, ...]) -> tuple[dict[int, np.ndarray], list[int]]:
        """The views saved under ``names`` with ``shape``, by position in ``names``, and the
        positions of those still to render."""
        saved, missing = {}, []
        for position, name in enumerate(names):
            view = self.load(name)
            if view is not None and view.shape == tuple(shape):
                saved[position] = view
            else:
                missing.append(position)
        return saved, missing

    def has(self, name: str) -> bool:
        """Whether ``name`` is saved and readable, from its header alone (a 512³ bake is 512 MB)."""
        try:
            np.load(self._path(name), mmap_mode="r")
        except Exception:  # as load's
            return False
        return True

    def save(self, name: str, array: np.ndarray) -> None:
        def write(temporary: Path) -> None:
            with open(temporary, "wb") as handle:
                np.save(handle, array)
                handle.flush()
                os.fsync(handle.fileno())  # so a power cut cannot leave an empty file under the final name

        write_atomically(self._path(name), write)
        raise_if_interrupted(self.interrupt)
