"""The novel-view test's references (docs/design.md §2): renders of the preprocessed volume at views no
camera setup trains on, each pixel the mean over its area.

A splat is a continuous image, and a pixel of a real camera integrates light over its area; a
reference that samples each pixel's centre only would alias when the view zooms out, and score
a correct anti-aliased splat as wrong. So every reference pixel averages a k × k grid of
sub-pixel rays (:data:`cubecloud_cli.cameras.novel.SUPERSAMPLING`), rendered as k² images each
through one sub-pixel point of every pixel: the same rays as one image k times larger, in half
the time on a CPU (smaller, more coherent batches).

WORK/export/novel/ holds
  views.json          the directions, poses, magnifications and focal lengths (NovelViewSet.as_json)
  reference.npy       float32 (V, H, W), magnification-major, in the order of views.json's "views"
  contact_sheet.png   every novel reference, for people
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import torch

from cubecloud_cli.cameras.novel import SUPERSAMPLING, NovelViewSet
from cubecloud_cli.export.finished_views import ExportProgress
from cubecloud_cli.export.images import write_contact_sheet
from cubecloud_cli.render import ImageModel, render_view
from cubecloud_cli.scene import write_json

NOVEL_DIR = "novel"
VIEWS_FILE = "views.json"
REFERENCE_FILE = "reference.npy"


def subpixel_points(factor: int) -> list[tuple[float, float]]:
    """The centres of a factor × factor grid over a pixel, in fractions of a pixel."""
    return [((i + 0.5) / factor, (j + 0.5) / factor) for j in range(factor) for i in range(factor)]


def pixel_area_render(
    field, cameras, index: int, model: ImageModel, support, device: torch.device, factor: int
) -> np.ndarray:
    """(H, W) view ``index`` with each pixel the mean of factor × factor sub-pixel samples."""
    total = np.zeros((cameras.height, cameras.width), dtype=np.float64)
    for point in subpixel_points(factor):
        total += render_view(field, cameras, index, model, support, device, subpixel=point).cpu().numpy()
    return (total / (factor * factor)).astype(np.float32)


def render_novel_references(
    field,
    novel: NovelViewSet,
    model: ImageModel,
    device: torch.device,
    progress: ExportProgress,
    on_progress: Callable[[int, int], None],
) -> np.ndarray:
    """(V, H, W) pixel-area renders of ``field`` at every novel view, saving each as it is done
    and reusing the ones an interrupted run saved."""
    count = len(novel.directions)
    images = np.empty((len(novel), novel.resolution, novel.resolution), dtype=np.float32)
    support = None
    done = 0
    with torch.no_grad():
        for group, magnification in enumerate(novel.magnifications):
            cameras = novel.cameras(magnification)
            for direction in range(count):
                index = group * count + direction
                name = f"novel_view_{index:05d}"
                saved = progress.load(name)
                if saved is not None and saved.shape == images.shape[1:]:
                    images[index] = saved
                else:
                    if support is None and model.kind != "slice":
                        support = field.support(model.support_threshold)
                    images[index] = pixel_area_render(field, cameras, direction, model, support, device, SUPERSAMPLING)
                    progress.save(name, images[index])
                done += 1
                on_progress(done, len(novel))
    return images


def write_novel(directory: Path, novel: NovelViewSet, reference: np.ndarray) -> None:
    folder = directory / NOVEL_DIR
    folder.mkdir(parents=True, exist_ok=True)
    write_json(folder / VIEWS_FILE, novel.as_json())
    np.save(folder / REFERENCE_FILE, reference)
    write_contact_sheet(
        reference,
        folder / "contact_sheet.png",
        set(),
        f"novel views (rows of {len(novel.directions)} directions at "
        f"{', '.join(f'{m:g}x' for m in novel.magnifications)}), reference renders",
        columns=len(novel.directions),
    )
