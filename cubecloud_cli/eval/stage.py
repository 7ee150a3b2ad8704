"""`cubecloud eval`: score every splat run of a work directory, and CuNeRF, against the reference
renders of the preprocessed volume, on the held-out views; write the numbers and the pictures."""

from __future__ import annotations

import csv
import json
import logging
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.core.artifacts import StageWriter, is_complete, read_manifest, to_jsonable
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.progress import ProgressCallback, no_progress
from cubecloud_cli.core.runtime import Runtime, peak_memory_mb, reset_peak_memory
from cubecloud_cli.core.stage import Stage
from cubecloud_cli.eval.figures import error_grid, line_plot_svg, write_turntable
from cubecloud_cli.eval.novel_scores import annotate, pictured_views, summarize_novel, view_angles
from cubecloud_cli.eval.outputs import PAPER_TABLE_I, report_markdown, write_per_view_csv
from cubecloud_cli.eval.runs import (
    ScoredScene,
    SplatRun,
    file_digest,
    find_splat_runs,
    load_run,
    load_scored_scene,
    render_views,
    resolve_scene,
    turntable_cameras,
)
from cubecloud_cli.eval.scoring import score_views, summarize
from cubecloud_cli.eval.settings import EvalSettings
from cubecloud_cli.raster.backends import rasterizer_for

log = logging.getLogger("cubecloud")

CUNERF_ROW, CUNERF_TRAINING_ROW = "cunerf", "cunerf-training-views"


def protocol_description(scored: ScoredScene, foreign_rows: list[str]) -> dict:
    protocol = {
        "name": "cubecloud held-out views v1",
        "reference": (
            "renders of the preprocessed volume (export/reference.npy), with the export's image model"
            if scored.reference_kind == "volume"
            else "the scene's own images (it has no reference.npy: a foreign COLMAP scene)"
        ),
        "views": "the scene's held-out test views (split.json: every 8th view), never trained on",
        "novel views": (
            f"{len(scored.novel.views.directions)} fixed directions (from the head, from the feet, then seeded "
            f"random ones) at magnifications {', '.join(f'{m:g}' for m in scored.novel.views.magnifications)}, "
            "rendered from the volume with pixel-area references (supersampled), the same for every camera "
            "setup; cells: angle from the nearest training camera × magnification; the headline `novel PSNR` "
            "is the mean over 0.75–1.33×"
            if scored.novel is not None
            else "none: the scene has no novel-view test (an export made before it, a foreign scene, or "
            "--novel-directions 0)"
        ),
        "metrics": "docs/design.md §5: PSNR with data range 1, SSIM (Gaussian window σ = 1.5, 11 taps, no sample-covariance "
        "correction, as scikit-image), MSE on [0, 1]; per view, then mean and population std over views; "
        "colour renders are scored on their grey mean, as the references are grey",
        "foreground": "the *_foreground scores count only pixels where the reference is non-zero",
        "rows": "each splat run; `cunerf`: CuNeRF's own renders of the same views; `cunerf-training-views`: CuNeRF's "
        "renders of the training views against the reference, the error baked into 3DGS's targets",
        "timing": "splat rows: median ms per frame rendering the held-out views here; CuNeRF rows: the export's "
        "render time per view from the baked grid, as recorded when the export ran",
        "non-finite values": 'written as the strings "inf" and "nan" (identical images have infinite PSNR)',
        "image_model": json.dumps(scored.export_manifest.get("image_model")) if scored.export_manifest else "unknown",
    }
    if foreign_rows:
        protocol["other scenes"] = (
            f"{', '.join(foreign_rows)} trained on another scene and are scored on its held-out "
            "views against its own reference (column `against`): not comparable with the rows above"
        )
    return protocol


def _score_row(
    reference: np.ndarray,
    estimate: np.ndarray,
    names: list[str],
    row: str,
    method: str,
    per_view: list[dict],
    scene: Path,
    against: str,
) -> dict:
    scores = score_views(reference, estimate)
    per_view += [
        {
            "row": row,
            "method": method,
            "set": "held-out",
            "view": name,
            "scene": str(scene),
            "against": against,
            **score,
        }
        for name, score in zip(names, scores)
    ]
    return {"method_name": method, **summarize(scores), "view_names": names, "scene": str(scene), "reference": against}


def _cunerf_rows(work: Path, scored: ScoredScene, per_view: list[dict]) -> dict[str, dict]:
    scene, export = scored.scene, scored.export_manifest or {}
    images = scene.images.numpy().mean(axis=-1)
    cunerf_dir = work / "cunerf"
    cunerf = read_manifest(cunerf_dir) if is_complete(cunerf_dir) else {}
    timings = export.get("timings_s", {})
    resumed = bool(export.get("resumed", {}).get("views"))  # then only the missing views were timed
    extra = {
        "ms_per_frame": None
        if resumed or "render_images" not in timings
        else 1000.0 * timings["render_images"] / max(1, len(scene.names)),
        "train_seconds": cunerf.get("timings_s", {}).get("total"),
        "size_mb": (cunerf_dir / "model.pt").stat().st_size / 1e6 if (cunerf_dir / "model.pt").is_file() else None,
        "render_source": export.get("render_source"),
    }
    rows = {}
    for row, method, views_of in (
        (CUNERF_ROW, "CuNeRF renders (held-out views)", scene.test),
        (CUNERF_TRAINING_ROW, "CuNeRF renders = 3DGS targets (training views)", scene.train),
    ):
        names = [scene.names[i] for i in views_of]
        rows[row] = {
            **_score_row(
                scored.reference[views_of], images[views_of], names, row, method, per_view, scene.directory, "volume"
            ),
            **extra,
        }
    return rows


def _score_novel(
    run: SplatRun, gaussians, scored: ScoredScene, rasterizer, tick, per_view: list[dict], result: dict
) -> dict[int, np.ndarray]:
    """Render ``run`` at the scene's novel views, score them, put the summary into ``result`` and
    their rows into ``per_view``; returns the renders of the views the report pictures."""
    test = scored.novel
    count = len(test.views.directions)
    renders = np.concatenate(
        [
            render_views(gaussians, test.views.cameras(m), list(range(count)), rasterizer, tick, run.antialias)[0]
            for m in test.views.magnifications
        ]
    )
    if not np.isfinite(renders).all():
        raise CubecloudError(f"{run.name} renders NaN or Inf at a novel view: retrain it with `{run.retrain}`")
    angles = view_angles(test, scored.scene.cameras.centres()[scored.scene.train])
    rows = annotate(score_views(test.reference, renders), test, angles)
    per_view += [
        {
            "row": run.name,
            "method": run.method,
            "set": "novel",
            "scene": str(scored.scene.directory),
            "against": "volume, pixel area",
            **row,
        }
        for row in rows
    ]
    novel = summarize_novel(rows)
    headline = novel["headline"]
    result.update(
        {
            "novel_psnr": headline["psnr"],
            "novel_psnr_std": headline["psnr_std"],
            "novel_ssim": headline["ssim"],
            "novel_ssim_std": headline["ssim_std"],
            "novel_views": headline["views"],
            "novel": novel,
        }
    )
    return {index: renders[index] for _, index in pictured_views(test)}


def _training_curve(run: SplatRun) -> tuple[list[float], list[float]]:
    path = run.directory / "log.csv"
    iterations, psnrs = [], []
    if path.is_file():
        with open(path, newline="") as handle:
            for row in csv.DictReader(handle):
                try:
                    iteration, value = float(row.get("iteration") or "nan"), float(row.get("test_psnr") or "nan")
                except ValueError:
                    continue
                if math.isfinite(iteration) and math.isfinite(value):
                    iterations.append(iteration)
                    psnrs.append(value)
    return iterations, psnrs


def _picture_name(view_name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in Path(view_name).with_suffix("").as_posix())


def eval_is_current(work: Path, settings: EvalSettings | None = None) -> bool:
    """``work/eval`` is complete, of the runs there are now, made from their present files (and,
    given ``settings``, with them)."""
    directory = Path(work) / "eval"
    if not is_complete(directory):
        return False
    try:
        manifest = read_manifest(directory)
    except CubecloudError:  # an unreadable eval is simply not current: it is redone
        return False
    runs = find_splat_runs(work, report=False)  # the evaluation that may follow reports them
    if manifest.get("params", {}).get("runs") != runs:
        return False
    if settings is not None and any(manifest["params"].get(k) != v for k, v in asdict(settings).items()):
        return False
    recorded = manifest.get("inputs", {})
    return all(
        (Path(work) / run / "point_cloud.ply").is_file()
        and recorded.get(f"{run}/point_cloud.ply") == file_digest(Path(work) / run / "point_cloud.ply")
        for run in runs
    )


@dataclass(frozen=True)
class EvalStage(Stage):
    """The eval stage of a pipeline, after the stages in ``upstream`` (docs/design.md §1). eval is
    cheap and holds no choices worth protecting: one made with other settings or of other runs
    (a splat-NAME/ the user trained beside them) is not current, and simply redone, never refused."""

    work: Path
    settings: EvalSettings
    runtime: Runtime = Runtime()
    upstream: tuple[str, ...] = ()
    folder = "eval"

    def input_files(self) -> list[Path]:
        return [self.work / run / "point_cloud.ply" for run in find_splat_runs(self.work, report=False)]

    def recorded_params(self) -> dict:
        return {**asdict(self.settings), "runs": find_splat_runs(self.work, report=False)}

    def is_current(self) -> bool:
        return eval_is_current(self.work, self.settings)

    def run(self, force: bool, resume: bool, on_progress: ProgressCallback) -> dict:
        return evaluate_work(self.work, self.settings, force=force, runtime=self.runtime, on_progress=on_progress)


@dataclass
class LoadedRuns:
    """The runs to score, each with the scene it is scored on, and the work directory's own scene."""

    runs: list[SplatRun]
    scene_of: dict[str, ScoredScene]
    main_scene: ScoredScene
    own_export: Path
    turntables: dict[str, PinholeCameras | None]

    def frames(self) -> int:
        """Renders to make: each run's held-out views, novel views and turntable."""
        total = 0
        for run in self.runs:
            scored, turntable = self.scene_of[run.name], self.turntables[run.name]
            total += len(scored.scene.test) + (len(turntable) if turntable else 0)
            total += len(scored.novel.views) if scored.novel else 0
        return total


@dataclass
class Scores:
    """What scoring found: a row per run (and CuNeRF), per-view rows, and the renders the report pictures."""

    results: dict[str, dict] = field(default_factory=dict)
    per_view: list[dict] = field(default_factory=list)
    renders_by_view: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # held-out view -> row -> render
    novel_renders: dict[int, dict[str, np.ndarray]] = field(
        default_factory=dict
    )  # pictured novel view -> run -> render
    pictures: dict[str, list[str]] = field(
        default_factory=lambda: {"views": [], "novel": [], "turntables": [], "curves": []}
    )


def evaluate_work(
    work: Path,
    settings: EvalSettings = EvalSettings(),
    force: bool = False,
    runtime: Runtime = Runtime(),
    on_progress: ProgressCallback = no_progress,
) -> dict:
    work = Path(work)
    settings.validate()
    if not work.is_dir():
        raise CubecloudError(f"{work} is not a work directory: run `cubecloud run -o {work}` first")
    folders = find_splat_runs(work)
    if not folders:
        raise CubecloudError(f"{work} has no trained splat run: run `cubecloud splat {work}` first")
    device = runtime.apply()
    rasterizer = rasterizer_for(device)
    reset_peak_memory(device)
    writer = StageWriter(work, "eval", {**asdict(settings), "runs": folders}, force=force)
    writer.check_can_start()
    with writer:
        with writer.phase("load"):
            loaded = _load_runs(work, folders, settings, writer)
        total, done = loaded.frames(), 0

        def tick() -> None:
            nonlocal done
            done += 1
            on_progress("render", done, total, {})

        scores = Scores()
        with writer.phase("score"):
            for run in loaded.runs:
                _score_run(run, loaded, rasterizer, device, tick, scores, writer.directory)
            _score_cunerf(work, loaded, scores)
        with writer.phase("pictures"):
            _draw_pictures(loaded, scores, writer.directory)
        _write_report(work, loaded, scores, writer)
        writer.metrics.update(peak_memory_mb(device))
        writer.extra["rasterizer"] = rasterizer.description
    return read_manifest(work / "eval")


def _load_runs(work: Path, folders: list[str], settings: EvalSettings, writer: StageWriter) -> LoadedRuns:
    """Each run and its scene (loaded once however many runs share it), recording the runs' files as inputs."""
    runs = [load_run(work, folder) for folder in folders]
    scenes: dict[Path, ScoredScene] = {}
    scene_of = {}
    for run in runs:
        directory = resolve_scene(work, run)
        if directory not in scenes:
            channels = int(run.manifest.get("params", {}).get("channels", 1))
            scenes[directory] = load_scored_scene(directory, channels)
        scene_of[run.name] = scenes[directory]
        writer.add_input(run.directory / "point_cloud.ply", f"{run.name}/point_cloud.ply")
    own_export = (work / "export").resolve()
    main_scene = scenes.get(own_export) or scene_of[runs[0].name]
    turntables = {
        run.name: turntable_cameras(scene_of[run.name], settings.turntable_frames, settings.turntable_resolution)
        if settings.turntable_frames
        else None
        for run in runs
    }
    return LoadedRuns(runs, scene_of, main_scene, own_export, turntables)


def _score_run(
    run: SplatRun, loaded: LoadedRuns, rasterizer, device: torch.device, tick, scores: Scores, directory: Path
) -> None:
    """Score one run on its held-out and novel views, and render its turntable, on ``device``."""
    scored = loaded.scene_of[run.name]
    test, names = scored.scene.test, [scored.scene.names[i] for i in scored.scene.test]
    gaussians = run.gaussians().to(device)
    renders, ms = render_views(gaussians, scored.scene.cameras, test, rasterizer, tick, run.antialias)
    if not np.isfinite(renders).all():
        raise CubecloudError(
            f"{run.name} renders NaN or Inf (its point_cloud.ply holds non-finite values): "
            f"retrain it with `{run.retrain}`"
        )
    result = scores.results[run.name] = {
        **_score_row(
            scored.reference[test],
            renders,
            names,
            run.name,
            run.method,
            scores.per_view,
            scored.scene.directory,
            scored.reference_kind,
        ),
        "ms_per_frame": ms,
        "fps": 1000.0 / ms if ms > 0 else None,
        "gaussians": len(gaussians),
        "size_mb": run.size_mb,
        "train_seconds": run.manifest.get("timings_s", {}).get("train"),
        "iterations": run.manifest.get("metrics", {}).get("iterations"),
        "rasterizer": rasterizer.description,
    }
    if scored.novel is not None:
        pictured = _score_novel(run, gaussians, scored, rasterizer, tick, scores.per_view, result)
        if scored is loaded.main_scene:
            for index, render in pictured.items():
                scores.novel_renders.setdefault(index, {})[run.name] = render
    if scored is loaded.main_scene:
        for name, render in zip(names, renders):
            scores.renders_by_view.setdefault(name, {})[run.name] = render
    turntable = loaded.turntables[run.name]
    if turntable is not None:
        frames, _ = render_views(gaussians, turntable, list(range(len(turntable))), rasterizer, tick, run.antialias)
        relative = f"turntable_{run.name}.gif"
        write_turntable(directory / relative, frames)
        scores.pictures["turntables"].append(relative)


def _score_cunerf(work: Path, loaded: LoadedRuns, scores: Scores) -> None:
    """The CuNeRF rows, when the runs trained on this work directory's own export with its reference renders."""
    main = loaded.main_scene
    if main.reference_kind != "volume" or main.scene.directory.resolve() != loaded.own_export:
        log.warning(
            f"no CuNeRF rows: {loaded.own_export} is not the scene the runs trained on, or has no reference renders"
        )
        return
    scores.results.update(_cunerf_rows(work, main, scores.per_view))
    images = main.scene.images.numpy().mean(axis=-1)
    for index in main.scene.test:
        scores.renders_by_view.setdefault(main.scene.names[index], {})[CUNERF_ROW] = images[index]


def _draw_pictures(loaded: LoadedRuns, scores: Scores, directory: Path) -> None:
    """Reference | render | error grids of the held-out and pictured novel views, and the training curves."""
    main, pictures = loaded.main_scene, scores.pictures
    (directory / "views").mkdir(exist_ok=True)
    for index in main.scene.test:
        name = main.scene.names[index]
        if name in scores.renders_by_view:
            relative = f"views/{_picture_name(name)}.png"
            error_grid(main.reference[index], scores.renders_by_view[name], f"held-out view {name}").save(
                directory / relative
            )
            pictures["views"].append(relative)
    if main.novel is not None:
        for label, index in pictured_views(main.novel):
            if index in scores.novel_renders:
                name = main.novel.views.entries()[index][0]
                relative = f"views/{name}.png"
                error_grid(
                    main.novel.reference[index], scores.novel_renders[index], f"novel view {name}: {label}"
                ).save(directory / relative)
                pictures["novel"].append(relative)
    curves = [(run.name, *_training_curve(run)) for run in loaded.runs]
    if any(xs for _, xs, _ in curves):
        (directory / "psnr_vs_iteration.svg").write_text(
            line_plot_svg(curves, "test PSNR during training (against the training images)", "iteration", "PSNR (dB)")
        )
        pictures["curves"].append("psnr_vs_iteration.svg")


def _write_report(work: Path, loaded: LoadedRuns, scores: Scores, writer: StageWriter) -> None:
    """metrics.json, per_view.csv and report.md, and the headline scores into the manifest."""
    foreign = [run.name for run in loaded.runs if loaded.scene_of[run.name] is not loaded.main_scene]
    protocol = protocol_description(loaded.main_scene, foreign)
    metrics = {"protocol": protocol, "results": scores.results, "paper": PAPER_TABLE_I}
    (writer.directory / "metrics.json").write_text(json.dumps(to_jsonable(metrics), indent=2, allow_nan=False) + "\n")
    write_per_view_csv(writer.directory / "per_view.csv", scores.per_view)
    (writer.directory / "report.md").write_text(
        report_markdown(f"cubecloud eval: {work}", protocol, scores.results, scores.pictures)
    )
    writer.metrics.update(
        {
            row: {k: result.get(k) for k in ("novel_psnr", "novel_ssim", "psnr", "ssim", "mse")}
            for row, result in scores.results.items()
        }
    )
