"""`cubecloud eval`: score every splat run of a work directory, and CuNeRF, against the reference
renders of the preprocessed volume, on the held-out views; write the numbers and the pictures."""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from cubecloud_cli.cameras import PinholeCameras
from cubecloud_cli.cameras.novel import HEADLINE_MAGNIFICATIONS
from cubecloud_cli.core.artifacts import (
    StageWriter,
    is_complete,
    read_manifest,
    sha256_of_file,
    to_jsonable,
)
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.core.progress import ProgressCallback, no_progress
from cubecloud_cli.core.runtime import Runtime, peak_memory_mb, reset_peak_memory
from cubecloud_cli.core.stage import Stage
from cubecloud_cli.core.writes import save_picture
from cubecloud_cli.eval.figures import error_grid, line_plot_svg, write_turntable
from cubecloud_cli.eval.novel_scores import pictured_views
from cubecloud_cli.eval.outputs import PAPER_TABLE_I, report_markdown, write_per_view_csv
from cubecloud_cli.eval.rows import (
    CUNERF_ROW,
    HeldOutPicture,
    cunerf_rows,
    picture_name,
    protocol_description,
    score_fixed_opacity,
    score_held_out_transfers,
    score_novel,
    score_row,
    training_curve,
)
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
from cubecloud_cli.eval.settings import EvalSettings
from cubecloud_cli.raster.backends import rasterizer_for
from cubecloud_cli.splat.training_views import export_remake

log = logging.getLogger("cubecloud")


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
            if scored.novel and run.scalar:
                drawings = len(scored.novel.held_out) + run.chord_lengths  # and its fixed-opacity PLY
                total += drawings * len(scored.novel.views.directions) * len(HEADLINE_MAGNIFICATIONS)
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
    # held-out transfer function -> run -> its picture (one novel view)
    held_out_pictures: dict[str, dict[str, HeldOutPicture]] = field(default_factory=dict)
    pictures: dict[str, list[str]] = field(
        default_factory=lambda: {"views": [], "novel": [], "held_out_transfers": [], "turntables": [], "curves": []}
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
        _check_unchanged(work, loaded, writer)
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
        ply = run.directory / "point_cloud.ply"
        writer.add_input(ply, f"{run.name}/point_cloud.ply", remake=run.retrain)
    for directory in scenes:
        _check_references(directory, writer)
    own_export = (work / "export").resolve()
    main_scene = scenes.get(own_export) or scene_of[runs[0].name]
    turntables = {
        run.name: turntable_cameras(scene_of[run.name], settings.turntable_frames, settings.turntable_resolution)
        if settings.turntable_frames
        else None
        for run in runs
    }
    return LoadedRuns(runs, scene_of, main_scene, own_export, turntables)


def _check_unchanged(work: Path, loaded: LoadedRuns, writer: StageWriter) -> None:
    """Each run's Gaussians are still the ones scored: a splat run that finished while eval ran
    (`splat --force` replaces its folder whole) would otherwise leave scores of the old ones."""
    for run in loaded.runs:
        ply = run.directory / "point_cloud.ply"
        scored = writer.inputs.get(f"{run.name}/point_cloud.ply")
        now = sha256_of_file(ply) if ply.is_file() else None
        if now != scored:
            raise CubecloudError(
                f"{ply} was replaced while eval scored it (a splat run finished meanwhile): run `cubecloud eval {work}` again"
            )


def _check_references(directory: Path, writer: StageWriter) -> None:
    """The references eval scores against, hashed into its manifest and checked against what their
    export recorded (a same-size edit of one would change every score)."""
    remake = export_remake(directory)
    if remake is None:  # a foreign scene: its own images are the reference
        return
    novel = directory / "novel"
    for path in [directory / "reference.npy", *sorted(novel.glob("reference*.npy"))]:
        if path.is_file():
            writer.add_input(path, f"{directory.name}/{path.relative_to(directory)}", remake=remake)


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
        **score_row(
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
        pictured = score_novel(run, gaussians, scored, rasterizer, tick, scores.per_view, result)
        scalar = run.scalar_gaussians() if scored.novel.held_out else None
        if scalar is not None:
            held = score_held_out_transfers(run, scalar.to(device), scored, rasterizer, tick, scores.per_view, result)
            if scored is loaded.main_scene:
                for name, picture in held.items():
                    scores.held_out_pictures.setdefault(name, {})[run.name] = picture
        if run.chord_lengths:
            score_fixed_opacity(run, run.fixed_opacity_gaussians().to(device), scored, rasterizer, tick, result)
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
    scores.results.update(cunerf_rows(work, main, scores.per_view))
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
            relative = f"views/{picture_name(name)}.png"
            grid = error_grid(main.reference[index], scores.renders_by_view[name], f"held-out view {name}")
            save_picture(grid, directory / relative)
            pictures["views"].append(relative)
    if main.novel is not None:
        for label, index in pictured_views(main.novel):
            if index in scores.novel_renders:
                name = main.novel.views.entries()[index][0]
                relative = f"views/{name}.png"
                grid = error_grid(
                    main.novel.reference[index], scores.novel_renders[index], f"novel view {name}: {label}"
                )
                save_picture(grid, directory / relative)
                pictures["novel"].append(relative)
    for name, by_run in scores.held_out_pictures.items():
        first = next(iter(by_run.values()))
        relative = f"views/held_out_{picture_name(name)}.png"
        renders = {run: picture.render for run, picture in by_run.items()}
        save_picture(
            error_grid(first.reference, renders, f"held out: {name}, novel view {first.view}"), directory / relative
        )
        pictures["held_out_transfers"].append(relative)
    curves = [(run.name, *training_curve(run)) for run in loaded.runs]
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
