"""`cubecloud run`: the stages in order, skipping those already complete with the same settings.

preprocess → cunerf → export → splat (Cube-Cloud initialisation) → splat-random (the paper's
baseline: the same training from random points) → eval.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

from cubecloud_cli.artifacts import PARTIAL_SUFFIX, is_complete, read_manifest, sha256_of_path
from cubecloud_cli.cunerf import CunerfSettings, Runtime, train_cunerf
from cubecloud_cli.cunerf.stage import CHECKPOINT_FILE
from cubecloud_cli.errors import CubecloudError
from cubecloud_cli.eval import EvalSettings, evaluate_work
from cubecloud_cli.eval.stage import eval_is_current
from cubecloud_cli.export import ExportSettings, export_scene
from cubecloud_cli.preprocess import PreprocessSettings, preprocess_scan
from cubecloud_cli.splat.settings import SplatSettings
from cubecloud_cli.splat.stage import CHECKPOINT_FILE as SPLAT_CHECKPOINT
from cubecloud_cli.splat.stage import train_splat


@dataclass(frozen=True)
class StageOutcome:
    stage: str
    status: str  # "ran", "resumed" or "skipped"
    seconds: float


# Parameters added after stages were first written, with the value that older manifests implied,
# so that `run` does not refuse a work directory made before they existed.
ADDED_PARAMETERS = {"cameras": "orbit", "novel_directions": 0, "antialias": False}


def _differences(recorded: dict, requested: dict) -> list[str]:
    # A JSON round trip makes tuples lists, as they are in the manifest.
    requested = json.loads(json.dumps(requested))
    recorded = {**{k: v for k, v in ADDED_PARAMETERS.items() if k in requested}, **recorded}
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
    for path in input_paths:
        if sha256_of_path(path) not in recorded_hashes:
            # The first stage reads the scan; later ones read files of the stages before them.
            changes.append("the input scan differs" if stage_dir.name == "preprocess" else f"its input {path.parent.name}/{path.name} changed")
    if changes:
        raise CubecloudError(
            f"{stage_dir} was made with other settings ({'; '.join(changes)}): pass --force to "
            f"redo it, or choose another -o"
        )
    return True


def _preprocess_quietly(scan: Path, work: Path, settings: PreprocessSettings, force: bool) -> dict:
    return preprocess_scan(scan, work, settings, force=force)


def _cunerf_quietly(work: Path, settings: CunerfSettings, force: bool, resume: bool, runtime: Runtime) -> dict:
    return train_cunerf(work, settings, force=force, resume=resume, runtime=runtime)


def _export_quietly(work: Path, settings: ExportSettings, force: bool, runtime: Runtime) -> dict:
    return export_scene(work, settings, force=force, runtime=runtime)


def _splat_quietly(work: Path, settings: SplatSettings, force: bool, resume: bool, runtime: Runtime,
                   name: str | None = None) -> dict:
    return train_splat(work, settings, force=force, resume=resume, runtime=runtime, name=name)


def _eval_quietly(work: Path, settings: EvalSettings, force: bool, runtime: Runtime) -> dict:
    return evaluate_work(work, settings, force=force, runtime=runtime)


BASELINE_NAME = "random"


def run_pipeline(
    scan: Path,
    work: Path,
    preprocess_settings: PreprocessSettings,
    cunerf_settings: CunerfSettings,
    export_settings: ExportSettings = ExportSettings(),
    splat_settings: SplatSettings = SplatSettings(),
    *,
    force: bool = False,
    runtime: Runtime = Runtime(),
    run_preprocess: Callable[[Path, Path, PreprocessSettings, bool], dict] | None = None,
    run_cunerf: Callable[[Path, CunerfSettings, bool, bool, Runtime], dict] | None = None,
    run_export: Callable[[Path, ExportSettings, bool, Runtime], dict] | None = None,
    run_splat: Callable[..., dict] | None = None,
    eval_settings: EvalSettings = EvalSettings(),
    run_eval: Callable[[Path, EvalSettings, bool, Runtime], dict] | None = None,
    baseline: bool = True,
    on_stage: Callable[[StageOutcome], None] = lambda outcome: None,
) -> list[StageOutcome]:
    """Run the stages in order. ``run_*`` let the caller wrap a stage (progress display).

    A stage whose input was just rebuilt is rebuilt too; an interrupted cunerf run with a
    checkpoint is resumed.
    """
    run_preprocess = run_preprocess or _preprocess_quietly
    run_cunerf = run_cunerf or _cunerf_quietly
    run_export = run_export or _export_quietly
    run_splat = run_splat or _splat_quietly
    run_eval = run_eval or _eval_quietly
    outcomes: list[StageOutcome] = []

    def finish(stage: str, status: str, started: float) -> None:
        outcomes.append(StageOutcome(stage, status, 0.0 if status == "skipped" else time.perf_counter() - started))
        on_stage(outcomes[-1])

    work = Path(work)

    start = time.perf_counter()
    if not force and stage_is_current(work / "preprocess", asdict(preprocess_settings), [Path(scan)]):
        finish("preprocess", "skipped", start)
    else:
        run_preprocess(scan, work, preprocess_settings, force)
        finish("preprocess", "ran", start)
    upstream_changed = force or outcomes[-1].status == "ran"

    start = time.perf_counter()
    volume = work / "preprocess" / "volume.npy"
    if not upstream_changed and stage_is_current(work / "cunerf", cunerf_settings.as_dict(), [volume]):
        finish("cunerf", "skipped", start)
    else:
        checkpoint = work / f".cunerf{PARTIAL_SUFFIX}" / CHECKPOINT_FILE
        resume = checkpoint.is_file() and not upstream_changed
        run_cunerf(work, cunerf_settings, upstream_changed or (work / "cunerf").exists(), resume, runtime)
        finish("cunerf", "resumed" if resume else "ran", start)
    upstream_changed = upstream_changed or outcomes[-1].status != "skipped"

    start = time.perf_counter()
    export_params = {**export_settings.as_dict(), "cunerf": "cunerf"}
    export_inputs = [volume, work / "cunerf" / "model.pt"]
    if not upstream_changed and stage_is_current(work / "export", export_params, export_inputs):
        finish("export", "skipped", start)
    else:
        manifest = run_export(work, export_settings, upstream_changed or (work / "export").exists(), runtime)
        resumed = bool(manifest.get("resumed", {}).get("views"))
        finish("export", "resumed" if resumed else "ran", start)
    upstream_changed = upstream_changed or outcomes[-1].status != "skipped"

    export_changed = upstream_changed
    runs = [("splat", None, splat_settings)]
    if baseline:
        runs.append((f"splat-{BASELINE_NAME}", BASELINE_NAME, replace(splat_settings, init="random")))
    for folder, name, settings in runs:
        start = time.perf_counter()
        splat_params = {**settings.as_dict(), "scene": str(work / "export")}
        splat_inputs = [work / "export" / "images.npy", work / "export" / "points3D.ply"]
        if not export_changed and stage_is_current(work / folder, splat_params, splat_inputs):
            finish(folder, "skipped", start)
        else:
            checkpoint = work / f".{folder}{PARTIAL_SUFFIX}" / SPLAT_CHECKPOINT
            resume = checkpoint.is_file() and not export_changed
            run_splat(work, settings, export_changed or (work / folder).exists(), resume, runtime, name)
            finish(folder, "resumed" if resume else "ran", start)
        upstream_changed = upstream_changed or outcomes[-1].status != "skipped"

    start = time.perf_counter()
    # eval is cheap and holds no choices worth protecting: one made with other settings or of
    # other runs (a splat-NAME/ the user trained beside them) is simply redone, never refused.
    if not upstream_changed and eval_is_current(work, eval_settings):
        finish("eval", "skipped", start)
    else:
        run_eval(work, eval_settings, upstream_changed or (work / "eval").exists(), runtime)
        finish("eval", "ran", start)
    return outcomes
