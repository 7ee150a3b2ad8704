"""The stage contract (docs/design.md §1): what `cubecloud run` knows of a stage, and when a
complete stage is current.

Each of the five stages (preprocess, cunerf, export, splat, eval) has a class in its
``stage.py`` that implements :class:`Stage`; the pipeline's table is a list of them and its loop
(``cubecloud_cli/pipeline/runner.py``) reads nothing else of a stage.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, Mapping, Protocol

from cubecloud_cli.core.artifacts import is_complete, read_manifest, sha256_of_path
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.progress import ProgressCallback

# Parameters added after stages were first written, with the value that older manifests implied,
# so that `run` does not refuse a work directory made before they existed.
ADDED_PARAMETERS = {
    "cameras": "orbit",
    "novel_directions": 0,
    "antialias": False,
    "grid_init": "random",
    "precision": "float32",
    "scalar": False,
    "transfer_set": 1,
    "held_out_windows": 0,
    "transfer_stride": 1,
    "lr_value": 0.0025,
    "lr_length": 0.025,
}
# Parameters recorded for provenance only: the scene a splat run read is identified by its files'
# hashes, so `-o work` and `-o /abs/work` (or a moved work directory) are the same stage.
PROVENANCE_PARAMETERS = {"scene"}


class Stage(Protocol):
    """One stage of the pipeline: the folder it writes in WORK, the folders it reads, its settings
    and how to run it. A class that subclasses this inherits ``is_current`` (its manifest records
    these settings and these inputs), ``resumed`` and ``checkpoint``."""

    work: Path
    settings: Any

    @property
    def folder(self) -> str:
        """WORK/folder, which the stage writes (``splat-random`` for a named run)."""
        ...

    @property
    def upstream(self) -> tuple[str, ...]:
        """The folders of the stages it reads: when one of them is redone, so is this one."""
        ...

    def input_files(self) -> list[Path]:
        """The files it reads, whose sha256 its manifest records."""
        ...

    def recorded_params(self) -> dict:
        """What a complete stage must have been made with to be current."""
        ...

    def run(self, force: bool, resume: bool, on_progress: ProgressCallback) -> dict:
        """Write the stage (``force``: replace a complete one; ``resume``: continue from the
        checkpoint); returns its manifest."""
        ...

    @property
    def checkpoint(self) -> Path | None:
        """Saved work of an interrupted run, which ``run(resume=True)`` continues; None for a
        stage that keeps none."""
        return None

    def is_current(self) -> bool:
        """Complete, made with these settings from these very inputs (raises when it was made
        otherwise)."""
        return stage_is_current(self.work / self.folder, self.recorded_params(), self.input_files())

    def resumed(self, manifest: Mapping[str, Any]) -> bool:
        """Whether a run that was not asked to resume reused saved work all the same."""
        return False

    def beside(self, others: int, cores: int) -> Stage | None:
        """This stage as it runs in a process of its own beside ``others`` more such stages, on
        its share of ``cores`` (it must pickle); None to run it in turn, in this process."""
        return None

    def compile_ahead(self) -> Callable[[], object] | None:
        """What this stage's run will compile, as a picklable job a helper process may run ahead
        while earlier stages leave cores idle; None: nothing worth it."""
        return None


def parameter_differences(recorded: Mapping[str, Any], requested: Mapping[str, Any]) -> list[str]:
    """``name: old -> new`` for each parameter that differs, parameters added since ``recorded``
    was written taking the value older manifests implied."""
    # A JSON round trip makes tuples lists, as they are in the manifest.
    requested = json.loads(json.dumps(requested))
    recorded = {**{k: v for k, v in ADDED_PARAMETERS.items() if k in requested}, **recorded}
    keys = sorted((set(recorded) | set(requested)) - PROVENANCE_PARAMETERS)
    return [f"{k}: {recorded.get(k)!r} -> {requested.get(k)!r}" for k in keys if recorded.get(k) != requested.get(k)]


def stage_is_current(stage_dir: Path, params: Mapping[str, Any], input_paths: list[Path]) -> bool:
    """True when ``stage_dir`` is complete, made with ``params``, from these very inputs.

    A complete stage made otherwise raises: silently redoing it would discard work, silently
    keeping it would mix settings.
    """
    if not is_complete(stage_dir):
        return False
    manifest = read_manifest(stage_dir)
    changes = parameter_differences(manifest.get("params", {}), params)
    recorded_hashes = set(manifest.get("inputs", {}).values())
    for path in input_paths:
        if sha256_of_path(path) not in recorded_hashes:
            # The first stage reads the scan; later ones read files of the stages before them.
            changes.append(
                "the input scan differs"
                if stage_dir.name == "preprocess"
                else f"its input {path.parent.name}/{path.name} changed"
            )
    if changes:
        raise CubecloudError(
            f"{stage_dir} was made with other settings ({'; '.join(changes)}): pass --force to "
            f"redo it, or choose another -o"
        )
    return True
