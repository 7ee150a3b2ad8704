"""`cubecloud eval`: score every splat run of a work directory, and CuNeRF, against the reference
renders of the preprocessed volume, on the held-out views; write the numbers and the pictures."""

from __future__ import annotations

import csv
import json
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from cubecloud_cli.artifacts import StageWriter, is_complete, read_manifest, sha256_of_path, to_jsonable
from cubecloud_cli.errors import CubecloudError
from cubecloud_cli.eval.figures import error_grid, line_plot_svg, write_turntable
from cubecloud_cli.eval.report import PAPER_TABLE_I, report_markdown, write_per_view_csv
from cubecloud_cli.eval.runs import (
    ScoredScene,
    SplatRun,
    find_splat_runs,
    load_run,
    load_scored_scene,
    render_views,
    turntable_cameras,
)
from cubecloud_cli.eval.scoring import score_views, summarize
from cubecloud_cli.raster.backends import rasterizer_for
from cubecloud_cli.runtime import Runtime, peak_memory_mb, reset_peak_memory

log = logging.getLogger("cubecloud")

ProgressCallback = Callable[[str, int, int, dict], None]
CUNERF_ROW, CUNERF_TRAINING_ROW = "cunerf", "cunerf-training-views"


@dataclass(frozen=True)
class EvalSettings:
    turntable_frames: int = 72  # 0: no turntables
    turntable_resolution: int = 256  # renders larger than this are shown at this size

    def validate(self) -> None:
        if self.turntable_frames < 0 or self.turntable_frames > 3600:
            raise CubecloudError(f"--turntable-frames {self.turntable_frames} must be between 0 (none) and 3600, e.g. 72")
        if not 16 <= self.turntable_resolution <= 4096:
            raise CubecloudError(f"--turntable-resolution {self.turntable_resolution} must be between 16 and 4096 pixels")


def protocol_description(scored: ScoredScene | None) -> dict:
    reference = ("renders of the preprocessed volume (export/reference.npy), with the export's image model"
                 if scored is None or scored.reference_kind == "volume" else
                 "the scene's own images (it has no reference.npy: a foreign COLMAP scene)")
    return {
        "name": "cubecloud held-out views v1",
        "reference": reference,
        "views": "the scene's held-out test views (split.json: every 8th view of the orbit), never trained on",
        "metrics": "DESIGN §5: PSNR with data range 1, SSIM (Gaussian window σ = 1.5, 11 taps, no sample-covariance "
                   "correction, as scikit-image), MSE on [0, 1]; per view, then mean and population std over views",
        "foreground": "the *_foreground scores count only pixels where the reference is non-zero",
        "rows": "each splat run; `cunerf`: CuNeRF's own renders of the same views; `cunerf-training-views`: CuNeRF's "
                "renders of the training views against the reference, the error baked into 3DGS's targets",
        "non-finite values": "written as the strings \"inf\" and \"nan\" (identical images have infinite PSNR)",
        "image_model": json.dumps(scored.export_manifest.get("image_model")) if scored and scored.export_manifest else "unknown",
    }


def _score_row(reference: np.ndarray, estimate: np.ndarray, names: list[str], row: str, method: str,
               per_view: list[dict]) -> dict:
    scores = score_views(reference, estimate)
    per_view += [{"row": row, "method": method, "view": name, **score} for name, score in zip(names, scores)]
    return {"method_name": method, **summarize(scores), "view_names": names}


def _cunerf_rows(work: Path, scored: ScoredScene, per_view: list[dict]) -> dict[str, dict]:
    scene, export = scored.scene, scored.export_manifest or {}
    images = scene.images.numpy().mean(axis=-1)
    rows = {}
    cunerf_dir = work / "cunerf"
    cunerf = read_manifest(cunerf_dir) if is_complete(cunerf_dir) else {}
    timings = export.get("timings_s", {})
    views = max(1, len(scene.names))
    extra = {
        "ms_per_frame": 1000.0 * timings["render_images"] / views if "render_images" in timings else None,
        "train_seconds": cunerf.get("timings_s", {}).get("total"),
        "size_mb": (cunerf_dir / "model.pt").stat().st_size / 1e6 if (cunerf_dir / "model.pt").is_file() else None,
        "render_source": export.get("render_source"),
    }
    for row, method, views_of in ((CUNERF_ROW, "CuNeRF renders (held-out views)", scene.test),
                                  (CUNERF_TRAINING_ROW, "CuNeRF renders = 3DGS targets (training views)", scene.train)):
        names = [scene.names[i] for i in views_of]
        rows[row] = {**_score_row(scored.reference[views_of], images[views_of], names, row, method, per_view), **extra}
    return rows


def _training_curve(run: SplatRun) -> tuple[list[float], list[float]]:
    path = run.directory / "log.csv"
    iterations, psnrs = [], []
    if path.is_file():
        with open(path, newline="") as handle:
            for row in csv.DictReader(handle):
                try:
                    value = float(row.get("test_psnr") or "nan")
                except ValueError:
                    continue
                if math.isfinite(value):
                    iterations.append(float(row["iteration"]))
                    psnrs.append(value)
    return iterations, psnrs


def _scene_directory(work: Path, manifest: dict) -> Path:
    """The scene a run trained on: this work directory's own export when its images are the ones
    the run recorded (so a copied or moved work directory scores against its own files), else the
    directory the manifest names."""
    own = work / "export" / "images.npy"
    recorded_hash = manifest.get("inputs", {}).get("export/images.npy")
    if recorded_hash and own.is_file() and sha256_of_path(own) == recorded_hash:
        return own.parent.resolve()
    return Path(manifest.get("scene", {}).get("directory", work / "export")).resolve()


def evaluate_work(
    work: Path,
    settings: EvalSettings = EvalSettings(),
    force: bool = False,
    runtime: Runtime = Runtime(),
    on_progress: ProgressCallback = lambda phase, done, total, fields: None,
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
            runs = [load_run(work, folder) for folder in folders]
            scenes: dict[Path, ScoredScene] = {}
            for run in runs:
                directory = _scene_directory(work, run.manifest)
                run.manifest["scene"]["resolved"] = directory
                if directory not in scenes:
                    scenes[directory] = load_scored_scene(directory, run.gaussians.channels)
                writer.add_input(run.directory / "point_cloud.ply", f"{run.name}/point_cloud.ply")
            main_scene = scenes.get((work / "export").resolve()) or next(iter(scenes.values()))
        frames_per_run = len(main_scene.scene.test) + settings.turntable_frames
        total, done = len(runs) * frames_per_run, 0
        results: dict[str, dict] = {}
        per_view: list[dict] = []
        renders_by_view: dict[str, dict[str, np.ndarray]] = {}

        def tick() -> None:
            nonlocal done
            done += 1
            on_progress("render", done, total, {})

        with writer.phase("score"):
            for run in runs:
                scored = scenes[run.manifest["scene"]["resolved"]]
                test, names = scored.scene.test, [scored.scene.names[i] for i in scored.scene.test]
                renders, ms = render_views(run.gaussians, scored.scene.cameras, test, rasterizer, tick)
                results[run.name] = {
                    **_score_row(scored.reference[test], renders, names, run.name, run.method, per_view),
                    "ms_per_frame": ms, "fps": 1000.0 / ms if ms > 0 else None, "gaussians": len(run.gaussians),
                    "size_mb": run.size_mb, "train_seconds": run.manifest.get("timings_s", {}).get("train"),
                    "iterations": run.manifest.get("metrics", {}).get("iterations"), "rasterizer": rasterizer.description,
                    "reference": scored.reference_kind,
                }
                if scored is main_scene:
                    for name, render in zip(names, renders):
                        renders_by_view.setdefault(name, {})[run.name] = render
            if main_scene.reference_kind == "volume" and main_scene.scene.directory == (work / "export").resolve():
                results.update(_cunerf_rows(work, main_scene, per_view))
                images = main_scene.scene.images.numpy().mean(axis=-1)
                for index in main_scene.scene.test:
                    renders_by_view.setdefault(main_scene.scene.names[index], {})[CUNERF_ROW] = images[index]
        pictures: dict[str, list[str]] = {"views": [], "turntables": [], "curves": []}
        with writer.phase("pictures"):
            (writer.directory / "views").mkdir(exist_ok=True)
            for index in main_scene.scene.test:
                name = main_scene.scene.names[index]
                if name in renders_by_view:
                    relative = f"views/{Path(name).stem}.png"
                    error_grid(main_scene.reference[index], renders_by_view[name], f"held-out view {name}").save(writer.directory / relative)
                    pictures["views"].append(relative)
            if settings.turntable_frames:
                for run in runs:
                    scored = scenes[run.manifest["scene"]["resolved"]]
                    cameras = turntable_cameras(scored, settings.turntable_frames, settings.turntable_resolution)
                    frames, _ = render_views(run.gaussians, cameras, list(range(len(cameras.rotations))), rasterizer, tick)
                    relative = f"turntable_{run.name}.gif"
                    write_turntable(writer.directory / relative, frames)
                    pictures["turntables"].append(relative)
            curves = [(run.name, *_training_curve(run)) for run in runs]
            if any(xs for _, xs, _ in curves):
                (writer.directory / "psnr_vs_iteration.svg").write_text(line_plot_svg(
                    curves, "test PSNR during training (against the training images)", "iteration", "PSNR (dB)"))
                pictures["curves"].append("psnr_vs_iteration.svg")
        protocol = protocol_description(main_scene)
        metrics = {"protocol": protocol, "results": results, "paper": PAPER_TABLE_I}
        (writer.directory / "metrics.json").write_text(json.dumps(to_jsonable(metrics), indent=2, allow_nan=False) + "\n")
        write_per_view_csv(writer.directory / "per_view.csv", per_view)
        (writer.directory / "report.md").write_text(report_markdown(f"cubecloud eval: {work}", protocol, results, pictures))
        writer.metrics.update({row: {k: result.get(k) for k in ("psnr", "ssim", "mse")} for row, result in results.items()})
        writer.metrics.update(peak_memory_mb(device))
        writer.extra["rasterizer"] = rasterizer.description
    return read_manifest(work / "eval")
