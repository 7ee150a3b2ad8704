"""The rows of eval's tables: each run's and CuNeRF's scores on the held-out views, the novel-view
cells, the training curve, and the protocol that metrics.json names beside them."""

from __future__ import annotations

import csv
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cubecloud_cli.cameras.novel import headline_views
from cubecloud_cli.core.artifacts import is_complete, read_manifest, sha256_of_file, verify_recorded
from cubecloud_cli.core.errors import CubecloudError
from cubecloud_cli.eval.novel_scores import annotate, pictured_views, summarize_novel, view_angles
from cubecloud_cli.eval.runs import (
    ScoredScene,
    SplatRun,
    render_views,
)
from cubecloud_cli.eval.scoring import score_views, summarize

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


def score_row(
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


def cunerf_rows(work: Path, scored: ScoredScene, per_view: list[dict]) -> dict[str, dict]:
    scene, export = scored.scene, scored.export_manifest or {}
    images = scene.images.numpy().mean(axis=-1)
    cunerf_dir = work / "cunerf"
    cunerf = read_manifest(cunerf_dir) if is_complete(cunerf_dir) else {}
    model = cunerf_dir / "model.pt"
    if cunerf and model.is_file():  # its rows quote the stage's manifest: only while the model is the one it wrote
        verify_recorded(model, sha256_of_file(model), f"cubecloud cunerf {work} --force")
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
            **score_row(
                scored.reference[views_of], images[views_of], names, row, method, per_view, scene.directory, "volume"
            ),
            **extra,
        }
    return rows


def score_novel(
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


def training_curve(run: SplatRun) -> tuple[list[float], list[float]]:
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


def picture_name(view_name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in Path(view_name).with_suffix("").as_posix())


def _headline(test) -> tuple[list[float], list[int]]:
    """The headline magnifications (0.75–1.33×) and the storage index of each of their views."""
    count = len(test.views.directions)
    headline = list(headline_views(test.views).magnifications)
    return headline, [test.views.magnifications.index(m) * count + d for m in headline for d in range(count)]


def _headline_renders(run: SplatRun, drawn, test, headline: list[float], rasterizer, tick, what: str) -> np.ndarray:
    count = len(test.views.directions)
    renders = np.concatenate(
        [
            render_views(drawn, test.views.cameras(m), list(range(count)), rasterizer, tick, run.antialias)[0]
            for m in headline
        ]
    )
    if not np.isfinite(renders).all():
        raise CubecloudError(f"{run.name} renders NaN or Inf {what}: retrain it with `{run.retrain}`")
    return renders


def score_fixed_opacity(run: SplatRun, baked, scored: ScoredScene, rasterizer, tick, result: dict) -> None:
    """A chord-length scalar scene as a viewer with one opacity per Gaussian draws it (its PLY's
    reference columns: any splat viewer but `view` and `share`), at the headline novel views, into
    ``result["novel_fixed_opacity"]``: what that approximation costs beside ``novel``."""
    test = scored.novel
    headline, storage = _headline(test)
    renders = _headline_renders(run, baked, test, headline, rasterizer, tick, "from its PLY's reference columns")
    result["novel_fixed_opacity"] = summarize(score_views(test.reference[storage], renders))


@dataclass(frozen=True)
class HeldOutPicture:
    """One novel view under a held-out transfer function: the volume's reference and the render."""

    view: str  # the novel view's name
    reference: np.ndarray  # (H, W)
    render: np.ndarray  # (H, W)


def score_held_out_transfers(
    run: SplatRun, scalar, scored: ScoredScene, rasterizer, tick, per_view: list[dict], result: dict
) -> dict[str, HeldOutPicture]:
    """Draw a scalar scene under each transfer function it never trained under and score it at
    the headline novel views (0.75–1.33×) against the volume's references under that transfer
    function; the summaries go into ``result["held_out_transfers"]`` by name. Returns, by name,
    the first of the report's pictured views among them (from above, 1×) for the report to picture."""
    test = scored.novel
    headline, storage = _headline(test)
    count = len(test.views.directions)
    angles = view_angles(test, scored.scene.cameras.centres()[scored.scene.train])
    shown = [storage.index(index) for _, index in pictured_views(test) if index in storage]
    pictured = shown[0] if shown else 0
    view_name = test.views.entries()[storage[pictured]][0]
    summaries, pictures = {}, {}
    for held in test.held_out:
        drawn = scalar.drawn_as(held.function)
        renders = _headline_renders(run, drawn, test, headline, rasterizer, tick, f"under {held.name}")
        all_rows = annotate([{}] * len(test.views.entries()), test, angles)
        references = held.reference[held.views_at(headline, count)]
        rows = [{**all_rows[index], **scores} for index, scores in zip(storage, score_views(references, renders))]
        pictures[held.name] = HeldOutPicture(view_name, references[pictured], renders[pictured])
        per_view += [
            {
                "row": run.name,
                "method": run.method,
                "set": f"novel, held-out transfer function {held.name}",
                "scene": str(scored.scene.directory),
                "against": "volume, pixel area",
                **row,
            }
            for row in rows
        ]
        summaries[held.name] = {
            "transfer": held.function.as_dict(),
            **summarize(rows),
        }
    result["held_out_transfers"] = summaries
    if test.not_scored:
        result["held_out_not_scored"] = dict(test.not_scored)
    return pictures
