"""How every stage reports progress: one callback shape, free of any terminal concern.

``on_progress(phase, done, total, fields)``: the stage is in ``phase``, ``done`` of ``total``
units of work are finished (iterations, views, frames, or expected seconds where the work has
no natural count), and ``fields`` holds live figures such as the loss or a PSNR. A new
``total`` starts a new count. The command line draws it (cubecloud_cli/cli/progress_bar.py).
"""

from __future__ import annotations

from typing import Mapping, Protocol

ProgressFields = Mapping[str, "float | str"]


class ProgressCallback(Protocol):
    def __call__(self, phase: str, done: float, total: float, fields: ProgressFields) -> None: ...


def no_progress(phase: str, done: float, total: float, fields: ProgressFields) -> None:
    """The default callback of every stage: report nothing."""
