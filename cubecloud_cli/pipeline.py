"""`cubecloud run`: the stages in order, skipping those already complete with the same settings.

Only the stages that exist so far take part; each later stage joins the list when it lands.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

from cubecloud_cli.artifacts import is_complete, read_manifest, sha256_of_path
from cubecloud_cli.errors import CubecloudError
from cubecloud_cli.preprocess import PreprocessSettings, preprocess_scan


@dataclass(frozen=True)
class StageOutcome:
    stage: str
    status: str  # "ran" or "skipped"
    seconds: float


def _differences(recorded: dict, requested: dict) -> list[str]:
    # A JSON round trip makes tuples lists, as they are in the manifest.
    requested = json.loads(json.dumps(requested))
    keys = sorted(set(recorded) | set(requested))
    return [f"{k}: {recorded.get(k)!r} -> {requested.get(k)!r}" for k in keys if recorded.get(k) != requested.get(k)]


def stage_is_current(stage_dir: Path, params: dict, input_paths: list[Path]) -> bool:
    """True when ``stage_dir`` is complete, made with ``params``, from these very inputs.

    A complete stage made otherwise raises: silently redoing it would discard work, silently
    keeping it would mix settings.
    """
    if not is_complete(stage_dir):
        return False
    manifest = read_manifest(stage_dir)
    changes = _differences(manifest.get("params", {}), params)
    recorded_hashes = set(manifest.get("inputs", {}).values())
    if any(sha256_of_path(p) not in recorded_hashes for p in input_paths):
        changes.append("the input scan differs")
    if changes:
        raise CubecloudError(
            f"{stage_dir} was made with other settings ({'; '.join(changes)}): pass --force to "
            f"redo it, or choose another -o"
        )
    return True


def _preprocess_quietly(scan: Path, work: Path, settings: PreprocessSettings, force: bool) -> dict:
    return preprocess_scan(scan, work, settings, force=force)


def run_pipeline(
    scan: Path,
    work: Path,
    preprocess_settings: PreprocessSettings,
    *,
    force: bool = False,
    run_preprocess: Callable[[Path, Path, PreprocessSettings, bool], dict] | None = None,
) -> list[StageOutcome]:
    """Run the stages in order. ``run_preprocess`` lets the caller wrap the stage (progress)."""
    run_preprocess = run_preprocess or _preprocess_quietly
    outcomes = []
    work = Path(work)
    start = time.perf_counter()
    if not force and stage_is_current(work / "preprocess", asdict(preprocess_settings), [Path(scan)]):
        outcomes.append(StageOutcome("preprocess", "skipped", 0.0))
    else:
        run_preprocess(scan, work, preprocess_settings, force)
        outcomes.append(StageOutcome("preprocess", "ran", time.perf_counter() - start))
    return outcomes
